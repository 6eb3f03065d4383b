use serde::{Deserialize, Serialize};

use crate::hierarchy::{BlockLocation, PackRef, PageRef, is_content_hash, range_in_pack};
use crate::{BLOCK_SIZE, BlockKey};

/// Bumped whenever a reader of an older manifest would misread a newer one.
/// 3: the block list moved into hierarchy pages (`hierarchy.rs`).
/// 4: packs span pages; a page lists several packs (page version 3).
pub const FORMAT_VERSION: u32 = 5;

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
    /// Bit `i` set when `key.children()[i]` is stored (x | y<<1 | z<<2); 0 on level 0.
    #[serde(default)]
    pub child_mask: u8,
    /// Where the bytes are: the block's own file, or a range of a pack.
    #[serde(default)]
    pub location: BlockLocation,
}

/// How the grid resolution was chosen, for the build report and the catalog.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResolutionChoice {
    /// `auto`, `voxel-size` or `explicit`.
    pub mode: String,
    pub resolution: u32,
    /// Source units; equals `grid.voxel_size`.
    pub voxel_size: f64,
    /// The scan's median triangle edge in source units, when measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub median_edge: Option<f64>,
    /// One sentence saying why.
    pub reason: String,
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
    pub resolution_choice: ResolutionChoice,
    /// Levels each hierarchy page spans (`hierarchy::PAGE_LEVELS` when written).
    pub page_levels: u8,
    /// The coarsest level's one block.
    pub root: BlockEntry,
    /// The page listing the blocks below the root; `None` when the root is on level 0.
    pub root_page: Option<PageRef>,
    /// The pack holding the root block's bytes (`root.location.pack == 0`):
    /// the last pack the build closed (the root is the last block written).
    /// `None` when the root is its own file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_pack: Option<PackRef>,
    /// The pack holding the root page's bytes (`root_page.location.pack == 0`); `None` when the
    /// root page is its own file or there is no root page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_page_pack: Option<PackRef>,
    /// Tight bounds of the level-0 voxels, so a catalog can show the scene's extent without
    /// reading every hierarchy page. Absent in scenes built before it was written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bounds: Option<VoxelBounds>,
    /// Bytes of all hierarchy pages together (absent in older scenes, like `bounds`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub page_bytes: Option<u64>,
    /// The precomputed AO field the blocks carry (issue 9 item 2; their AO
    /// field column), with the R and λ it was computed for; `None` when the
    /// blocks have none (a scene built without it, or before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ao_field: Option<AoFieldInfo>,
}

/// How a scene's AO field was computed (`Manifest::ao_field`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AoFieldInfo {
    /// Cells per edge of the whole-grid occupancy the field was traced through.
    pub cells: u32,
    /// R in grid units (level-0 voxels).
    pub max_distance: f32,
    /// λ in w(d) = 1 / (1 + λ·d/R).
    pub falloff: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    #[error("manifest is not valid JSON for this format: {0}")]
    Json(#[from] serde_json::Error),
    #[error(
        "manifest format version {0} is not supported (expected {FORMAT_VERSION}): rebuild the scene from its mesh with `voxstream build`"
    )]
    Version(u32),
    #[error("manifest is inconsistent: {0}")]
    Inconsistent(String),
}

