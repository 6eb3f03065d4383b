// Pass 1 of the AO: cone tracing (ao.wgsl) at reduced resolution. Each texel
// of the 1/f-resolution target traces the one full-resolution pixel
// `traced_pixel` names (seed 001 §1.1: sparse tracing), from the G-buffer's
// position and normal. Background texels hold 1. With f = 1 this is the
// full-resolution AO. A compute pass: on GPUs with few raster units (a
// data-centre H100 runs fragments on 2 of its 66 TPCs) a full-screen
// fragment pass is many times slower than the same work in compute.

@group(1) @binding(0) var gbuffer_position: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_normal: texture_2d<f32>;
@group(1) @binding(2) var traced_out: texture_storage_2d<r32float, write>;

@compute @workgroup_size(8, 8)
fn cs_trace(@builtin(global_invocation_id) id: vec3<u32>) {
    let low = textureDimensions(traced_out);
    if id.x >= low.x || id.y >= low.y {
        return;
    }
    textureStore(traced_out, vec2<i32>(id.xy), trace_texel(vec2<i32>(id.xy)));
}

fn trace_texel(texel: vec2<i32>) -> vec4<f32> {
    let size = vec2<i32>(textureDimensions(gbuffer_normal));
    let pixel = traced_pixel(texel, size);
    let s = load_surface(gbuffer_position, gbuffer_normal, pixel);
    if !s.surface {
        return vec4<f32>(1.0, 0.0, 0.0, 1.0);
    }
    return vec4<f32>(surface_visibility(s, interleaved_turn(texel)), 0.0, 0.0, 1.0);
}
