//! The build pipeline, one stage a module, in data-flow order:
//! [`read`] (mesh files) → [`stream`] (chunked triangle stream) → [`bin`]
//! (triangles binned by 64³ block, out of core) → [`voxelize`] (one brick a
//! block) → [`pyramid`] (faces, coarser levels) → [`write`] (pack, encode,
//! publish). [`build_scene`] runs them as one call, reporting [`progress`].

pub mod aofield;
pub mod bin;
pub mod progress;
pub mod pyramid;
pub mod read;
pub mod stream;
pub mod voxelize;
pub mod write;

pub use voxelize::{Resolution, ResolutionChoice};

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Instant;

use voxstream_format::SourceInfo;

use crate::pipeline::bin::StreamSink;
use crate::pipeline::progress::{Progress, ProgressSink, Stage};
use crate::pipeline::pyramid::{
    DrawnBlock, FULL_LOD_BLOCK_BYTES, LodVoxel, Pyramid, level_count, mark_exposed_faces_lod, parent_share,
};
use crate::pipeline::read::{IngestError, ReadOptions};
use crate::pipeline::stream::ChunkStore;
use crate::pipeline::stream::MAX_CHUNK_TRIANGLES;
use crate::pipeline::voxelize::BLOCK_VOXELIZER_BYTES;
use crate::pipeline::voxelize::{Topology, VoxelizeError};
use crate::pipeline::write::{BlockWriter, ENCODE_BYTES_PER_VOXEL};
use crate::store::{self, StoreError};

#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// How many level-0 voxels an edge of the grid has: matched to the scan
    /// (auto), from a voxel size, or a given power of two.
    pub resolution: Resolution,
    /// The most `auto` picks (the server's `--max-resolution`).
    pub max_resolution: u32,
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
    /// Bytes a PLY's vertex table may take in memory before it is paged from
    /// a temporary file through a cache of half as many; `None`: half the
    /// budget (the cache then takes a quarter). Tests set it to force paging.
    pub ply_vertex_memory: Option<u64>,
    /// Told of every pack and page as it is finished (a build into a bucket uploads them from
    /// there); an error stops the build.
    pub finished_files: Option<FinishedFiles>,
    /// Called with the scene id right after the new scene is renamed into the store and before
    /// the scene it replaced is removed, so a server can switch readers to the new manifest
    /// while the old one's blocks still exist.
    pub on_published: Option<OnPublished>,
    /// The precomputed AO field (issue 9 item 2): computed and stored in every
    /// block when `Some` (the default).
    pub ao_field: Option<aofield::AoFieldOptions>,
}

/// See [`BuildOptions::on_published`].
#[derive(Clone)]
pub struct OnPublished(pub Arc<dyn Fn(&str) + Send + Sync>);

impl std::fmt::Debug for OnPublished {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("OnPublished")
    }
}

/// Called with a finished file's name inside the scene (`packs/<blake3>.vxp`,
/// `pages/<key>.<blake3>.vxh`) and its bytes; an error stops the build. It may block: that is the
/// back-pressure that bounds what a slower consumer holds.
#[derive(Clone)]
pub struct FinishedFiles(pub Arc<FinishedFile>);

/// Takes one finished file: its name inside the scene and its bytes.
pub type FinishedFile = dyn Fn(&str, Vec<u8>) -> Result<(), String> + Send + Sync;

impl std::fmt::Debug for FinishedFiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FinishedFiles")
    }
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
            resolution: Resolution::Auto,
            max_resolution: voxelize::MAX_RESOLUTION,
            name: None,
            topology: Topology::Conservative,
            cancel: None,
            memory_budget: DEFAULT_MEMORY_BUDGET,
            temp_dir: None,
            ply_vertex_memory: None,
            finished_files: None,
            on_published: None,
            // Opt-in: the field costs ~30 % more bytes a block and is less accurate than cone
            // tracing on every benchmarked view (docs/ao-benchmark.md).
            ao_field: None,
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
    /// The grid's resolution and why it was chosen.
    pub resolution_choice: ResolutionChoice,
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
    #[error(
        "the memory budget {} is too small for resolution {resolution}: at least {} is needed ({detail}); \
         raise --memory-budget or lower --resolution",
        mib(*budget),
        mib(*needed)
    )]
    BudgetTooSmall { budget: u64, resolution: u32, needed: u64, detail: String },
}

