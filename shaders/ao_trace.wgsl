// Pass 1 of the AO: cone tracing (ao.wgsl) at reduced resolution. Each texel
// of the 1/f-resolution target traces the one full-resolution pixel
// `traced_pixel` names (seed 001 §1.1: sparse tracing), from the G-buffer's
// position and normal. Background texels hold 1. With f = 1 this is the
// full-resolution AO.

@group(1) @binding(0) var gbuffer_position: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_normal: texture_2d<f32>;

@fragment
fn fs_trace(@builtin(position) clip: vec4<f32>) -> @location(0) vec4<f32> {
    let size = vec2<i32>(textureDimensions(gbuffer_normal));
    let pixel = traced_pixel(vec2<i32>(clip.xy), size);
    let s = load_surface(gbuffer_position, gbuffer_normal, pixel);
    if !s.surface {
        return vec4<f32>(1.0, 0.0, 0.0, 1.0);
    }
    // The AO field mode: the voxel's precomputed V where it has one.
    if frame.ao_mode.x > 0.5 && s.field >= 0.0 && frame.volume.w > 0.0 {
        return vec4<f32>(s.field, 0.0, 0.0, 1.0);
    }
    // Interleaved sampling: each texel turns the frame's cone set further by
    // its own interleaved-gradient-noise fraction, so neighbouring texels (which
    // the upsample and the eye average) see different cone sets.
    var turn = 0.0;
    if frame.ao_temporal.w > 0.5 {
        let texel = floor(clip.xy);
        turn = fract(52.9829189 * fract(dot(texel, vec2<f32>(0.06711056, 0.00583715))));
    }
    return vec4<f32>(ambient_visibility(s.position, s.normal, turn), 0.0, 0.0, 1.0);
}
