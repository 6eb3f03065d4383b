// Occlusion proxies (seed 003 §4): a block's bounding box, drawn after the
// frame's blocks with the depth test on, no depth write and no colour, inside
// an occlusion query. Samples that pass mean something in the box may show.
// 36 vertices per box (12 triangles), no vertex buffer.

struct Proxy {
    view_proj: mat4x4<f32>,
}

// One box: min.xyz, max.xyz in grid units (camera-relative, like the frame's matrix).
struct ProxyBox {
    min: vec4<f32>,
    max: vec4<f32>,
}

@group(0) @binding(0) var<uniform> proxy: Proxy;
@group(0) @binding(1) var<storage, read> boxes: array<ProxyBox>;

// Corner bits (x | y << 1 | z << 2) of the 12 triangles; winding is irrelevant,
// the pipeline culls nothing.
const CORNERS = array<u32, 36>(
    0u, 2u, 3u, 0u, 3u, 1u,  // -z
    4u, 5u, 7u, 4u, 7u, 6u,  // +z
    0u, 4u, 6u, 0u, 6u, 2u,  // -x
    1u, 3u, 7u, 1u, 7u, 5u,  // +x
    0u, 1u, 5u, 0u, 5u, 4u,  // -y
    2u, 6u, 7u, 2u, 7u, 3u,  // +y
);

@vertex
fn vs_proxy(@builtin(vertex_index) vertex: u32, @builtin(instance_index) instance: u32) -> @builtin(position) vec4<f32> {
    let b = boxes[instance];
    let c = CORNERS[vertex];
    let p = select(b.min.xyz, b.max.xyz, vec3<bool>((c & 1u) != 0u, (c & 2u) != 0u, (c & 4u) != 0u));
    return proxy.view_proj * vec4<f32>(p, 1.0);
}

// No output: the colour target's write mask is empty; only depth-tested samples count.
@fragment
fn fs_proxy() {}
