// Pass 2 of the AO (only when traced at 1/f resolution, f > 1): joint
// bilateral upsampling (seed 001 §5, Kopf et al. 2007) to full resolution.
// A pixel blends the 2×2 traced texels around it with their bilinear weights
// times how alike their surfaces are, read from the full-resolution G-buffer
// at the pixels they traced:
//
//   w = bilinear * exp(-(plane distance / tolerance)^2) * max(n_s . n, 0)^8
//
// the plane distance being |(p_s - p) . n|: zero for samples on the pixel's
// own plane however it is tilted, large across a depth discontinuity; the
// normal term rejects samples across a crease.
//
// Where the texels of the pixel's own surface hold under RETRACE_BELOW of its
// bilinear weight (a depth edge, a crease, a feature thinner than f pixels),
// the pixel is traced itself (frame.ao_sparse.w = 2, the default): the few
// texels left, or the most alike texel of another surface, stood in for it
// badly. Such pixels are the edges', a small share at full-screen sizes; they
// are queued for the retrace pass (ao_retrace.wgsl), which traces them 64 a
// workgroup, and traced here only when the queue is full.
// frame.ao_sparse.w = 1: the bilateral blend alone (a pixel no texel matches
// takes the most alike one); 0: plain bilinear upsampling, which blurs
// across edges (comparisons). Module: frame.wgsl, screen.wgsl, ao.wgsl, this.

// viewer-wasm/src/ao.rs `RETRACE_BELOW` holds the same number.
const RETRACE_BELOW: f32 = 0.25;

@group(1) @binding(0) var gbuffer_position: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_normal: texture_2d<f32>;
@group(1) @binding(2) var traced: texture_2d<f32>;
@group(1) @binding(3) var upsampled_out: texture_storage_2d<r32float, write>;
@group(1) @binding(4) var<storage, read_write> retrace: RetraceQueue;

// The pixels to trace (ao_retrace.wgsl's `RetraceList`); the frame clears
// `count` and `groups` before this pass, `groups_y` and `groups_z` stay 1.
struct RetraceQueue {
    count: atomic<u32>,
    groups: atomic<u32>,
    groups_y: u32,
    groups_z: u32,
    pixels: array<u32>,
}

// Queues `pixel` for the retrace pass; false when the queue is full.
fn queue_retrace(pixel: vec2<i32>) -> bool {
    let slot = atomicAdd(&retrace.count, 1u);
    if slot >= arrayLength(&retrace.pixels) {
        return false;
    }
    retrace.pixels[slot] = u32(pixel.x) | (u32(pixel.y) << 16u);
    // A workgroup for each 64 queued pixels: the indirect dispatch's count.
    if slot % 64u == 0u {
        atomicAdd(&retrace.groups, 1u);
    }
    return true;
}

@compute @workgroup_size(8, 8)
fn cs_upsample(@builtin(global_invocation_id) id: vec3<u32>) {
    let size = textureDimensions(upsampled_out);
    if id.x >= size.x || id.y >= size.y {
        return;
    }
    textureStore(upsampled_out, vec2<i32>(id.xy), upsample_pixel(vec2<i32>(id.xy)));
}

fn upsample_pixel(pixel: vec2<i32>) -> vec4<f32> {
    let size = vec2<i32>(textureDimensions(gbuffer_normal));
    let low = vec2<i32>(textureDimensions(traced));
    let here = load_surface(gbuffer_position, gbuffer_normal, pixel);
    let bilateral = frame.ao_sparse.w > 0.5;
    if bilateral && !here.surface {
        return vec4<f32>(1.0, 0.0, 0.0, 1.0);
    }
    let f = max(frame.ao_sparse.x, 1.0);
    // Texel t traced pixel t * f + offset: this pixel's place among the texels.
    let g = (vec2<f32>(pixel) - frame.ao_sparse.yz) / f;
    let base = vec2<i32>(floor(g));
    let t = g - floor(g);
    let tolerance = surface_tolerance(here.position);
    var sum = 0.0;
    var weight_sum = 0.0;
    var best = 1.0;
    var best_likeness = -1.0;
    for (var k = 0; k < 4; k += 1) {
        let corner = vec2<i32>(k & 1, k >> 1u);
        let texel = clamp(base + corner, vec2<i32>(0), low - vec2<i32>(1));
        let bilinear = select(1.0 - t.x, t.x, corner.x == 1) * select(1.0 - t.y, t.y, corner.y == 1);
        let v = textureLoad(traced, texel, 0).r;
        var w = bilinear;
        if bilateral {
            let s = load_surface(gbuffer_position, gbuffer_normal, traced_pixel(texel, size));
            let plane = abs(dot(s.position - here.position, here.normal)) / tolerance;
            let likeness = select(0.0, exp(-plane * plane) * pow(max(dot(s.normal, here.normal), 0.0), 8.0), s.surface);
            // A small floor on the bilinear weight: a matching texel at the far
            // corner still beats no sample at all.
            w = (bilinear + 1e-3) * likeness;
            if likeness > best_likeness {
                best_likeness = likeness;
                best = v;
            }
        }
        sum += w * v;
        weight_sum += w;
    }
    if frame.ao_sparse.w > 1.5 && weight_sum < RETRACE_BELOW && !queue_retrace(pixel) {
        return vec4<f32>(surface_visibility(here, interleaved_turn(pixel)), 0.0, 0.0, 1.0);
    }
    if weight_sum > 1e-6 {
        return vec4<f32>(sum / weight_sum, 0.0, 0.0, 1.0);
    }
    return vec4<f32>(best, 0.0, 0.0, 1.0);
}
