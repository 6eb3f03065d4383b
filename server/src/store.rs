//! Store: encodes blocks, writes a scene directory and publishes it
//! atomically; reads scenes back for serving.
//!
//! Layout: `<store>/<id>/manifest.json` and `<store>/<id>/blocks/<key>.vxb`.
//! A scene is written under `<store>/.tmp-<id>-<pid>-<n>` and renamed into
//! place only once every file is written and synced, so readers never see a
//! half-written scene. Directories starting with `.` are never listed.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use voxstream_format::hierarchy::page_path;
use voxstream_format::{
    BLOCK_SIZE, Block, BlockEntry, BlockKey, BlockLocation, FORMAT_VERSION, GridFrame, LevelInfo, Manifest,
    PAGE_LEVELS, PackedVoxel, PageBuilder, PageError, ResolutionChoice, SceneIndex, SourceInfo, VoxelBounds,
    coverage_from_count, encode_block, load_scene_index, oct_encode,
};

use crate::lod::{LodBlock, local_position};
use crate::progress::{ProgressSink, Stage, StageCounter};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    #[error(
        "scene id {0:?} is invalid: use 1–64 characters from a-z, 0-9, '-' and '_', not starting with '-' or '_'"
    )]
    BadId(String),
    #[error("scene {id} is damaged: {message}")]
    Damaged { id: String, message: String },
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io { action, path: path.to_path_buf(), source }
}

/// Scene ids are safe path components and URL segments by construction.
pub fn validate_id(id: &str) -> Result<(), StoreError> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
        && !id.starts_with(['-', '_']);
    if ok { Ok(()) } else { Err(StoreError::BadId(id.to_string())) }
}

/// Derives a valid id from a file name: `Koala Scan.OBJ` → `koala-scan`.
pub fn id_from_file_stem(path: &Path) -> String {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let mut id: String = stem
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '_' { c.to_ascii_lowercase() } else { '-' })
        .collect();
    id = id.trim_matches(['-', '_']).chars().take(64).collect();
    if id.is_empty() { "scene".to_string() } else { id }
}

/// Linear [0, 1] → sRGB8 (the viewer shows colours as stored, like its grey).
pub fn linear_to_srgb8(c: f32) -> u8 {
    let c = if c.is_finite() { c.clamp(0.0, 1.0) } else { 0.0 };
    let s = if c <= 0.003_130_8 { 12.92 * c } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0).round() as u8
}

/// Average colour of a voxel as sRGB8, if it has any colour weight.
fn average_color(v: &voxstream_format::PackedVoxel, sum: [f32; 3], weight: f32) -> PackedVoxel {
    if weight > 0.0 && weight.is_finite() {
        v.with_color(sum.map(|c| linear_to_srgb8(c / weight)))
    } else {
        *v
    }
}

/// Neutral colour for uncoloured voxels in a block that has colour (the
/// viewer's grey, BASE_COLOUR in shaders/voxel.wgsl).
pub const NEUTRAL_SRGB8: [u8; 3] = [219, 204, 184];

/// The block as stored: normals are the normalised sums (octahedral snorm8),
/// colours the area-weighted averages (sRGB8; blocks with no colour weight at
/// all have no colour column), coverage the solid count over 8^level.
pub fn packed_block(b: &LodBlock) -> Block {
    let level = b.key.level;
    let has_color = b.voxels.iter().any(|v| v.voxel.color_weight > 0.0);
    Block {
        key: b.key,
        voxels: b
            .voxels
            .iter()
            .map(|v| {
                let mut p =
                    PackedVoxel::new(local_position(&v.voxel), v.voxel.faces, oct_encode(v.voxel.normal_sum))
                        .with_coverage(coverage_from_count(v.solid as u64, level));
                if has_color {
                    p = average_color(&p.with_color(NEUTRAL_SRGB8), v.voxel.color_sum, v.voxel.color_weight);
                }
                p
            })
            .collect(),
    }
}

