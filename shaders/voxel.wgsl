// Draws the face records written by expand.wgsl: 6 vertices per face, no
// vertex buffers (vertex pulling). Everything is in grid units (level-0 voxels).
// The viewer prepends frame.wgsl (the `Frame` uniform, group 0). This pass
// writes the G-buffer: position, normal and the lit colour without AO; the
// cone-traced ambient occlusion runs afterwards in its own passes
// (ao_trace.wgsl with ao.wgsl, ao_upsample, ao_temporal) and ao_composite.wgsl
// multiplies it in.

// PageInfo and PAGE_FACES: face_arena.wgsl, which comes before this file.

struct FaceRecord {
    pos_face: u32,
    normal: u32,
    // sRGB8 r | g << 8 | b << 16 | 255 << 24, or 0 when the block has no colour.
    color: u32,
}

// One chunk of the face arena. A block's draw starts at its first face
// (first_vertex = 6 x first face), so the vertex index names the face in the
// chunk, and the face's page names the block.
@group(1) @binding(0) var<storage, read> pages: array<PageInfo>;
@group(1) @binding(1) var<storage, read> faces: array<FaceRecord>;

// A block fading in or out over a level change (viewer-wasm/src/crossfade.rs).
struct FadeInfo {
    // x: share of the pixels the newcomers own (0..1), y: 1 for a newcomer, 0 for a leaver.
    value: vec4<f32>,
}

// Only fs_fade reads group 2, so the other pipelines' layouts need not have it.
@group(2) @binding(0) var<uniform> fade: FadeInfo;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) grid_pos: vec3<f32>,
    @location(1) @interpolate(flat) normal: vec3<f32>,
    @location(2) @interpolate(flat) face_normal: vec3<f32>,
    // rgb: base colour, as displayed (the canvas has no sRGB conversion).
    @location(3) @interpolate(flat) base_colour: vec3<f32>,
    // The voxel's AO field byte (1 + round(254 V); 0 = none), bits 16..24 of its normal word.
    @location(4) @interpolate(flat) field: u32,
}

// Inverse of voxstream_format::oct_encode (two snorm8 bytes, x low).
fn oct_decode(e: u32) -> vec3<f32> {
    let u = max(f32(bitcast<i32>(e << 24u) >> 24u) / 127.0, -1.0);
    let v = max(f32(bitcast<i32>(e << 16u) >> 24u) / 127.0, -1.0);
    let z = 1.0 - abs(u) - abs(v);
    let t = max(-z, 0.0);
    let x = u - t * sign(u);
    let y = v - t * sign(v);
    return normalize(vec3<f32>(x, y, z));
}

// Corner (in the face's two tangent axes) of each of the 6 vertices. Positive
// faces wind counter-clockwise seen from outside; negative faces swap the two
// tangent coordinates, which mirrors the winding.
fn face_corner(corner: u32, positive: bool) -> vec2<f32> {
    var c = vec2<f32>(0.0, 0.0);
    switch corner {
        case 1u: { c = vec2<f32>(1.0, 0.0); }
        case 2u, 4u: { c = vec2<f32>(1.0, 1.0); }
        case 5u: { c = vec2<f32>(0.0, 1.0); }
        default: { c = vec2<f32>(0.0, 0.0); }
    }
    if positive {
        return c;
    }
    return c.yx;
}