/// Bytes as whole MiB, rounded up (a budget named in a message must suffice).
fn mib(bytes: u64) -> String {
    format!("{} MiB", bytes.div_ceil(1 << 20))
}

/// The largest triangle record: f64 positions and a colour.
const MAX_RECORD_BYTES: usize = 72 + 12;

/// Encoding a full 64³ block takes at most this (packed voxels, columns, output).
const ENCODE_FULL_BYTES: usize = voxstream_format::BLOCK_VOXELS * ENCODE_BYTES_PER_VOXEL;

/// What a level-0 block takes on its worker until its real size is known:
/// the block, its share of the parent (one octant: ⅛ of a block) and its encoding.
pub const IN_FLIGHT_BYTES: usize = FULL_LOD_BLOCK_BYTES + FULL_LOD_BLOCK_BYTES / 8 + ENCODE_FULL_BYTES;

/// One voxelizing worker: its brick, and its block in flight or, while it
/// voxelizes, one segment read back (encoded and decoded).
pub const WORKER_BYTES: usize =
    BLOCK_VOXELIZER_BYTES + max_usize(IN_FLIGHT_BYTES, 2 * MAX_CHUNK_TRIANGLES * MAX_RECORD_BYTES);

const fn max_usize(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

/// The fold's encoding of one coarser block. The block itself is out of the
/// front while it is encoded, so the front's reserve holds it.
pub const WRITER_BYTES: usize = ENCODE_FULL_BYTES;

/// The least the triangle stores and bin buffers of passes 1 and 2 get.
const SPARE_MIN: u64 = 4 << 20;

/// How a build splits its memory budget B (ARCHITECTURE.md, "Memory").
///
/// The pyramid stage reserves its worst case up front: the front (one
/// partial 64³ block per level above 0, plus one growing), the writer's queue
/// and one worker. What is left, the spare S = B − reserve, must be at least
/// [`SPARE_MIN`]: the stream and bin stores keep S/4 each resident, the bin
/// buffers S/8 (S/4 with capacity slack). During pass 3 the bin index and
/// the resident bins come out of S, and the rest of S buys more workers and
/// finished level-0 blocks waiting for their turn in Morton order. Before
/// pass 3 the reserve is idle; pass 2's chunks written behind it
/// ([`bin::CHUNKS_IN_FLIGHT_BYTES`]) fit in it at any resolution.
#[derive(Debug, Clone, Copy)]
pub struct MemoryPlan {
    pub budget: u64,
    pub resolution: u32,
    /// Bytes held outside the stores: front, writer, one worker and the AO field's peak.
    pub reserve: u64,
    field_cells: u32,
}

impl MemoryPlan {
    fn front(levels: u8) -> u64 {
        if levels > 1 { levels as u64 * FULL_LOD_BLOCK_BYTES as u64 } else { 0 }
    }

    /// The writer's queue, its open pack's buffer and the pages held until that pack closes.
    fn writer(levels: u8) -> u64 {
        (WRITER_BYTES + write::pack_writer_bytes(levels)) as u64
    }

    /// What the pyramid stage holds at worst besides the bins.
    pub fn reserve(resolution: u32) -> u64 {
        let levels = level_count(resolution);
        // Pass 2's chunks in flight borrow the reserve before pass 3 needs it.
        (Self::front(levels) + Self::writer(levels) + WORKER_BYTES as u64)
            .max(bin::CHUNKS_IN_FLIGHT_BYTES as u64)
    }

    /// The smallest budget a build at `resolution` can run in, whatever the input.
    pub fn minimum_budget(resolution: u32) -> u64 {
        Self::reserve(resolution) + SPARE_MIN
    }

    /// Checks the resolution and that the budget holds a build at it.
    pub fn new(budget: u64, resolution: u32) -> Result<Self, BuildError> {
        voxelize::check_resolution(resolution)?;
        let needed = Self::minimum_budget(resolution);
        if budget < needed {
            let levels = level_count(resolution);
            return Err(BuildError::BudgetTooSmall {
                budget,
                resolution,
                needed,
                detail: format!(
                    "{} levels: a front of {} blocks of 64³ voxels at {} each, the writer's queue and open packs, \
                     one voxelizer and {} for the triangle stores",
                    levels,
                    if levels > 1 { levels } else { 0 },
                    mib(FULL_LOD_BLOCK_BYTES as u64),
                    mib(SPARE_MIN)
                ),
            });
        }
        Ok(Self { budget, resolution, reserve: Self::reserve(resolution), field_cells: 0 })
    }

    /// The plan with an AO field of `cells`³ (its peak joins the reserve); refused when the
    /// budget has no room for it beside the smallest plan. The cells come from the options,
    /// never from the budget, so the store stays the same for any budget that holds it.
    pub fn with_field(self, cells: u32) -> Result<Self, BuildError> {
        let field = aofield::peak_bytes_cells(cells);
        let needed = Self::minimum_budget(self.resolution) + field;
        if self.budget < needed {
            return Err(BuildError::BudgetTooSmall {
                budget: self.budget,
                resolution: self.resolution,
                needed,
                detail: format!(
                    "the AO field of {cells}³ cells takes {} (build without --ao-field, or with a smaller --ao-field-cells)",
                    mib(field)
                ),
            });
        }
        Ok(Self { reserve: self.reserve + field, field_cells: cells, ..self })
    }

    /// The AO field's cells per edge ([`MemoryPlan::with_field`]; 0: no field).
    pub fn field_cells(&self) -> u32 {
        self.field_cells
    }

    fn field_bytes(&self) -> u64 {
        if self.field_cells > 0 { aofield::peak_bytes_cells(self.field_cells) } else { 0 }
    }

    fn spare(&self) -> u64 {
        self.budget - self.reserve
    }

    pub fn stream_resident(&self) -> usize {
        (self.spare() / 4) as usize
    }

    /// Pass 1: the most a PLY's vertex table may hold in memory; a larger one
    /// is paged from a temporary file through a cache of half as much. With
    /// the stream store's resident chunks beside it, pass 1 stays within the
    /// budget (nothing of passes 2 and 3 is alive yet).
    pub fn ply_vertex_table(&self) -> u64 {
        self.budget / 2
    }

    pub fn bin_resident(&self) -> usize {
        (self.spare() / 4) as usize
    }

    pub fn bin_buffers(&self) -> usize {
        (self.spare() / 8) as usize
    }

    /// Pass 2: what the chunks being grouped by block may take. The pyramid
    /// stage's reserve is not in use yet, so they get it.
    pub fn bin_groups(&self) -> usize {
        self.reserve as usize
    }

    /// Bytes pass 3 has for workers and waiting level-0 blocks, once the
    /// bins hold `index_bytes` of index; an error when not even one worker fits.
    pub fn pass3_pool(&self, index_bytes: u64) -> Result<u64, BuildError> {
        let levels = level_count(self.resolution);
        let fixed = Self::front(levels)
            + Self::writer(levels)
            + self.bin_resident() as u64
            + index_bytes
            + self.field_bytes();
        let needed = fixed + WORKER_BYTES as u64;
        if self.budget < needed {
            return Err(BuildError::BudgetTooSmall {
                budget: self.budget,
                resolution: self.resolution,
                needed: needed + (self.bin_resident() as u64).max(SPARE_MIN),
                detail: format!("this input's bin index takes {}", mib(index_bytes)),
            });
        }
        Ok(self.budget - fixed)
    }
}

/// The most finished level-0 results may wait for the fold, beyond the blocks in flight.
const FOLD_BACKLOG_BYTES: usize = 64 << 20;

/// A level-0 block as its worker leaves it: its share of the parent
/// ([`parent_share`]) and its drawn voxels encoded (`None` when all are buried).
struct Level0 {
    key: voxstream_format::BlockKey,
    share: Vec<LodVoxel>,
    encoded: Option<(voxstream_format::BlockEntry, Vec<u8>)>,
}

/// Bookkeeping of an encoded block beside its bytes (entry, hash text).
const ENTRY_BYTES: usize = 256;

impl Level0 {
    /// Heap bytes it holds until the fold has taken it.
    fn bytes(&self) -> usize {
        self.share.capacity() * std::mem::size_of::<LodVoxel>()
            + self.encoded.as_ref().map_or(0, |(_, b)| b.capacity() + ENTRY_BYTES)
    }
}

/// A worker's part of pass 3 for one block: voxelize, mark faces, downsample
/// into the parent's octant, drop buried voxels and encode.
fn level0_block(
    bins: &bin::Bins,
    key: voxstream_format::BlockKey,
    triangles: bin::BlockTriangles,
    frame: &voxstream_format::GridFrame,
    topology: Topology,
    levels: u8,
    field: Option<&aofield::AoField>,
) -> Result<Option<Level0>, BuildError> {
    let Some(mut block) = bin::voxelize_bin(bins, key, triangles, frame, topology)? else {
        return Ok(None);
    };
    mark_exposed_faces_lod(&mut block);
    let share = if levels > 1 { parent_share(&block) } else { Vec::new() };
    let drawn = DrawnBlock::new(block);
    let encoded = (!drawn.block.voxels.is_empty()).then(|| write::encode_drawn_entry(&drawn, field));
    Ok(Some(Level0 { key, share, encoded }))
}

/// What the producer hands the fold, in Morton order.
enum ToFold {
    Block(Level0),
    /// Every block was sent: complete the pyramid.
    End,
}

/// An encoded block with the bytes it holds in `committed` until written.
type Encoded = ((voxstream_format::BlockEntry, Vec<u8>), usize);

/// A block waiting its turn to be written: ready, or a coarse block being
/// encoded on the rayon pool (its result comes on the channel).
enum Queued {
    Ready(Encoded),
    Encoding(mpsc::Receiver<std::thread::Result<(voxstream_format::BlockEntry, Vec<u8>)>>, usize),
}

/// The fold's side of the writer: blocks enter in post order and are written
/// in that order; coarse blocks are encoded on the rayon pool meanwhile.
///
/// Memory: a coarse block encoded off the fold thread holds its voxels and
/// encoding in `committed` (within `limit`, the producer's) until written.
/// When it does not fit, the queue is written out first, and a block that
/// still does not fit is encoded on the fold thread, as the plan reserves
/// (one coarse block, [`WRITER_BYTES`]).
struct WriteQueue<'a> {
    writer: &'a mut BlockWriter,
    queue: std::collections::VecDeque<Queued>,
    committed: &'a AtomicUsize,
    limit: usize,
    freed: mpsc::Sender<()>,
    field: Option<Arc<aofield::AoField>>,
}