fn tight_bounds(b: &LodBlock) -> VoxelBounds {
    let base = b.key.coord().map(|c| c * BLOCK_SIZE);
    let mut min = [u32::MAX; 3];
    let mut max = [0u32; 3];
    for v in &b.voxels {
        let p = local_position(&v.voxel);
        for a in 0..3 {
            min[a] = min[a].min(base[a] + p[a]);
            max[a] = max[a].max(base[a] + p[a] + 1);
        }
    }
    VoxelBounds { min, max }
}

/// What a scene is made of before it is written.
pub struct SceneContent<'a> {
    pub name: String,
    pub source: SourceInfo,
    pub grid: GridFrame,
    pub resolution_choice: ResolutionChoice,
    /// Blocks per level, finest first, each level sorted by key.
    pub levels: &'a [Vec<LodBlock>],
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut f = fs::File::create(path).map_err(io("create", path))?;
    f.write_all(bytes).map_err(io("write", path))?;
    f.sync_all().map_err(io("sync", path))
}

/// Encodes and writes a scene, then publishes it as `<store>/<id>`, replacing
/// any previous scene of that id. Returns the manifest written.
pub fn write_scene(store: &Path, id: &str, content: &SceneContent) -> Result<Manifest, StoreError> {
    write_scene_reporting(store, id, content, &ProgressSink::new(&|_| {}))
}

/// [`write_scene`], reporting each block written to `progress`.
pub fn write_scene_reporting(
    store: &Path,
    id: &str,
    content: &SceneContent,
    progress: &ProgressSink,
) -> Result<Manifest, StoreError> {
    validate_id(id)?;
    fs::create_dir_all(store).map_err(io("create directory", store))?;
    let tmp = store.join(format!(
        ".tmp-{id}-{}-{}",
        std::process::id(),
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos())
    ));
    let result = write_scene_dir(&tmp, content, progress).and_then(|manifest| {
        publish(store, id, &tmp)?;
        Ok(manifest)
    });
    if result.is_err() {
        let _ = fs::remove_dir_all(&tmp);
    }
    result
}

fn write_scene_dir(
    dir: &Path,
    content: &SceneContent,
    progress: &ProgressSink,
) -> Result<Manifest, StoreError> {
    let counter = StageCounter::new(progress, Stage::Write, content.levels.iter().map(Vec::len).sum());
    let blocks_dir = dir.join("blocks");
    let pages_dir = dir.join("pages");
    for d in [&blocks_dir, &pages_dir] {
        fs::create_dir_all(d).map_err(io("create directory", d))?;
    }
    let coarsest = (content.levels.len().max(1) - 1) as u8;
    let mut pages = PageBuilder::new(coarsest, PAGE_LEVELS);
    let mut levels = Vec::new();
    // Finest level first: children reach the page builder before their parents.
    for (l, level) in content.levels.iter().enumerate() {
        let entries: Vec<BlockEntry> = level
            .par_iter()
            .map(|b| {
                let entry = write_block(&blocks_dir, b)?;
                counter.tick();
                Ok(entry)
            })
            .collect::<Result<_, StoreError>>()?;
        levels.push(LevelInfo {
            level: l as u8,
            resolution: content.grid.resolution >> l,
            blocks: entries.len() as u32,
            voxels: entries.iter().map(|e| e.voxels as u64).sum(),
            bytes: entries.iter().map(|e| e.bytes as u64).sum(),
        });
        for e in entries {
            if let Some((page_ref, bytes)) = pages.add(e).map_err(page_err)? {
                write_synced(&dir.join(page_path(&page_ref.root)), &bytes)?;
            }
        }
    }
    let (root, root_page) = pages.finish().map_err(page_err)?;
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        name: content.name.clone(),
        source: content.source.clone(),
        grid: content.grid.clone(),
        block_size: BLOCK_SIZE,
        levels,
        resolution_choice: content.resolution_choice.clone(),
        page_levels: PAGE_LEVELS,
        root,
        root_page,
    };
    write_synced(&dir.join("manifest.json"), &manifest.to_json())?;
    for d in [&blocks_dir, &pages_dir] {
        fs::File::open(d).and_then(|f| f.sync_all()).map_err(io("sync", d))?;
    }
    Ok(manifest)
}