@vertex
fn vs_main(@builtin(vertex_index) vertex_index: u32) -> VertexOut {
    var out: VertexOut;
    let face_index = vertex_index / 6u;
    let block = pages[min(face_index / PAGE_FACES, arrayLength(&pages) - 1u)];
    if face_index >= arrayLength(&faces) || face_index >= block.face_end {
        // Degenerate: outside the clip volume.
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    let record = faces[face_index];
    let local = vec3<f32>(
        f32(record.pos_face & 63u),
        f32((record.pos_face >> 6u) & 63u),
        f32((record.pos_face >> 12u) & 63u),
    );
    let face = (record.pos_face >> 18u) & 7u;
    let axis = face / 2u;
    let positive = (face & 1u) == 1u;
    let uv = face_corner(vertex_index % 6u, positive);

    var offset = vec3<f32>(0.0, 0.0, 0.0);
    var normal = vec3<f32>(0.0, 0.0, 0.0);
    let side = select(-1.0, 1.0, positive);
    let plane = select(0.0, 1.0, positive);
    // The tangent axes are the two axes following `axis` cyclically, so that
    // tangent_u x tangent_v = +axis.
    if axis == 0u {
        offset = vec3<f32>(plane, uv.x, uv.y);
        normal = vec3<f32>(side, 0.0, 0.0);
    } else if axis == 1u {
        offset = vec3<f32>(uv.y, plane, uv.x);
        normal = vec3<f32>(0.0, side, 0.0);
    } else {
        offset = vec3<f32>(uv.x, uv.y, plane);
        normal = vec3<f32>(0.0, 0.0, side);
    }
    let grid_pos = block.origin + (local + offset) * block.voxel_size;
    out.clip = frame.view_proj * vec4<f32>(grid_pos, 1.0);
    out.grid_pos = grid_pos;
    out.normal = oct_decode(record.normal);
    out.field = (record.normal >> 16u) & 255u;
    out.face_normal = normal;
    let rgba = unpack4x8unorm(record.color);
    out.base_colour = select(BASE_COLOUR, rgba.rgb, rgba.a > 0.5);
    return out;
}

const BASE_COLOUR: vec3<f32> = vec3<f32>(0.86, 0.80, 0.72);

struct Shaded {
    // Lit colour, AO not applied yet (ao_composite.wgsl multiplies V in).
    colour: vec4<f32>,
    // The unit normal of the AO hemisphere.
    normal: vec3<f32>,
    // Whether `normal` is the stored normal as it is (not turned to the side we see).
    stored: bool,
}

// A stored normal more than 45 degrees past edge-on to the eye belongs to the
// surface's other side: scans' triangles disagree on their winding, and both
// sides of a triangle are surface (issue 9's definition). Nearer edge-on it
// stays, since at a small convex feature the voxel staircase shows faces a
// little past its silhouette, whose outward normals point slightly away.
const OTHER_SIDE_COS: f32 = -0.70710678;

fn shade(in: VertexOut) -> Shaded {
    let to_eye = normalize(frame.eye.xyz - in.grid_pos);
    // The stored normal is the smooth surface normal, which hides the voxel
    // staircase. Where it belongs to the side we do not see, it turns over;
    // where it points away from the face we are drawing (thin features), it
    // bends until it faces the same side as the face.
    var n = normalize(in.normal);
    var stored = true;
    if dot(n, to_eye) < OTHER_SIDE_COS {
        n = -n;
        stored = false;
    }
    let agreement = dot(n, in.face_normal);
    if agreement < 0.0 {
        n = normalize(n + in.face_normal * (0.3 - agreement));
        stored = false;
    }
    let headlight = max(dot(n, to_eye), 0.0);
    let key = max(dot(n, frame.key_light.xyz), 0.0);
    let diffuse = 0.65 * headlight + 0.35 * key;
    // Ambient and direct light are both scaled by the visibility later, with
    // no floor. Shaded voxels still never take the background colour (20, 24,
    // 36): a warm or grey base scaled by one factor keeps red >= blue, which
    // the background does not have.
    let light = 0.3 + 0.7 * diffuse;
    var out: Shaded;
    out.colour = vec4<f32>(in.base_colour * light, 1.0);
    out.normal = n;
    out.stored = stored;
    return out;
}

// Colour last: with a 16-byte-aligned f32 target first, the three fit
// WebGPU's 32 bytes of colour attachments per sample (16 + 8 + 8).
struct GBufferOut {
    // xyz: the grid position the AO is computed for, w: 1, or 2 + V where the
    // voxel carries the precomputed AO field's V.
    @location(0) position: vec4<f32>,
    // xyz: the AO hemisphere's unit normal, w: 1 (0 = background).
    @location(1) normal: vec4<f32>,
    // The lit colour without AO.
    @location(2) colour: vec4<f32>,
}

fn gbuffer(in: VertexOut) -> GBufferOut {
    let s = shade(in);
    var out: GBufferOut;
    out.colour = s.colour;
    // The field's V was computed for the stored normal; where shade() turned
    // or bent the normal (the other side, a thin sheet seen from behind) it
    // does not apply, and the trace pass cone-traces the pixel instead.
    var field_w = 1.0;
    if in.field > 0u && s.stored {
        field_w = 2.0 + f32(in.field - 1u) / 254.0;
    }
    out.position = vec4<f32>(in.grid_pos, field_w);
    out.normal = vec4<f32>(s.normal, 1.0);
    return out;
}

// The draw of every frame, in the browser and natively.
@fragment
fn fs_gbuffer(in: VertexOut) -> GBufferOut {
    return gbuffer(in);
}

// Interleaved gradient noise (Jimenez 2014): a per-pixel threshold in [0, 1)
// that is evenly spread over any small neighbourhood, so a partial screen door
// reads as a blend rather than a pattern.
fn dither(pixel: vec2<f32>) -> f32 {
    return fract(52.9829189 * fract(dot(floor(pixel), vec2<f32>(0.06711056, 0.00583715))));
}

// A block in a cross-fade: a newcomer keeps the pixels whose threshold is below
// t, a leaver the others, so each pixel shows exactly one of the two levels.
@fragment
fn fs_fade(in: VertexOut) -> GBufferOut {
    let mine = dither(in.clip.xy) < fade.value.x;
    if (mine != (fade.value.y > 0.5)) {
        discard;
    }
    return gbuffer(in);
}
