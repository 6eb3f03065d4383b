// Occlusion feedback (viewer-wasm/src/occlusion.rs): the farthest depth of each
// tile × tile tile of the frame's depth buffer, so the CPU maps a sixteenth of
// it and builds the rest of its max-depth pyramid from there. The farthest
// depth of a tile bounds every pixel in it, so the Hi-Z test stays conservative.

struct ReduceParams {
    // Depth buffer size in pixels, and the reduced image's size in tiles.
    size: vec2<u32>,
    out_size: vec2<u32>,
    // x: the tile edge in pixels.
    tile: vec4<u32>,
}

@group(0) @binding(0) var depth: texture_depth_2d;
@group(0) @binding(1) var<storage, read_write> farthest: array<f32>;
@group(0) @binding(2) var<uniform> params: ReduceParams;

@compute @workgroup_size(8, 8)
fn reduce_depth(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.out_size.x || id.y >= params.out_size.y) {
        return;
    }
    let tile = params.tile.x;
    let origin = id.xy * tile;
    var m = 0.0;
    for (var dy = 0u; dy < tile; dy++) {
        for (var dx = 0u; dx < tile; dx++) {
            // Edge tiles repeat the last row or column: a max is unchanged by repeats.
            let p = min(origin + vec2<u32>(dx, dy), params.size - 1u);
            m = max(m, textureLoad(depth, p, 0));
        }
    }
    farthest[id.y * params.out_size.x + id.x] = m;
}