impl WriteQueue<'_> {
    /// Queues a block already encoded (by a worker), holding `held` bytes.
    fn push_ready(
        &mut self,
        encoded: Option<(voxstream_format::BlockEntry, Vec<u8>)>,
        held: usize,
    ) -> Result<(), BuildError> {
        match encoded {
            Some(e) => self.queue.push_back(Queued::Ready((e, held))),
            None => self.release(held),
        }
        self.write_ready(false)
    }

    /// Queues a coarse block the pyramid completed, encoding it on the pool when its bytes fit.
    fn push_coarse(&mut self, b: DrawnBlock) -> Result<(), BuildError> {
        let held = b.block.voxels.capacity() * std::mem::size_of::<LodVoxel>()
            + b.block.voxels.len() * ENCODE_BYTES_PER_VOXEL
            + ENTRY_BYTES;
        if !self.reserve(held) {
            self.write_ready(true)?;
            if !self.reserve(held) {
                let encoded = write::encode_drawn_entry(&b, self.field.as_deref());
                drop(b);
                return self.push_ready(Some(encoded), 0);
            }
        }
        let (tx, rx) = mpsc::channel();
        let field = self.field.clone();
        rayon::spawn(move || {
            let _ = tx.send(std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                write::encode_drawn_entry(&b, field.as_deref())
            })));
        });
        self.queue.push_back(Queued::Encoding(rx, held));
        self.write_ready(false)
    }

    fn reserve(&self, bytes: usize) -> bool {
        self.committed
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |c| {
                (c + bytes <= self.limit).then_some(c + bytes)
            })
            .is_ok()
    }

    fn release(&self, bytes: usize) {
        self.committed.fetch_sub(bytes, Ordering::Relaxed);
        let _ = self.freed.send(());
    }

    /// Writes the queue's head while it is ready; with `wait`, all of it.
    fn write_ready(&mut self, wait: bool) -> Result<(), BuildError> {
        while let Some(head) = self.queue.pop_front() {
            let (encoded, held) = match head {
                Queued::Ready(e) => e,
                Queued::Encoding(rx, held) => {
                    let got = if wait { rx.recv().ok() } else { rx.try_recv().ok() };
                    match got {
                        Some(Ok(e)) => (e, held),
                        Some(Err(panic)) => std::panic::resume_unwind(panic),
                        None if !wait => {
                            self.queue.push_front(Queued::Encoding(rx, held));
                            return Ok(());
                        }
                        None => unreachable!("an encoding job always sends its result"),
                    }
                }
            };
            let (entry, bytes) = encoded;
            self.writer.add_encoded(entry, &bytes)?;
            drop(bytes);
            self.release(held);
        }
        Ok(())
    }
}