impl Manifest {
    pub fn from_json(bytes: &[u8]) -> Result<Self, ManifestError> {
        // The version first: an older manifest lacks fields and would otherwise fail as "missing field".
        #[derive(Deserialize)]
        struct Version {
            format_version: u32,
        }
        let v: Version = serde_json::from_slice(bytes)?;
        if v.format_version != FORMAT_VERSION {
            return Err(ManifestError::Version(v.format_version));
        }
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
        if let Some(f) = &self.ao_field {
            if !(f.cells > 0
                && f.max_distance.is_finite()
                && f.max_distance > 0.0
                && f.falloff.is_finite()
                && f.falloff >= 0.0)
            {
                return bad(format!("ao_field is invalid: {f:?}"));
            }
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
        if self.levels.last().is_some_and(|l| l.resolution > BLOCK_SIZE) {
            return bad("the coarsest level is larger than one block".into());
        }
        if !(1..=4).contains(&self.page_levels) {
            return bad(format!("page levels {} is not 1 to 4", self.page_levels));
        }
        let root = &self.root;
        if root.key != BlockKey::new(self.coarsest_level(), 0, 0, 0) {
            return bad(format!("root block {} is not the coarsest level's block", root.key));
        }
        if !(root.geometric_error.is_finite() && root.geometric_error >= 0.0) {
            return bad(format!("root block has geometric error {}", root.geometric_error));
        }
        match (&self.root_page, root.key.level) {
            (None, 0) => {}
            (Some(p), l) if l > 0 && p.root == root.key && root.child_mask != 0 => {}
            _ => return bad("the root page does not match the root block".into()),
        }
        if !root.location.is_file() {
            match &self.root_pack {
                Some(p)
                    if root.location.pack == 0
                        && is_content_hash(&p.hash)
                        && range_in_pack(root.location.offset, root.bytes, p.bytes) => {}
                _ => return bad("the root block's pack range is not in the root pack".into()),
            }
        }
        if let Some(page) = self.root_page.as_ref().filter(|p| !p.location.is_file()) {
            match &self.root_page_pack {
                Some(p)
                    if page.location.pack == 0
                        && is_content_hash(&p.hash)
                        && range_in_pack(page.location.offset, page.bytes, p.bytes) => {}
                _ => return bad("the root page's pack range is not in the root page's pack".into()),
            }
        }
        if let Some(b) = &self.bounds
            && (0..3).any(|a| b.min[a] >= b.max[a] || b.max[a] > self.grid.resolution)
        {
            return bad(format!("scene bounds {:?}..{:?} are empty or outside the grid", b.min, b.max));
        }
        if self.resolution_choice.resolution != self.grid.resolution {
            return bad("resolution choice disagrees with the grid".into());
        }
        Ok(())
    }

    /// Blocks in the scene, all levels.
    pub fn block_count(&self) -> u64 {
        self.levels.iter().map(|l| l.blocks as u64).sum()
    }

    pub fn coarsest_level(&self) -> u8 {
        (self.levels.len() - 1) as u8
    }

    pub fn summary(&self, id: &str) -> SceneSummary {
        SceneSummary {
            id: id.to_string(),
            name: self.name.clone(),
            triangles: self.source.triangles,
            voxels: self.levels.first().map_or(0, |l| l.voxels),
            blocks: self.block_count() as u32,
            bytes: self.levels.iter().map(|l| l.bytes).sum(),
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
    use crate::hierarchy::PageRef;

    pub(crate) fn entry(key: BlockKey, error: f32) -> BlockEntry {
        let base = key.coord().map(|c| c * BLOCK_SIZE);
        BlockEntry {
            key,
            bounds: VoxelBounds { min: base, max: base.map(|b| b + 1) },
            voxels: 1,
            faces: 6,
            bytes: 30,
            hash: "ab".repeat(32),
            geometric_error: error,
            child_mask: 0,
            location: Default::default(),
        }
    }

    fn sample() -> Manifest {
        let mut root = entry(BlockKey::new(1, 0, 0, 0), 1.5);
        root.child_mask = 0b10;
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
            resolution_choice: ResolutionChoice {
                mode: "explicit".into(),
                resolution: 128,
                voxel_size: 0.01,
                median_edge: None,
                reason: "asked for".into(),
            },
            page_levels: 3,
            root,
            root_page: Some(PageRef {
                root: BlockKey::new(1, 0, 0, 0),
                hash: "cd".repeat(32),
                bytes: 99,
                location: BlockLocation::FILE,
            }),
            root_pack: None,
            root_page_pack: None,
            ao_field: None,
            bounds: Some(VoxelBounds { min: [0, 0, 0], max: [1, 1, 1] }),
            page_bytes: Some(99),
        }
    }

    #[test]
    fn json_round_trip_keeps_f64_origin() {
        let m = sample();
        let back = Manifest::from_json(&m.to_json()).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.grid.origin[0], 1e7);
        // Written before `bounds` and `page_bytes` existed: still read, without them.
        let mut older: serde_json::Value = serde_json::from_slice(&m.to_json()).unwrap();
        older.as_object_mut().unwrap().retain(|k, _| k != "bounds" && k != "page_bytes");
        let back = Manifest::from_json(&serde_json::to_vec(&older).unwrap()).unwrap();
        assert_eq!((back.bounds, back.page_bytes), (None, None));
        assert_eq!(back.block_count(), 2);
    }

    #[test]
    fn inconsistent_manifests_are_rejected() {
        let mut m = sample();
        m.root.key = BlockKey::new(0, 0, 0, 0);
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.root.geometric_error = -1.0;
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.root_page = None;
        assert!(Manifest::from_json(&m.to_json()).is_err(), "a level-1 root needs its page");
        let mut m = sample();
        m.grid.resolution = 96;
        assert!(Manifest::from_json(&m.to_json()).is_err());
        let mut m = sample();
        m.bounds = Some(VoxelBounds { min: [0, 0, 0], max: [129, 1, 1] });
        assert!(Manifest::from_json(&m.to_json()).is_err(), "bounds beyond the grid");
        m.bounds = Some(VoxelBounds { min: [0, 3, 0], max: [1, 3, 1] });
        assert!(Manifest::from_json(&m.to_json()).is_err(), "empty bounds");
        let mut m = sample();
        m.format_version = 99;
        assert!(matches!(Manifest::from_json(&m.to_json()), Err(ManifestError::Version(99))));
        assert!(Manifest::from_json(b"{").is_err());
    }

    #[test]
    fn the_root_block_lies_inside_its_pack() {
        let mut m = sample();
        m.root.location = BlockLocation { pack: 0, offset: 70 };
        m.root_pack = Some(PackRef { hash: "ef".repeat(32), bytes: 100 });
        assert_eq!(Manifest::from_json(&m.to_json()).unwrap(), m, "30 bytes at 70 of 100");
        let mut past = m.clone();
        past.root.location.offset = 71;
        assert!(Manifest::from_json(&past.to_json()).is_err(), "one byte past the pack's end");
        let mut none = m.clone();
        none.root_pack = None;
        assert!(Manifest::from_json(&none.to_json()).is_err(), "a packed root needs its pack");
        let mut other = m.clone();
        other.root.location.pack = 1;
        assert!(Manifest::from_json(&other.to_json()).is_err(), "pack 1 does not exist");
        let mut huge = m;
        huge.root.location.offset = u64::MAX;
        assert!(Manifest::from_json(&huge.to_json()).is_err(), "an offset that overflows");
    }

    #[test]
    fn an_old_manifest_is_told_to_rebuild() {
        // A format-2 manifest has `blocks` and no `root`: the version is checked first.
        let old = br#"{"format_version": 2, "name": "k", "blocks": []}"#;
        let err = Manifest::from_json(old).unwrap_err();
        assert!(matches!(err, ManifestError::Version(2)), "{err}");
        assert!(err.to_string().contains("rebuild"), "{err}");
        // Format 3 (one pack a page): its pages are version 2, which this reader refuses.
        let mut m = sample();
        m.format_version = 3;
        let err = Manifest::from_json(&m.to_json()).unwrap_err();
        assert!(matches!(err, ManifestError::Version(3)), "{err}");
        assert!(err.to_string().contains("rebuild"), "{err}");
    }
}
