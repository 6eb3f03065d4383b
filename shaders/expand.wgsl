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

// Layout of wgpu::util::DrawIndirectArgs. The CPU initialises a block's to
// (0, 1, 6 x its first face, 0), in the slot of its first page.
struct DrawArgs {
    vertex_count: atomic<u32>,
    instance_count: u32,
    first_vertex: u32,
    first_instance: u32,
}

// One block of the batch (viewer-wasm/src/expand.rs: ExpandHeader), at a dynamic offset.
struct ExpandBlock {
    voxel_first: u32,
    voxel_count: u32,
    first_page: u32,
    pages: u32,
    info: PageInfo,
}

const VERTICES_PER_FACE: u32 = 6u;
const WORKGROUP_SIZE: u32 = 64u;

// The frame's whole upload buffer; the block's voxels start at `block.voxel_first`.
@group(0) @binding(0) var<storage, read> voxels: array<Voxel>;
@group(0) @binding(1) var<uniform> block: ExpandBlock;
// The chunk of the face arena the block's run of pages is in.
@group(0) @binding(2) var<storage, read_write> faces: array<FaceRecord>;
@group(0) @binding(3) var<storage, read_write> pages: array<PageInfo>;
@group(0) @binding(4) var<storage, read_write> draw_args: array<DrawArgs>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn expand_faces(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = id.x;
    if index < block.pages {
        pages[block.first_page + index] = block.info;
    }
    if index >= block.voxel_count {
        return;
    }
    let voxel = voxels[block.voxel_first + index];
    let mask = (voxel.pos_faces >> 18u) & 63u;
    let count = countOneBits(mask);
    if count == 0u {
        return;
    }
    // One atomic per voxel reserves all of its faces at once.
    let first = atomicAdd(&draw_args[block.first_page].vertex_count, count * VERTICES_PER_FACE) / VERTICES_PER_FACE;
    let position = voxel.pos_faces & 0x3ffffu;
    let base = block.first_page * PAGE_FACES;
    // The CPU sizes the run from the popcount; the guard only keeps a wrong
    // size from writing into the next block's pages.
    let capacity = block.info.face_end - base;
    var slot = first;
    for (var face = 0u; face < 6u; face += 1u) {
        if (mask & (1u << face)) != 0u {
            if slot < capacity {
                faces[base + slot] = FaceRecord(position | (face << 18u), voxel.normal, voxel.color);
            }
            slot += 1u;
        }
    }
}
