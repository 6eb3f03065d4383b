// GPU voxel expansion (seed 003: voxels are expanded into quads on the GPU).
// WebGPU has no geometry shaders, so one compute invocation per voxel appends
// one face record per set face bit, and the same atomic that hands out face
// slots is the vertex count of the indirect draw that follows (6 vertices per
// face, pulled from the face buffer in voxel.wgsl).

// voxstream_format::PackedVoxel: x | y << 6 | z << 12 | faces << 18 | coverage << 24,
// octahedral snorm8 normal, sRGB8 colour with alpha 255 (0 = no colour).
struct Voxel {
    pos_faces: u32,
    normal: u32,
    color: u32,
}

// One exposed face: x | y << 6 | z << 12 | face index (0..6) << 18; normal and colour as in Voxel.
struct FaceRecord {
    pos_face: u32,
    normal: u32,
    color: u32,
}

// Layout of wgpu::util::DrawIndirectArgs. The CPU initialises it to (0, 1, 0, 0).
struct DrawArgs {
    vertex_count: atomic<u32>,
    instance_count: u32,
    first_vertex: u32,
    first_instance: u32,
}

const VERTICES_PER_FACE: u32 = 6u;
const WORKGROUP_SIZE: u32 = 64u;

@group(0) @binding(0) var<storage, read> voxels: array<Voxel>;
@group(0) @binding(1) var<storage, read_write> faces: array<FaceRecord>;
@group(0) @binding(2) var<storage, read_write> draw_args: DrawArgs;

@compute @workgroup_size(WORKGROUP_SIZE)
fn expand_faces(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = id.x;
    if index >= arrayLength(&voxels) {
        return;
    }
    let voxel = voxels[index];
    let mask = (voxel.pos_faces >> 18u) & 63u;
    let count = countOneBits(mask);
    if count == 0u {
        return;
    }
    // One atomic per voxel reserves all of its faces at once.
    let first = atomicAdd(&draw_args.vertex_count, count * VERTICES_PER_FACE) / VERTICES_PER_FACE;
    let position = voxel.pos_faces & 0x3ffffu;
    let capacity = arrayLength(&faces);
    var slot = first;
    for (var face = 0u; face < 6u; face += 1u) {
        if (mask & (1u << face)) != 0u {
            // The CPU sizes the buffer from the popcount; the guard only keeps
            // a wrong size from writing out of bounds.
            if slot < capacity {
                faces[slot] = FaceRecord(position | (face << 18u), voxel.normal, voxel.color);
            }
            slot += 1u;
        }
    }
}
