// Clipmap pass 2 (viewer-wasm/src/clipmap.rs): one source block's voxels
// added to (or, for a block that left, subtracted from) one level's cells,
// one invocation per voxel. A voxel of edge E in cells of edge c adds its
// prefiltered coverage as surface opacity, coverage/255 * E^3 / c^2 (spread
// over the (E/c)^3 cells of a voxel larger than a cell), clamped to 1 and in
// fixed point (4096 = 1) with integer arithmetic: `voxel_density_fixed` in
// clipmap.rs computes the same bits, and subtracting undoes adding exactly.
// Only cells inside the level's region and outside the keep box (cells a
// scroll kept) are touched.

struct Dispatch {
    // xyz: block corner (grid units), w: voxel edge E.
    block: vec4<u32>,
    // x: level, y: cell edge c (grid units), z: cells per edge N, w: 1 = subtract.
    level: vec4<u32>,
    // xyz: the level's first cell, w: the block's voxel count.
    region: vec4<i32>,
    // Cells already right: [keep_min.xyz, keep_max.xyz). keep_min.w: the
    // block's first word in voxel_words (every source block's words share it).
    keep_min: vec4<i32>,
    keep_max: vec4<i32>,
}

const DENSITY_ONE: u32 = 4096u;

@group(0) @binding(0) var<uniform> dispatch: Dispatch;
@group(0) @binding(1) var<storage, read_write> cells: array<atomic<u32>>;
// voxstream_format::PackedVoxel::pos_faces: x | y << 6 | z << 12 | faces << 18 | coverage << 24.
@group(0) @binding(2) var<storage, read> voxel_words: array<u32>;

fn voxel_density_fixed(coverage: u32, edge: u32, cell: u32) -> u32 {
    let t = min(coverage, 255u) * DENSITY_ONE;
    let e = i32(firstLeadingBit(max(edge, 1u)));
    let c = i32(firstLeadingBit(max(cell, 1u)));
    var shift = c;
    if e <= c {
        shift = 3 * e - 2 * c;
    }
    var q = 0u;
    if shift >= 8 {
        q = select(0u, DENSITY_ONE, coverage > 0u);
    } else if shift >= 0 {
        q = (t << u32(shift)) / 255u;
    } else if -shift < 24 {
        q = t / (255u << u32(-shift));
    }
    return min(q, DENSITY_ONE);
}

@compute @workgroup_size(64)
fn splat_block(@builtin(global_invocation_id) id: vec3<u32>) {
    let at = u32(dispatch.keep_min.w) + id.x;
    if id.x >= u32(dispatch.region.w) || at >= arrayLength(&voxel_words) {
        return;
    }
    let word = voxel_words[at];
    let edge = dispatch.block.w;
    let cell = dispatch.level.y;
    let q = voxel_density_fixed(word >> 24u, edge, cell);
    if q == 0u {
        return;
    }
    let local = vec3<u32>(word & 63u, (word >> 6u) & 63u, (word >> 12u) & 63u);
    let first = vec3<i32>((dispatch.block.xyz + local * edge) / cell);
    let span = i32(max(edge / cell, 1u));
    let n = i32(dispatch.level.z);
    let lo = max(first, dispatch.region.xyz);
    let hi = min(first + vec3<i32>(span), dispatch.region.xyz + vec3<i32>(n));
    let subtract = dispatch.level.w == 1u;
    // voxel_axes in clipmap.rs: the axes of its exposed faces, all three for none.
    let faces = (word >> 18u) & 63u;
    let axes = vec3<bool>((faces & 3u) != 0u, (faces & 12u) != 0u, (faces & 48u) != 0u) | vec3<bool>(faces == 0u);
    for (var z = lo.z; z < hi.z; z += 1) {
        for (var y = lo.y; y < hi.y; y += 1) {
            for (var x = lo.x; x < hi.x; x += 1) {
                let w = vec3<i32>(x, y, z);
                if all(w >= dispatch.keep_min.xyz) && all(w < dispatch.keep_max.xyz) {
                    continue;
                }
                let m = vec3<u32>((w % n + n) % n);
                // `cells` is this level's range of the cells buffer.
                let index = ((m.z * u32(n) + m.y) * u32(n) + m.x) * 3u;
                for (var a = 0u; a < 3u; a += 1u) {
                    if !axes[a] {
                        continue;
                    }
                    if subtract {
                        atomicSub(&cells[index + a], q);
                    } else {
                        atomicAdd(&cells[index + a], q);
                    }
                }
            }
        }
    }
}