fn page_err(e: PageError) -> StoreError {
    StoreError::Damaged { id: "(being written)".into(), message: format!("hierarchy: {e}") }
}

/// Packs, encodes and writes one block as `blocks/<key>.vxb`; returns its entry
/// (child mask still 0: the page builder fills it in).
pub fn write_block(blocks_dir: &Path, b: &LodBlock) -> Result<BlockEntry, StoreError> {
    let packed = packed_block(b);
    let bytes = encode_block(&packed);
    write_synced(&blocks_dir.join(format!("{}.vxb", b.key)), &bytes)?;
    Ok(BlockEntry {
        key: b.key,
        bounds: tight_bounds(b),
        voxels: packed.voxels.len() as u32,
        faces: packed.face_count(),
        bytes: bytes.len() as u32,
        hash: blake3::hash(&bytes).to_hex().to_string(),
        geometric_error: b.geometric_error(),
        child_mask: 0,
        location: BlockLocation::FILE,
    })
}

fn publish(store: &Path, id: &str, tmp: &Path) -> Result<(), StoreError> {
    let dest = store.join(id);
    if dest.exists() {
        // One atomic swap where the kernel offers it, so a reader never finds the
        // scene missing; the old scene then sits at `tmp` until removed (a crash
        // leaves it as a `.tmp-*` dir, which start-up cleanup removes).
        if exchange_dirs(tmp, &dest).is_ok() {
            let _ = fs::remove_dir_all(tmp);
        } else {
            // Move the old scene aside first: rename cannot replace a non-empty directory.
            let old = store.join(format!(".old-{id}-{}", std::process::id()));
            fs::rename(&dest, &old).map_err(io("move aside", &dest))?;
            fs::rename(tmp, &dest).map_err(io("publish", &dest))?;
            let _ = fs::remove_dir_all(&old);
        }
    } else {
        fs::rename(tmp, &dest).map_err(io("publish", &dest))?;
    }
    fs::File::open(store).and_then(|d| d.sync_all()).map_err(io("sync", store))
}

/// Atomically swaps two directories (Linux `renameat2(RENAME_EXCHANGE)`).
#[cfg(target_os = "linux")]
fn exchange_dirs(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let a = CString::new(a.as_os_str().as_bytes())?;
    let b = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: both are valid NUL-terminated paths that outlive the call.
    let r = unsafe {
        libc::renameat2(libc::AT_FDCWD, a.as_ptr(), libc::AT_FDCWD, b.as_ptr(), libc::RENAME_EXCHANGE)
    };
    if r == 0 { Ok(()) } else { Err(std::io::Error::last_os_error()) }
}

#[cfg(not(target_os = "linux"))]
fn exchange_dirs(_a: &Path, _b: &Path) -> std::io::Result<()> {
    Err(std::io::Error::from(std::io::ErrorKind::Unsupported))
}

/// A published scene, as the server reads it: the manifest and every page,
/// checked when opened, so a listed scene's hierarchy is complete.
#[derive(Debug, Clone)]
pub struct StoredScene {
    pub id: String,
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub index: std::sync::Arc<SceneIndex>,
}

impl StoredScene {
    pub fn block_path(&self, key: &BlockKey) -> PathBuf {
        self.dir.join("blocks").join(format!("{key}.vxb"))
    }

    pub fn page_path(&self, root: &BlockKey) -> PathBuf {
        self.dir.join(page_path(root))
    }

    /// Every block entry, sorted by key.
    pub fn blocks(&self) -> Vec<&BlockEntry> {
        let mut all: Vec<&BlockEntry> = self.index.blocks().collect();
        all.sort_by_key(|b| b.key);
        all
    }
}

