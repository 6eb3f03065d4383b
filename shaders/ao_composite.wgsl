// Last pass: the shaded colour the voxel draw wrote (lit, AO not applied)
// times the visibility V the AO passes left, into the frame's target. The
// shading scales ambient and direct light alike by V, with no floor: a fully
// occluded crease is black. With AO off (frame.volume.w = 0) V is 1.

@group(1) @binding(0) var gbuffer_normal: texture_2d<f32>;
@group(1) @binding(1) var gbuffer_colour: texture_2d<f32>;
@group(1) @binding(2) var visibility: texture_2d<f32>;

@fragment
fn fs_composite(@builtin(position) clip: vec4<f32>) -> @location(0) vec4<f32> {
    let pixel = vec2<i32>(clip.xy);
    let colour = textureLoad(gbuffer_colour, pixel, 0);
    let surface = textureLoad(gbuffer_normal, pixel, 0).w > 0.5;
    if !surface || frame.volume.w <= 0.0 {
        return colour;
    }
    let v = clamp(textureLoad(visibility, pixel, 0).r, 0.0, 1.0);
    return vec4<f32>(colour.rgb * v, colour.a);
}