/// The fold: takes level-0 results in Morton order, appends their shares to
/// the pyramid, has the coarser blocks it completes encoded on the pool and
/// writes everything in post order ([`WriteQueue`]). Frees each result's
/// bytes in `committed` once written and says so on `freed`.
fn fold(
    from_producer: mpsc::Receiver<ToFold>,
    freed: mpsc::Sender<()>,
    committed: &AtomicUsize,
    limit: usize,
    resolution: u32,
    writer: &mut BlockWriter,
    field: Option<Arc<aofield::AoField>>,
) -> Result<(), BuildError> {
    let mut pyramid = Pyramid::new(resolution);
    let mut out = WriteQueue { writer, queue: Default::default(), committed, limit, freed, field };
    loop {
        let msg = match from_producer.try_recv() {
            Ok(msg) => msg,
            // Idle: finish the queued encodes first, so that their bytes are
            // freed even if the producer now waits for memory.
            Err(mpsc::TryRecvError::Empty) if !out.queue.is_empty() => {
                out.write_ready(true)?;
                continue;
            }
            Err(mpsc::TryRecvError::Empty) => match from_producer.recv() {
                Ok(msg) => msg,
                Err(mpsc::RecvError) => break,
            },
            Err(mpsc::TryRecvError::Disconnected) => break,
        };
        match msg {
            ToFold::Block(mut l0) => {
                let held = l0.bytes();
                pyramid.push_share(l0.key, &l0.share, &mut |b| out.push_coarse(b))?;
                let encoded = l0.encoded.take();
                drop(l0);
                out.push_ready(encoded, held)?;
            }
            ToFold::End => {
                pyramid.finish(&mut |b| out.push_coarse(b))?;
                return out.write_ready(true);
            }
        }
    }
    // The producer stopped without `End`: it failed, and returns its error.
    Ok(())
}

