use serde::{Deserialize, Serialize};

use crate::{BLOCK_SIZE, BlockKey};

/// Bumped whenever a reader of an older manifest would misread a newer one.
pub const FORMAT_VERSION: u32 = 2;

/// Where the voxel grid sits in the source mesh's coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridFrame {
    /// Source-space position of grid corner (0, 0, 0), in f64 so georeferenced
    /// scans keep full precision.
    pub origin: [f64; 3],
    /// Edge of a level-0 voxel in source units.
    pub voxel_size: f64,
    /// Level-0 voxels per grid edge; a power of two.
    pub resolution: u32,
    /// Source units, when the input says (e.g. "m").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceInfo {
    pub file: String,
    pub format: String,
    pub triangles: u64,
    /// Triangles skipped as degenerate or non-finite.
    pub skipped_triangles: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelInfo {
    pub level: u8,
    /// Voxels per grid edge on this level.
    pub resolution: u32,
    pub blocks: u32,
    pub voxels: u64,
    pub bytes: u64,
}

/// Tight bounds of a block's voxels in that level's voxel coordinates;
/// `min` inclusive, `max` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoxelBounds {
    pub min: [u32; 3],
    pub max: [u32; 3],
}

impl VoxelBounds {
    /// Bounds in grid units (level-0 voxels) for a block on `level`.
    pub fn grid_units(&self, level: u8) -> ([f64; 3], [f64; 3]) {
        let s = (1u64 << level) as f64;
        (self.min.map(|v| v as f64 * s), self.max.map(|v| v as f64 * s))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlockEntry {
    pub key: BlockKey,
    pub bounds: VoxelBounds,
    pub voxels: u32,
    /// Exposed faces: what the renderer will draw for this block.
    pub faces: u32,
    /// Encoded size in bytes.
    pub bytes: u32,
    /// How far, in grid units (level-0 voxels), drawing this block's voxels
    /// can put surface away from where the level-0 voxels below them are: an
    /// upper bound on the one-sided Hausdorff distance from the block's voxel
    /// cubes to the level-0 voxels they stand for (server `lod.rs` says how it
    /// is measured). 0 on level 0; never smaller than any child block's.
    pub geometric_error: f32,
    /// blake3 of the encoded bytes, hex; the block's ETag.
    pub hash: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    pub name: String,
    pub source: SourceInfo,
    pub grid: GridFrame,
    pub block_size: u32,
    /// Finest first; the last level holds a single block covering the grid.
    pub levels: Vec<LevelInfo>,
    /// Sorted by key: coarsest level first is *not* implied; use [`Manifest::block`].
    pub blocks: Vec<BlockEntry>,
}

#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    #[error("manifest is not valid JSON for this format: {0}")]
    Json(#[from] serde_json::Error),
    #[error("manifest format version {0} is not supported (expected {FORMAT_VERSION})")]
    Version(u32),
    #[error("manifest is inconsistent: {0}")]
    Inconsistent(String),
}

impl Manifest {
    pub fn from_json(bytes: &[u8]) -> Result<Self, ManifestError> {
        let m: Manifest = serde_json::from_slice(bytes)?;
        m.validate()?;
        Ok(m)
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(self).expect("manifest serialises")
    }

    /// Checks the invariants the viewer relies on: sorted unique keys, levels
    /// contiguous from 0, power-of-two grid, blocks inside their level.
    pub fn validate(&self) -> Result<(), ManifestError> {
        let bad = |s: String| Err(ManifestError::Inconsistent(s));
        if self.format_version != FORMAT_VERSION {
            return Err(ManifestError::Version(self.format_version));
        }
        if self.block_size != BLOCK_SIZE {
            return bad(format!("block size {} is not {BLOCK_SIZE}", self.block_size));
        }
        if !self.grid.resolution.is_power_of_two() {
            return bad(format!("grid resolution {} is not a power of two", self.grid.resolution));
        }
        if !(self.grid.voxel_size.is_finite() && self.grid.voxel_size > 0.0)
            || self.grid.origin.iter().any(|o| !o.is_finite())
        {
            return bad("grid frame is not finite and positive".into());
        }
        if self.levels.is_empty() || self.levels.iter().enumerate().any(|(i, l)| l.level as usize != i) {
            return bad("levels are not numbered 0, 1, 2, …".into());
        }
        if !self.blocks.windows(2).all(|w| w[0].key < w[1].key) {
            return bad("block keys are not sorted and unique".into());
        }
        for b in &self.blocks {
            let Some(level) = self.levels.get(b.key.level as usize) else {
                return bad(format!("block {} names a missing level", b.key));
            };
            let blocks_per_edge = level.resolution.div_ceil(BLOCK_SIZE);
            if b.key.coord().iter().any(|&c| c >= blocks_per_edge) {
                return bad(format!("block {} lies outside its level", b.key));
            }
            if !(b.geometric_error.is_finite() && b.geometric_error >= 0.0) {
                return bad(format!("block {} has geometric error {}", b.key, b.geometric_error));
            }
        }
        Ok(())
    }

    pub fn coarsest_level(&self) -> u8 {
        (self.levels.len() - 1) as u8
    }

    pub fn block(&self, key: &BlockKey) -> Option<&BlockEntry> {
        self.blocks.binary_search_by(|b| b.key.cmp(key)).ok().map(|i| &self.blocks[i])
    }

    pub fn summary(&self, id: &str) -> SceneSummary {
        SceneSummary {
            id: id.to_string(),
            name: self.name.clone(),
            triangles: self.source.triangles,
            voxels: self.levels.first().map_or(0, |l| l.voxels),
            blocks: self.blocks.len() as u32,
            bytes: self.blocks.iter().map(|b| b.bytes as u64).sum(),
        }
    }
}

/// One row of `GET /api/scenes`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneSummary {
    pub id: String,
    pub name: String,
    pub triangles: u64,
    /// Level-0 voxels.
    pub voxels: u64,
    pub blocks: u32,
    pub bytes: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Manifest {
        Manifest {
            format_version: FORMAT_VERSION,
            name: "t".into(),
            source: SourceInfo {
                file: "t.obj".into(),
                format: "obj".into(),
                triangles: 1,
                skipped_triangles: 0,
            },
            grid: GridFrame { origin: [1e7, 0.0, -3.5], voxel_size: 0.01, resolution: 128, units: None },
            block_size: BLOCK_SIZE,
            levels: vec![
                LevelInfo { level: 0, resolution: 128, blocks: 1, voxels: 1, bytes: 30 },
                LevelInfo { level: 1, resolution: 64, blocks: 1, voxels: 1, bytes: 30 },
            ],
            blocks: vec![
                BlockEntry {
                    key: BlockKey::new(0, 1, 0, 0),
                    bounds: VoxelBounds { min: [64, 0, 0], max: [65, 1, 1] },
                    voxels: 1,
                    faces: 6,
                    bytes: 30,
                    hash: "x".into(),
                    geometric_error: 0.0,
                },
                BlockEntry {
                    key: BlockKey::new(1, 0, 0, 0),
                    bounds: VoxelBounds { min: [32, 0, 0], max: [33, 1, 1] },
                    voxels: 1,
                    faces: 6,
                    bytes: 30,
                    hash: "y".into(),
                    geometric_error: 1.5,
                },
            ],
        }
    }

    #[test]
    fn json_round_trip_keeps_f64_origin() {
        let m = sample();
        let back = Manifest::from_json(&m.to_json()).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.block(&BlockKey::new(1, 0, 0, 0)).unwrap().hash, "y");
        assert!(back.block(&BlockKey::new(1, 0, 0, 1)).is_none());
    }

    #[test]
    fn inconsistent_manifests_are_rejected() {
        let mut m = sample();
        m.blocks.swap(0, 1);
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.blocks[0].key = BlockKey::new(0, 2, 0, 0);
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.blocks[1].geometric_error = -1.0;
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.format_version = 99;
        assert!(matches!(Manifest::from_json(&m.to_json()), Err(ManifestError::Version(99))));
        assert!(Manifest::from_json(b"{").is_err());
    }
}
