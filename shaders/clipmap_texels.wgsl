// Clipmap pass 3 (viewer-wasm/src/clipmap.rs): copies the cells the clear and
// splat passes changed into the levels' filterable texture, which the trace
// reads (ao.wgsl, `clip_trilinear`) with one hardware-filtered sample instead
// of eight cells of three words each. Level k is the block of (N + 1)^3
// texels from depth k * (N + 1); the cell w of slot s = w mod N is texel s of
// its level's block, and along each axis where s is 0 also texel N (the
// apron: a filtered read between slot N - 1 and the next slot, 0, then stays
// in the block). A texel holds (min(o_x, 1), min(o_y, 1), min(o_z, 1),
// min(o_x + o_y + o_z, 1)), o the cell's opacity along each axis (fixed
// point, 4096 = 1): the last channel bounds what the filtered axes may add up
// to (ao.wgsl).

struct TexelDispatch {
    // xyz: the box's first cell (grid cells of the level), w: the level.
    box_min: vec4<i32>,
    // xyz: the box's size in cells, w: cells per edge N.
    box_size: vec4<u32>,
}

@group(0) @binding(0) var<uniform> dispatch: TexelDispatch;
@group(0) @binding(1) var<storage, read> cells: array<u32>;
@group(0) @binding(2) var texels: texture_storage_3d<rgba8unorm, write>;

@compute @workgroup_size(64)
fn copy_texels(@builtin(global_invocation_id) id: vec3<u32>) {
    let size = dispatch.box_size.xyz;
    if id.x >= size.x * size.y * size.z {
        return;
    }
    let local = vec3<u32>(id.x % size.x, (id.x / size.x) % size.y, id.x / (size.x * size.y));
    let n = i32(dispatch.box_size.w);
    let w = dispatch.box_min.xyz + vec3<i32>(local);
    let s = vec3<u32>(((w % n) + n) % n);
    let un = u32(n);
    // `cells` is this level's range of the cells buffer.
    let at = ((s.z * un + s.y) * un + s.x) * 3u;
    let o = min(vec3<f32>(f32(cells[at]), f32(cells[at + 1u]), f32(cells[at + 2u])) / 4096.0, vec3<f32>(1.0));
    let texel = vec4<f32>(o, min(o.x + o.y + o.z, 1.0));
    let block = vec3<u32>(0u, 0u, u32(dispatch.box_min.w) * (un + 1u));
    // Texel s, and its copies at N along each axis where s is 0.
    for (var corner = 0u; corner < 8u; corner += 1u) {
        let apron = vec3<bool>((corner & 1u) != 0u, (corner & 2u) != 0u, (corner & 4u) != 0u);
        if any(apron & (s != vec3<u32>(0u))) {
            continue;
        }
        textureStore(texels, block + select(s, vec3<u32>(un), apron), texel);
    }
}