/// Pass 3: voxelizes the bins' blocks in Morton order, in parallel rounds
/// within the plan's pool (each worker also faces, downsamples and encodes
/// its block), while a fold thread feeds the results in order through the
/// streaming pyramid into `writer`: writing and the coarse levels overlap
/// the next round's voxelizing.
fn voxelize_pyramid(
    bins: &bin::Bins,
    frame: &voxstream_format::GridFrame,
    opts: &BuildOptions,
    plan: &MemoryPlan,
    progress: &ProgressSink,
    writer: &mut BlockWriter,
    field: Option<Arc<aofield::AoField>>,
) -> Result<(), BuildError> {
    let committed = AtomicUsize::new(0);
    let (to_fold, from_producer) = mpsc::channel();
    let (freed, on_freed) = mpsc::channel();
    let pool = plan.pass3_pool(bins.index_bytes() as u64)? as usize;
    let workers = (pool / WORKER_BYTES).clamp(1, rayon::current_num_threads());
    // Capped: results running far ahead of the fold only cost memory (a
    // 1 GiB build at 8192 otherwise peaked at 1005 MiB instead of ≈ 280).
    let limit = (pool - workers * (WORKER_BYTES - IN_FLIGHT_BYTES))
        .min(workers * IN_FLIGHT_BYTES + FOLD_BACKLOG_BYTES);
    std::thread::scope(|s| {
        let fold_field = field.clone();
        let folding =
            s.spawn(|| fold(from_producer, freed, &committed, limit, frame.resolution, writer, fold_field));
        let produced = produce(
            bins,
            frame,
            opts,
            (workers, limit),
            progress,
            (&committed, field.as_deref()),
            &to_fold,
            &on_freed,
        );
        drop(to_fold);
        let folded = folding.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
        produced.and(folded)
    })
}

