// Clipmap pass 1 (viewer-wasm/src/clipmap.rs): zeroes the cells of one level
// that are not already right. Storage slot s of a level holds the grid cell
// w = origin + ((s - origin) mod N) (toroidal addressing); slots whose cell
// lies in the keep box (the region before a scroll) keep their sums, the rest
// (newly exposed slabs, or everything on a rebuild) start from 0 before the
// splat pass adds the sources back.

struct Dispatch {
    // xyz: block corner (grid units), w: voxel edge (unused here).
    block: vec4<u32>,
    // x: level, y: cell edge (grid units), z: cells per edge N, w: 1 = subtract.
    level: vec4<u32>,
    // xyz: the level's first cell, w: voxel count (unused here).
    region: vec4<i32>,
    // Cells already right: [keep_min, keep_max).
    keep_min: vec4<i32>,
    keep_max: vec4<i32>,
}

@group(0) @binding(0) var<uniform> dispatch: Dispatch;
@group(0) @binding(1) var<storage, read_write> cells: array<u32>;

@compute @workgroup_size(64)
fn clear_cells(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = dispatch.level.z;
    if id.x >= n * n * n {
        return;
    }
    let s = vec3<i32>(vec3<u32>(id.x % n, (id.x / n) % n, id.x / (n * n)));
    let o = dispatch.region.xyz;
    let ni = i32(n);
    let w = o + ((s - o) % ni + ni) % ni;
    if all(w >= dispatch.keep_min.xyz) && all(w < dispatch.keep_max.xyz) {
        return;
    }
    // A cell's three words: its opacity along x, y and z. `cells` is this
    // level's range of the cells buffer (a binding per level: all levels
    // together pass WebGPU's 128 MiB binding limit at 6 levels of 128^3).
    let at = id.x * 3u;
    cells[at] = 0u;
    cells[at + 1u] = 0u;
    cells[at + 2u] = 0u;
}
