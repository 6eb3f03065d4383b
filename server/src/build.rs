//! The build pipeline: ingest → voxelize → lod → store, as one call.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use voxstream_format::SourceInfo;

use crate::ingest::{self, IngestError};
use crate::lod;
use crate::progress::{Progress, ProgressSink, Stage};
use crate::store::{self, SceneContent, StoreError};
use crate::voxelize::{self, Topology, VoxelizeError};

#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// Level-0 voxels per edge of the mesh's bounding cube; a power of two.
    pub resolution: u32,
    /// Scene id; derived from the input's file name when `None`.
    pub name: Option<String>,
    /// Which voxels a triangle sets.
    pub topology: Topology,
    /// Set to true from another thread to stop the build; it then returns
    /// [`BuildError::Cancelled`] and publishes nothing.
    pub cancel: Option<Arc<AtomicBool>>,
}

impl BuildOptions {
    pub fn check_cancelled(&self) -> Result<(), BuildError> {
        match &self.cancel {
            Some(flag) if flag.load(Ordering::Relaxed) => Err(BuildError::Cancelled),
            _ => Ok(()),
        }
    }
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self { resolution: 512, name: None, topology: Topology::Conservative, cancel: None }
    }
}

#[derive(Debug, Clone)]
pub struct BuildReport {
    pub id: String,
    pub scene_dir: PathBuf,
    pub triangles: u64,
    pub skipped_triangles: u64,
    /// Level-0 voxels written (buried voxels are not stored).
    pub voxels: u64,
    pub blocks: u32,
    pub levels: u8,
    /// Encoded bytes of all blocks on all levels.
    pub bytes: u64,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error(transparent)]
    Ingest(#[from] IngestError),
    #[error(transparent)]
    Voxelize(#[from] VoxelizeError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("the build was cancelled")]
    Cancelled,
}

pub fn build_scene(input: &Path, store_dir: &Path, opts: &BuildOptions) -> Result<BuildReport, BuildError> {
    build_scene_reporting(input, store_dir, opts, &|_| {})
}

/// [`build_scene`], calling `report` as the build moves through its stages.
pub fn build_scene_reporting(
    input: &Path,
    store_dir: &Path,
    opts: &BuildOptions,
    report: &(dyn Fn(Progress) + Sync),
) -> Result<BuildReport, BuildError> {
    let start = Instant::now();
    let progress = ProgressSink::new(report);
    let id = match &opts.name {
        Some(n) => {
            store::validate_id(n)?;
            n.clone()
        }
        None => store::id_from_file_stem(input),
    };
    voxelize::check_resolution(opts.resolution)?; // before reading a large file
    progress.stage(Stage::Read, 0.0);
    let (mesh, format) = ingest::read_mesh(input)?;
    progress.set_triangles(mesh.triangles.len() as u64);
    progress.stage(Stage::Read, 1.0);
    opts.check_cancelled()?;
    let frame = voxelize::choose_frame(&mesh, opts.resolution)?;
    let (level0, stats) = voxelize::voxelize_reporting(&mesh, &frame, opts.topology, &progress)?;
    drop(mesh);
    opts.check_cancelled()?;
    progress.stage(Stage::Lod, 0.0);
    let levels = lod::build_levels(level0, frame.resolution);
    progress.stage(Stage::Lod, 1.0);
    opts.check_cancelled()?;
    let content = SceneContent {
        name: id.clone(),
        source: SourceInfo {
            file: input.file_name().and_then(|f| f.to_str()).unwrap_or("").to_string(),
            format: format.to_string(),
            triangles: stats.triangles + stats.skipped,
            skipped_triangles: stats.skipped,
        },
        grid: frame,
        levels: &levels,
    };
    let manifest = store::write_scene_reporting(store_dir, &id, &content, &progress)?;
    Ok(BuildReport {
        scene_dir: store_dir.join(&id),
        id,
        triangles: manifest.source.triangles,
        skipped_triangles: stats.skipped,
        voxels: manifest.levels[0].voxels,
        blocks: manifest.blocks.len() as u32,
        levels: manifest.levels.len() as u8,
        bytes: manifest.levels.iter().map(|l| l.bytes).sum(),
        seconds: start.elapsed().as_secs_f64(),
    })
}
