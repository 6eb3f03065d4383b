// Helpers of the full-screen AO passes (ao_trace, ao_upsample, ao_temporal,
// ao_composite), appended after frame.wgsl to each of their modules.

// One triangle covering the viewport (vertices 0, 1, 2).
@vertex
fn vs_fullscreen(@builtin(vertex_index) vertex_index: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((vertex_index << 1u) & 2u), f32(vertex_index & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

// The full-resolution pixel that reduced-resolution texel `texel` traces:
// texel * f + this frame's offset in the f×f block, inside a `size` image.
fn traced_pixel(texel: vec2<i32>, size: vec2<i32>) -> vec2<i32> {
    let f = max(i32(frame.ao_sparse.x), 1);
    let offset = vec2<i32>(frame.ao_sparse.yz);
    return clamp(texel * f + offset, vec2<i32>(0), size - vec2<i32>(1));
}

// A pixel of the G-buffer: position (grid units) and unit normal; `surface`
// false on the background (the normal target is cleared to 0 there).
struct Surface {
    position: vec3<f32>,
    normal: vec3<f32>,
    surface: bool,
    // The voxel's precomputed AO field V (0..1), or -1 where it has none.
    field: f32,
}

fn load_surface(positions: texture_2d<f32>, normals: texture_2d<f32>, pixel: vec2<i32>) -> Surface {
    var s: Surface;
    let n = textureLoad(normals, pixel, 0);
    s.surface = n.w > 0.5 && dot(n.xyz, n.xyz) > 0.25;
    s.normal = select(vec3<f32>(0.0, 0.0, 1.0), normalize(n.xyz), s.surface);
    let p = textureLoad(positions, pixel, 0);
    s.position = p.xyz;
    // The voxel's precomputed AO field V (voxel.wgsl writes w = 2 + V), -1 = none.
    s.field = select(-1.0, clamp(p.w - 2.0, 0.0, 1.0), s.surface && p.w >= 1.5);
    return s;
}

// How far (grid units) two surface points may lie apart, across a plane or
// between frames, and still count as the same surface: one grid unit, or 1 %
// of the distance to the eye (a pixel's footprint grows with distance).
fn surface_tolerance(p: vec3<f32>) -> f32 {
    return max(1.0, 0.01 * distance(p, frame.eye.xyz));
}
