//! Fixtures for tests of this crate and of its users (feature `test-support`).

use crate::hierarchy::{PAGE_LEVELS, PageRef};
use crate::{
    BLOCK_SIZE, BlockEntry, FORMAT_VERSION, GridFrame, LevelInfo, Manifest, ResolutionChoice, SourceInfo,
};

/// A manifest for a synthetic scene: unit voxels at the origin, `resolution`
/// explicitly chosen, the given levels, root entry and root page.
pub fn manifest(
    name: &str,
    resolution: u32,
    levels: Vec<LevelInfo>,
    root: BlockEntry,
    root_page: Option<PageRef>,
) -> Manifest {
    Manifest {
        format_version: FORMAT_VERSION,
        name: name.into(),
        source: SourceInfo { file: name.into(), format: "obj".into(), triangles: 1, skipped_triangles: 0 },
        grid: GridFrame { origin: [0.0; 3], voxel_size: 1.0, resolution, units: None },
        block_size: BLOCK_SIZE,
        levels,
        resolution_choice: ResolutionChoice {
            mode: "explicit".into(),
            resolution,
            voxel_size: 1.0,
            median_edge: None,
            reason: "test".into(),
        },
        page_levels: PAGE_LEVELS,
        root,
        root_page,
        root_pack: None,
        root_page_pack: None,
        ao_field: None,
        bounds: None,
        page_bytes: None,
    }
}
