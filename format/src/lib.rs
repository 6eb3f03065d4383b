//! Types shared by the voxstream server and viewer: block keys, packed voxels,
//! the block codec and the scene manifest.
//!
//! Coordinates: a scene lives on a cubic grid of `resolution` level-0 voxels per
//! edge ("grid units"). Level `l` voxels are `2^l` grid units wide. A block is a
//! cube of [`BLOCK_SIZE`]³ voxels of one level, so block `(l, c)` covers grid units
//! `[c·64·2^l, (c+1)·64·2^l)`. World position = `grid.origin + grid_units · grid.voxel_size`.
//! Keeping the GPU in grid units keeps f32 precise even for georeferenced scans.

mod codec;
pub mod hierarchy;
mod key;
mod manifest;
#[cfg(any(test, feature = "test-support"))]
pub mod test_support;
mod voxel;

pub use codec::{
    BLOCK_DEPTH, BLOCK_MAGIC, CodecError, ColumnSizes, FLAG_COLOR, FLAG_FIELD, HEADER_LEN, VoxelColumns,
    decode_block, encode_block, encode_columns, predicted_face_masks,
};
pub use hierarchy::{
    BlockLocation, FinishedHierarchy, HierarchyPage, PAGE_LEVELS, PackRange, PackRef, PageBuilder, PageError,
    PageRef, SceneIndex, load_scene_index,
};
pub use key::{BlockKey, KeyError};
pub use manifest::{
    AoFieldInfo, BlockEntry, FORMAT_VERSION, GridFrame, LevelInfo, Manifest, ManifestError, ResolutionChoice,
    SceneSummary, SourceInfo, VoxelBounds,
};
pub use voxel::{
    Block, FULL_COVERAGE, Face, PackedVoxel, coverage_from_count, demorton3, morton3, oct_decode, oct_encode,
    oct_encode_many,
};

/// Voxels per block edge (seed 003 uses 64³ blocks).
pub const BLOCK_SIZE: u32 = 64;
/// Voxels in a full block.
pub const BLOCK_VOXELS: usize = (BLOCK_SIZE * BLOCK_SIZE * BLOCK_SIZE) as usize;
/// Deepest level index a key may name; 2^31 grid units is far beyond any grid we build.
pub const MAX_LEVEL: u8 = 24;