/// The producer half of [`voxelize_pyramid`] (the calling thread): rounds of
/// level-0 blocks on the worker pool, finished ones sent to the fold in order.
/// Each block in flight reserves [`IN_FLIGHT_BYTES`] of `committed` until
/// its real size is known, and keeps that until the fold frees it; the head
/// of the window may use the whole limit, the others all but one
/// reservation, so once the fold has caught up the head always fits.
#[allow(clippy::too_many_arguments)]
fn produce(
    bins: &bin::Bins,
    frame: &voxstream_format::GridFrame,
    opts: &BuildOptions,
    (workers, limit): (usize, usize),
    progress: &ProgressSink,
    (committed, field): (&AtomicUsize, Option<&aofield::AoField>),
    to_fold: &mpsc::Sender<ToFold>,
    on_freed: &mpsc::Receiver<()>,
) -> Result<(), BuildError> {
    use rayon::prelude::*;

    struct Slot<'b> {
        key: voxstream_format::BlockKey,
        triangles: bin::BlockTriangles<'b>,
        done: Option<Result<Option<Level0>, BuildError>>,
    }
    let levels = level_count(frame.resolution);
    let window_len = 32 * workers;
    let total = bins.block_count().max(1);
    let mut blocks = bins.blocks();
    let mut window: Vec<Slot> = Vec::with_capacity(window_len);
    let mut fed = 0usize;
    let thread_pool = if workers < rayon::current_num_threads() {
        Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(workers)
                .build()
                .map_err(|e| BuildError::Temp(format!("thread pool: {e}")))?,
        )
    } else {
        None
    };
    loop {
        opts.check_cancelled()?;
        window.extend(blocks.by_ref().take(window_len - window.len()).map(|(key, triangles)| Slot {
            key,
            triangles,
            done: None,
        }));
        if window.is_empty() {
            break;
        }
        // Frees seen from here on wake a stalled round below; earlier ones are in `committed`.
        while on_freed.try_recv().is_ok() {}
        let started = AtomicUsize::new(0);
        let mut run = || {
            window.par_iter_mut().enumerate().filter(|(_, s)| s.done.is_none()).for_each(|(i, slot)| {
                let cap = if i == 0 { limit } else { limit - IN_FLIGHT_BYTES };
                let reserved = committed
                    .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |c| {
                        (c + IN_FLIGHT_BYTES <= cap).then_some(c + IN_FLIGHT_BYTES)
                    })
                    .is_ok();
                if !reserved {
                    return; // its turn comes in a later round
                }
                started.fetch_add(1, Ordering::Relaxed);
                let result = opts.check_cancelled().and_then(|()| {
                    level0_block(bins, slot.key, slot.triangles, frame, opts.topology, levels, field)
                });
                let real = match &result {
                    Ok(Some(l0)) => l0.bytes(),
                    _ => 0,
                };
                committed.fetch_sub(IN_FLIGHT_BYTES - real, Ordering::Relaxed);
                slot.done = Some(result);
            })
        };
        match &thread_pool {
            Some(p) => p.install(run),
            None => run(),
        }
        let ready = window.iter().take_while(|s| s.done.is_some()).count();
        for slot in window.drain(..ready) {
            if let Some(l0) = slot.done.expect("counted as done")? {
                if to_fold.send(ToFold::Block(l0)).is_err() {
                    return Ok(()); // the fold failed; its error is the build's
                }
            }
            fed += 1;
        }
        if started.into_inner() == 0 && on_freed.recv().is_err() {
            return Ok(()); // nothing fitted until the fold frees memory; it failed if it never will
        }
        progress.stage(Stage::Voxelize, 0.3 + 0.7 * fed as f64 / total as f64);
    }
    let _ = to_fold.send(ToFold::End);
    Ok(())
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
    // Before reading a large file: the resolution and whether the budget holds
    // it (for auto and a voxel size, at least the smallest grid).
    let first_plan = MemoryPlan::new(
        opts.memory_budget,
        match opts.resolution {
            Resolution::Explicit(r) => r,
            _ => voxelize::MIN_AUTO_RESOLUTION,
        },
    )?;
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
    let read_opts = ReadOptions {
        memory_budget: opts.memory_budget,
        temp_dir: Some(temp.path().to_path_buf()),
        vertex_memory: Some(opts.ply_vertex_memory.unwrap_or_else(|| first_plan.ply_vertex_table())),
        ..Default::default()
    };
    let bytes_read = read_opts.bytes_read.clone();
    let mut on_tick = || {
        if opts.check_cancelled().is_err() {
            return Err(IngestError::Cancelled);
        }
        progress.stage(Stage::Read, bytes_read.load(Ordering::Relaxed) as f64 / input_len as f64);
        Ok(())
    };
    let stream_store = ChunkStore::new(&temp.path().join("stream.vxt"), first_plan.stream_resident());
    // Spilled chunks are compressed and written by tasks of the scope, beside the reader.
    let (format, sink) = rayon::scope(|scope| {
        let mut sink = StreamSink::new(stream_store, &mut on_tick, scope);
        let format = read::stream_mesh(input, &mut sink, &read_opts).and_then(|f| sink.finish().map(|()| f));
        let StreamSink { store, layout, bounds, triangles, skipped, edges, .. } = sink;
        (format, (store, layout, bounds, triangles, skipped, edges))
    });
    let (mut stream_store, layout, bounds, read_triangles, read_skipped, edges) = sink;
    let format = format.and_then(|f| stream_store.settle_behind().map(|()| f).map_err(bin::stream_err));
    let format = match format {
        Err(IngestError::Cancelled) => return Err(BuildError::Cancelled),
        r => r?,
    };
    if read_triangles + read_skipped == 0 {
        return Err(IngestError::Invalid("the file holds no triangles".into()).into());
    }
    tracing::debug!(seconds = start.elapsed().as_secs_f64(), "build: read done");
    progress.set_triangles(read_triangles + read_skipped);
    progress.stage(Stage::Read, 1.0);
    opts.check_cancelled()?;

    // The grid, now that the bounds and the edge lengths are known.
    let max_auto = (voxelize::MIN_AUTO_RESOLUTION.trailing_zeros()
        ..=voxelize::MAX_RESOLUTION.trailing_zeros())
        .map(|k| 1u32 << k)
        .filter(|&r| MemoryPlan::minimum_budget(r) <= opts.memory_budget)
        .max()
        .unwrap_or(voxelize::MIN_AUTO_RESOLUTION)
        .min(opts.max_resolution);
    let (frame, resolution_choice) =
        voxelize::choose_resolution(&bounds, opts.resolution, edges.median(), max_auto, read_skipped)?;
    drop(edges);
    let mut plan = MemoryPlan::new(opts.memory_budget, frame.resolution)?;
    if let Some(o) = &opts.ao_field {
        plan = plan.with_field(o.cells.min(frame.resolution).max(1))?;
    }
    tracing::debug!(reason = %resolution_choice.reason, "build: resolution");

    // The AO field, from the stream's triangles, before binning empties the stream.
    let field = match &opts.ao_field {
        Some(o) => {
            let check = || opts.check_cancelled();
            let cells = plan.field_cells();
            let occ = aofield::Occupancy::from_stream(&stream_store, layout, &frame, cells, &check)?;
            let field = aofield::AoField::compute(&occ, frame.resolution, o);
            tracing::debug!(
                seconds = start.elapsed().as_secs_f64(),
                marked = occ.marked(),
                bytes = field.bytes(),
                "build: ao field done"
            );
            Some(Arc::new(field))
        }
        None => None,
    };

    // Pass 2: bin by block. Binning by places moves the stream into the bins,
    // so its size is logged as it was.
    progress.stage(Stage::Voxelize, 0.0);
    let (stream_chunks, stream_spilled_bytes) = (stream_store.len(), stream_store.spilled_bytes());
    let bins = bin::bin_triangles(
        &mut stream_store,
        layout,
        &frame,
        &temp.path().join("bins.vxt"),
        (plan.bin_resident(), plan.bin_buffers(), plan.bin_groups()),
        opts,
        &progress,
    )?;
    tracing::debug!(
        seconds = start.elapsed().as_secs_f64(),
        stream_chunks,
        stream_spilled_bytes,
        bin_segments = bins.store.len(),
        bin_spilled_bytes = bins.store.spilled_bytes(),
        bin_index_bytes = bins.index_bytes(),
        bin_placed = bins.placed(),
        "build: bin done"
    );
    drop(stream_store);
    if bins.triangles == 0 {
        return Err(VoxelizeError::NoValidTriangle { skipped: bins.skipped + read_skipped }.into());
    }

    // Pass 3: voxelize, build the pyramid and write, streaming.
    // No queue: the build hands the writer encoded blocks only.
    let mut writer = BlockWriter::create(store_dir, &id, frame.resolution, 0)?;
    writer.finished_files = opts.finished_files.clone();
    writer.on_published = opts.on_published.clone();
    writer.ao_field = field.as_ref().map(|f| f.info().clone());
    voxelize_pyramid(&bins, &frame, opts, &plan, &progress, &mut writer, field)?;
    let skipped = bins.skipped + read_skipped;
    let triangles = bins.triangles + skipped;
    drop(bins);
    tracing::debug!(seconds = start.elapsed().as_secs_f64(), "build: pyramid done");
    opts.check_cancelled()?;
    progress.stage(Stage::Write, 0.0);
    let source = SourceInfo {
        file: input.file_name().and_then(|f| f.to_str()).unwrap_or("").to_string(),
        format: format.to_string(),
        triangles,
        skipped_triangles: skipped,
    };
    let manifest = writer.finish(id.clone(), source, frame, resolution_choice.clone())?;
    progress.stage(Stage::Write, 1.0);
    drop(temp);
    Ok(BuildReport {
        scene_dir: store_dir.join(&id),
        id,
        triangles: manifest.source.triangles,
        skipped_triangles: skipped,
        voxels: manifest.levels[0].voxels,
        blocks: manifest.block_count() as u32,
        levels: manifest.levels.len() as u8,
        resolution_choice,
        bytes: manifest.levels.iter().map(|l| l.bytes).sum(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pass_one_fits_the_vertex_table_and_the_stream_store_in_the_budget() {
        for resolution in [64u32, 4096, 65536] {
            let smallest = MemoryPlan::minimum_budget(resolution);
            for budget in [smallest, smallest + (7 << 20), 1 << 30, 16 << 30] {
                let plan = MemoryPlan::new(budget, resolution).unwrap();
                let pass1 = plan.ply_vertex_table() + plan.stream_resident() as u64;
                assert!(pass1 <= budget, "{resolution}: {pass1} > {budget}");
                // The paged table's cache is half the table: a quarter of the budget.
                assert!(plan.ply_vertex_table() / 2 <= budget / 4);
            }
        }
        // Pass 2's chunks in flight fit in the pyramid's own reserve, so they raise no minimum budget.
        for resolution in [64u32, 4096, 65536] {
            let levels = level_count(resolution);
            let own = MemoryPlan::front(levels) + MemoryPlan::writer(levels) + WORKER_BYTES as u64;
            assert!(bin::CHUNKS_IN_FLIGHT_BYTES as u64 <= own, "{resolution}");
        }
        // Control: the stream store does take memory in pass 1, so a table allowed the whole
        // budget would pass it.
        let plan = MemoryPlan::new(1 << 30, 4096).unwrap();
        assert!(plan.stream_resident() > 0 && 1u64 << 30 < (1 << 30) + plan.stream_resident() as u64);
    }
}