/// Reads every hierarchy page of the scene in `dir`.
pub fn read_scene_index(dir: &Path, manifest: &Manifest) -> Result<SceneIndex, String> {
    load_scene_index(manifest, |r| fs::read(dir.join(page_path(&r.root)))).map_err(|e| e.to_string())
}

/// Lists the published scenes of a store, sorted by id. A missing store is empty.
pub fn list_scenes(store: &Path) -> Result<Vec<StoredScene>, StoreError> {
    let entries = match fs::read_dir(store) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io("list", store)(e)),
    };
    let mut scenes = Vec::new();
    for entry in entries {
        let entry = entry.map_err(io("list", store))?;
        let Some(id) = entry.file_name().to_str().map(str::to_string) else { continue };
        if validate_id(&id).is_err() || !entry.path().is_dir() {
            continue; // temp dirs, stray files
        }
        scenes.push(open_scene(store, &id)?);
    }
    scenes.sort_by(|a, b| a.id.cmp(&b.id));
    Ok(scenes)
}

pub fn open_scene(store: &Path, id: &str) -> Result<StoredScene, StoreError> {
    validate_id(id)?;
    let dir = store.join(id);
    let path = dir.join("manifest.json");
    let bytes = fs::read(&path).map_err(io("read", &path))?;
    let damaged = |message: String| StoreError::Damaged { id: id.to_string(), message };
    let manifest = Manifest::from_json(&bytes).map_err(|e| damaged(e.to_string()))?;
    let index = read_scene_index(&dir, &manifest).map_err(damaged)?;
    Ok(StoredScene { id: id.to_string(), dir, manifest, index: std::sync::Arc::new(index) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_conversion() {
        assert_eq!(linear_to_srgb8(0.0), 0);
        assert_eq!(linear_to_srgb8(1.0), 255);
        assert_eq!(linear_to_srgb8(0.22), 129);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        assert_eq!(linear_to_srgb8(7.0), 255);
    }

    #[test]
    fn packing_averages_normals_and_colours() {
        use crate::lod::LodVoxel;
        use crate::voxelize::BuildVoxel;
        let voxel = |m, w: f32| LodVoxel {
            voxel: BuildVoxel {
                morton: m,
                normal_sum: [0.0, 0.0, -40.0],
                color_sum: [0.5 * w, 0.0, w],
                color_weight: w,
                faces: 1,
            },
            solid: 3,
            error: 2.0,
        };
        let b = LodBlock { key: BlockKey::new(1, 0, 0, 0), voxels: vec![voxel(0, 4.0), voxel(9, 0.0)] };
        let p = packed_block(&b);
        assert_eq!(voxstream_format::oct_decode(p.voxels[0].normal), [0.0, 0.0, -1.0]);
        assert_eq!(p.voxels[0].color(), Some([188, 0, 255]));
        assert_eq!(p.voxels[1].color(), Some(NEUTRAL_SRGB8), "uncoloured voxel in a coloured block");
        assert_eq!(p.voxels[0].coverage(), 96, "3 of 8");
        assert_eq!(b.geometric_error(), 2.0);
        let grey = LodBlock { key: BlockKey::new(0, 0, 0, 0), voxels: vec![voxel(0, 0.0)] };
        assert_eq!(packed_block(&grey).voxels[0].color(), None);
    }

    #[test]
    fn ids() {
        assert_eq!(id_from_file_stem(Path::new("/x/Koala Scan.OBJ")), "koala-scan");
        assert_eq!(id_from_file_stem(Path::new("..")), "scene");
        for good in ["koala", "a-1_b"] {
            assert!(validate_id(good).is_ok());
        }
        for bad in ["", "..", "a/b", "-x", "Koala", "a b", &"x".repeat(65)] {
            assert!(validate_id(bad).is_err(), "{bad:?}");
        }
    }
}
