// The face arena's page table, shared by the expansion (expand.wgsl, which
// writes it) and the draw (voxel.wgsl, which reads it); each module is this
// file followed by its own (viewer-wasm/src/shaders.rs; WGSL has no includes).

// A page's entry in its chunk's page table (viewer-wasm/src/expand.rs:
// PageInfo): the block that owns the page's faces.
struct PageInfo {
    // Grid-unit position of the block's corner.
    origin: vec3<f32>,
    // Voxel edge in grid units (2^level).
    voxel_size: f32,
    // One past the block's last face in the chunk.
    face_end: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

// Faces a page of the face arena holds (viewer-wasm/src/face_arena.rs).
const PAGE_FACES: u32 = 256u;
