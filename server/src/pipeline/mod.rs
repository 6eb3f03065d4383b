//! The build pipeline, one stage a module, in data-flow order:
//! [`read`] (mesh files) → [`stream`] (chunked triangle stream) → [`bin`]
//! (triangles binned by 64³ block, out of core) → [`voxelize`] (one brick a
//! block) → [`pyramid`] (faces, coarser levels) → [`write`] (pack, encode,
//! publish). [`build_scene`] runs them as one call, reporting [`progress`].

pub mod bin;
pub mod progress;
pub mod pyramid;
pub mod read;
pub mod stream;
pub mod voxelize;
pub mod write;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use voxstream_format::SourceInfo;

use crate::pipeline::bin::StreamSink;
use crate::pipeline::progress::{Progress, ProgressSink, Stage};
use crate::pipeline::read::{IngestError, ReadOptions};
use crate::pipeline::stream::ChunkStore;
use crate::pipeline::voxelize::{Topology, VoxelizeError};
use crate::pipeline::write::SceneContent;
use crate::store::{self, StoreError};

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
    /// Bytes the build may hold in memory (reader tables, resident chunks,
    /// bins, in-flight bricks, level 0); the rest goes to temporary files.
    pub memory_budget: u64,
    /// Where the build's temporary directory goes; the store directory when `None`.
    pub temp_dir: Option<PathBuf>,
}

impl BuildOptions {
    pub fn check_cancelled(&self) -> Result<(), BuildError> {
        match &self.cancel {
            Some(flag) if flag.load(Ordering::Relaxed) => Err(BuildError::Cancelled),
            _ => Ok(()),
        }
    }
}

/// 1 GiB.
pub const DEFAULT_MEMORY_BUDGET: u64 = 1 << 30;

/// Parses a byte count: plain bytes or a K/M/G/T suffix (powers of 1024;
/// `KiB`, `KB`, `K` and `k` all mean 1024), e.g. `1GiB`, `512M`, `1048576`.
pub fn parse_byte_size(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let shift = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kb" | "kib" => 10,
        "m" | "mb" | "mib" => 20,
        "g" | "gb" | "gib" => 30,
        "t" | "tb" | "tib" => 40,
        other => return Err(format!("unknown size unit {other:?} in {text:?}: use bytes or K, M, G, T")),
    };
    let value: f64 = number.parse().map_err(|_| format!("{text:?} is not a size such as 1GiB or 512M"))?;
    let bytes = value * (1u64 << shift) as f64;
    if !(1.0..1.8e19).contains(&bytes) {
        return Err(format!("size {text:?} is out of range"));
    }
    Ok(bytes as u64)
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self {
            resolution: 512,
            name: None,
            topology: Topology::Conservative,
            cancel: None,
            memory_budget: DEFAULT_MEMORY_BUDGET,
            temp_dir: None,
        }
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
    #[error("temporary build files: {0}")]
    Temp(String),
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
    let temp_parent = opts.temp_dir.as_deref().unwrap_or(store_dir);
    std::fs::create_dir_all(temp_parent)
        .map_err(|e| BuildError::Temp(format!("create {}: {e}", temp_parent.display())))?;
    // Dot-named, so a store never lists it; removed when dropped: on success, error and cancellation.
    // The pid lets a restarted server tell a killed build's leftovers from a live build's.
    let prefix = format!(".build-{}-", std::process::id());
    let temp = tempfile::Builder::new()
        .prefix(&prefix)
        .tempdir_in(temp_parent)
        .map_err(|e| BuildError::Temp(format!("create a directory in {}: {e}", temp_parent.display())))?;

    // Pass 1: read, streaming valid triangles into chunks.
    progress.stage(Stage::Read, 0.0);
    let input_len = std::fs::metadata(input).map(|m| m.len()).unwrap_or(0).max(1);
    let read_opts = ReadOptions { memory_budget: opts.memory_budget, ..Default::default() };
    let bytes_read = read_opts.bytes_read.clone();
    let mut on_tick = || {
        if opts.check_cancelled().is_err() {
            return Err(IngestError::Cancelled);
        }
        progress.stage(Stage::Read, bytes_read.load(Ordering::Relaxed) as f64 / input_len as f64);
        Ok(())
    };
    let stream_store = ChunkStore::new(&temp.path().join("stream.vxt"), (opts.memory_budget / 8) as usize);
    let mut sink = StreamSink::new(stream_store, &mut on_tick);
    let format = read::stream_mesh(input, &mut sink, &read_opts).and_then(|f| sink.finish().map(|()| f));
    let format = match format {
        Err(IngestError::Cancelled) => return Err(BuildError::Cancelled),
        r => r?,
    };
    let StreamSink {
        store: stream_store,
        layout,
        bounds,
        triangles: read_triangles,
        skipped: read_skipped,
        ..
    } = sink;
    if read_triangles + read_skipped == 0 {
        return Err(IngestError::Invalid("the file holds no triangles".into()).into());
    }
    tracing::debug!(seconds = start.elapsed().as_secs_f64(), "build: read done");
    progress.set_triangles(read_triangles + read_skipped);
    progress.stage(Stage::Read, 1.0);
    opts.check_cancelled()?;

    // Pass 2 and 3: bin by block, then voxelize blocks in parallel.
    let frame = voxelize::frame_from_bounds(&bounds, opts.resolution, read_skipped)?;
    progress.stage(Stage::Voxelize, 0.0);
    let bins =
        bin::bin_triangles(&stream_store, layout, &frame, &temp.path().join("bins.vxt"), opts, &progress)?;
    tracing::debug!(
        seconds = start.elapsed().as_secs_f64(),
        stream_chunks = stream_store.len(),
        stream_spilled_bytes = stream_store.spilled_bytes(),
        bin_segments = bins.store.len(),
        bin_spilled_bytes = bins.store.spilled_bytes(),
        "build: bin done"
    );
    drop(stream_store);
    let (level0, mut stats) =
        bin::voxelize_bins(&bins, &frame, opts.topology, opts, &progress).map_err(|e| match e {
            BuildError::Voxelize(VoxelizeError::NoValidTriangle { skipped }) => {
                VoxelizeError::NoValidTriangle { skipped: skipped + read_skipped }.into()
            }
            e => e,
        })?;
    stats.skipped += read_skipped;
    drop(bins);
    tracing::debug!(seconds = start.elapsed().as_secs_f64(), "build: vox done");
    opts.check_cancelled()?;
    progress.stage(Stage::Lod, 0.0);
    let levels = pyramid::build_levels(level0, frame.resolution);
    progress.stage(Stage::Lod, 1.0);
    tracing::debug!(seconds = start.elapsed().as_secs_f64(), "build: lod done");
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
    let manifest = write::write_scene_reporting(store_dir, &id, &content, &progress)?;
    drop(temp);
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
