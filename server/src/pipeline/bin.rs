//! Out-of-core voxelization: the build's three passes over the chunked
//! triangle stream ([`crate::pipeline::stream`]), each within the memory budget.
//!
//! 1. **Stream** ([`StreamSink`]): the reader pushes triangles; valid ones
//!    (finite, non-zero area) are packed into chunks whose headers carry
//!    their bounds, invalid ones are counted and dropped. The union of the
//!    chunk bounds gives the grid frame.
//! 2. **Bin** ([`bin_triangles`]): chunks are read back in order and every
//!    triangle's record is appended to the buffer of each 64³ block its
//!    bounds overlap. A full buffer (one chunk's worth) becomes a segment in
//!    the bin store; when all buffers together pass their share of the
//!    budget, every buffer is flushed. Segments of one block stay in input
//!    order.
//! 3. **Voxelize** ([`voxelize_bins`]): blocks in key order, in parallel
//!    (rayon), each reading its segments one at a time into a reused dense
//!    brick, so a block costs one brick and one segment however many
//!    triangles it has. At most `budget / 4 / brick` blocks are in flight.
//!
//! Determinism: passes 1 and 2 are sequential, and in pass 3 each block is
//! one thread's work over its triangles in input order, so the output does
//! not depend on the thread count.
//!
//! Memory: stream and bin stores each keep up to budget/8 of encoded chunks
//! resident and spill the rest to files in the build's temp dir; bin
//! buffers take up to budget/16 (budget/32 of records, capacity doubling).
//! Level-0 output is ~36 bytes a voxel (`BuildVoxel`) and must fit the
//! budget; a clear error says so otherwise.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;
use voxstream_format::{BlockKey, GridFrame};

use crate::pipeline::progress::{ProgressSink, Stage};
use crate::pipeline::read::{IngestError, TriangleSink};
use crate::pipeline::stream::{Bounds, ChunkStore, MAX_CHUNK_TRIANGLES, RecordLayout};
use crate::pipeline::voxelize::{
    BLOCK_VOXELIZER_BYTES, BuildVoxel, SparseBlock, Topology, VoxelizeError, VoxelizeStats, block_range,
    to_grid, to_grid_unchecked, valid_triangle, with_block_voxelizer,
};
use crate::pipeline::{BuildError, BuildOptions};

/// Chunks encoded (lz4 when spilled) together on all cores.
const PENDING_CHUNKS: usize = 8;

/// Pass 1: packs valid triangles into chunks.
pub struct StreamSink<'a> {
    pub store: ChunkStore,
    pub layout: RecordLayout,
    /// Bounds of every valid triangle.
    pub bounds: Bounds,
    pub triangles: u64,
    pub skipped: u64,
    raw: Vec<u8>,
    chunk_bounds: Bounds,
    /// Full chunks waiting to be encoded together.
    pending: Vec<(Vec<u8>, Bounds)>,
    begun: bool,
    on_tick: &'a mut dyn FnMut() -> Result<(), IngestError>,
}

impl<'a> StreamSink<'a> {
    pub fn new(store: ChunkStore, on_tick: &'a mut dyn FnMut() -> Result<(), IngestError>) -> Self {
        Self {
            store,
            layout: RecordLayout { f64_positions: true, color: false },
            bounds: Bounds::EMPTY,
            triangles: 0,
            skipped: 0,
            raw: Vec::new(),
            chunk_bounds: Bounds::EMPTY,
            pending: Vec::new(),
            begun: false,
            on_tick,
        }
    }

    /// Queues the current chunk; every [`PENDING_CHUNKS`] (and at the end) they are encoded together.
    fn flush(&mut self, last: bool) -> Result<(), IngestError> {
        if !self.raw.is_empty() {
            let raw = std::mem::replace(
                &mut self.raw,
                Vec::with_capacity(MAX_CHUNK_TRIANGLES * self.layout.size()),
            );
            self.pending.push((raw, std::mem::take(&mut self.chunk_bounds)));
        }
        if self.pending.len() >= PENDING_CHUNKS || (last && !self.pending.is_empty()) {
            self.store
                .push_many(self.layout, &self.pending)
                .map_err(|e| IngestError::Invalid(format!("temporary triangle stream: {e}")))?;
            self.pending.clear();
        }
        (self.on_tick)()
    }

    /// Writes the last partial chunk.
    pub fn finish(&mut self) -> Result<(), IngestError> {
        self.flush(true)
    }
}

impl TriangleSink for StreamSink<'_> {
    fn begin(&mut self, layout: RecordLayout) -> Result<(), IngestError> {
        if self.begun {
            return Err(IngestError::Invalid("reader began twice".into()));
        }
        self.begun = true;
        self.layout = layout;
        self.raw.reserve(MAX_CHUNK_TRIANGLES * layout.size());
        Ok(())
    }

    fn triangle(&mut self, tri: [[f64; 3]; 3], color: [f32; 3]) -> Result<(), IngestError> {
        if !valid_triangle(&tri) {
            self.skipped += 1;
            return Ok(());
        }
        self.layout.encode(&mut self.raw, &tri, color);
        self.chunk_bounds.add_triangle(&tri);
        self.bounds.add_triangle(&tri);
        self.triangles += 1;
        if self.raw.len() >= MAX_CHUNK_TRIANGLES * self.layout.size() {
            self.flush(false)?;
        }
        Ok(())
    }

    fn tick(&mut self) -> Result<(), IngestError> {
        (self.on_tick)()
    }
}

/// One block's pending records and the segments already stored.
#[derive(Default)]
struct BinBuffer {
    raw: Vec<u8>,
    bounds: Bounds,
    segments: Vec<usize>,
}

/// The bins: for each non-empty block, its segments in the bin store, in input order.
pub struct Bins {
    pub store: ChunkStore,
    pub layout: RecordLayout,
    blocks: BTreeMap<BlockKey, Vec<usize>>,
    /// Triangles that became degenerate or non-finite in grid units.
    pub skipped: u64,
    pub triangles: u64,
}

impl Bins {
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }
}

fn temp_err(e: crate::pipeline::stream::ChunkError) -> BuildError {
    BuildError::Temp(e.to_string())
}

/// A triangle's block range (closed) and its source-space bounds.
type Placement = ([u32; 3], [u32; 3], Bounds);

/// Pass 2: bins the stream's triangles by the 64³ blocks they overlap.
pub fn bin_triangles(
    stream: &ChunkStore,
    layout: RecordLayout,
    frame: &GridFrame,
    spill_path: &Path,
    opts: &BuildOptions,
    progress: &ProgressSink,
) -> Result<Bins, BuildError> {
    let res = frame.resolution as i64;
    let rec = layout.size();
    // Counted by length; capacities reach at most twice that.
    let buffer_limit = (opts.memory_budget / 32).max(1 << 20) as usize;
    let mut store = ChunkStore::new(spill_path, (opts.memory_budget / 8) as usize);
    // Buffers in first-hit order, found through a map and a one-entry cache
    // (consecutive triangles mostly share a block).
    let mut buffers: Vec<([u32; 3], BinBuffer)> = Vec::new();
    let mut index: HashMap<[u32; 3], usize> = HashMap::new();
    let mut last: Option<([u32; 3], usize)> = None;
    let mut buffered = 0usize;
    let (mut skipped, mut triangles) = (0u64, 0u64);
    // Full buffers wait here (buffer index, records, bounds) and are encoded together.
    let mut pending: Vec<(usize, Vec<u8>, Bounds)> = Vec::new();
    let take = |b: &mut BinBuffer, i: usize, pending: &mut Vec<(usize, Vec<u8>, Bounds)>| {
        if !b.raw.is_empty() {
            // Moved out, not cleared: idle blocks must not keep their high-water capacity.
            pending.push((i, std::mem::take(&mut b.raw), std::mem::take(&mut b.bounds)));
        }
    };
    let drain = |store: &mut ChunkStore,
                 buffers: &mut Vec<([u32; 3], BinBuffer)>,
                 pending: &mut Vec<(usize, Vec<u8>, Bounds)>|
     -> Result<(), BuildError> {
        let items: Vec<(Vec<u8>, Bounds)> =
            pending.iter_mut().map(|(_, r, b)| (std::mem::take(r), *b)).collect();
        let ids = store.push_many(layout, &items).map_err(temp_err)?;
        for ((i, _, _), id) in pending.drain(..).zip(ids) {
            buffers[i].1.segments.push(id);
        }
        Ok(())
    };
    for id in 0..stream.len() {
        opts.check_cancelled()?;
        let (_, raw) = stream.read(id).map_err(temp_err)?;
        // Where each triangle goes, computed on all cores; appended below in input order.
        let placed: Vec<Option<Placement>> = raw
            .par_chunks_exact(rec)
            .with_min_len(1024)
            .map(|record| {
                let (tri, _) = layout.decode(record);
                let g = to_grid(tri, frame)?;
                let (lo, hi) = block_range(&g, res);
                let mut bounds = Bounds::EMPTY;
                bounds.add_triangle(&tri);
                Some((lo, hi, bounds))
            })
            .collect();
        for (record, place) in raw.chunks_exact(rec).zip(placed) {
            let Some((blo, bhi, bounds)) = place else {
                skipped += 1;
                continue;
            };
            triangles += 1;
            for bz in blo[2]..=bhi[2] {
                for by in blo[1]..=bhi[1] {
                    for bx in blo[0]..=bhi[0] {
                        let key = [bx, by, bz];
                        let i = match last {
                            Some((k, i)) if k == key => i,
                            _ => {
                                let i = *index.entry(key).or_insert_with(|| {
                                    buffers.push((key, BinBuffer::default()));
                                    buffers.len() - 1
                                });
                                last = Some((key, i));
                                i
                            }
                        };
                        let buf = &mut buffers[i].1;
                        buf.raw.extend_from_slice(record);
                        buf.bounds.union(&bounds);
                        buffered += rec;
                        if buf.raw.len() >= MAX_CHUNK_TRIANGLES * rec {
                            buffered -= buf.raw.len();
                            take(buf, i, &mut pending);
                            if pending.len() >= PENDING_CHUNKS {
                                drain(&mut store, &mut buffers, &mut pending)?;
                            }
                        }
                    }
                }
            }
            if buffered > buffer_limit {
                for (i, (_, buf)) in buffers.iter_mut().enumerate() {
                    take(buf, i, &mut pending);
                }
                drain(&mut store, &mut buffers, &mut pending)?;
                buffered = 0;
            }
        }
        progress.stage(Stage::Voxelize, 0.3 * (id + 1) as f64 / stream.len() as f64);
    }
    for (i, (_, buf)) in buffers.iter_mut().enumerate() {
        take(buf, i, &mut pending);
    }
    drain(&mut store, &mut buffers, &mut pending)?;
    let blocks = buffers
        .into_iter()
        .filter(|(_, b)| !b.segments.is_empty())
        .map(|(c, b)| (BlockKey::new(0, c[0], c[1], c[2]), b.segments))
        .collect();
    Ok(Bins { store, layout, blocks, skipped, triangles })
}

/// Pass 3: voxelizes every block's segments; blocks come back sorted by key.
pub fn voxelize_bins(
    bins: &Bins,
    frame: &GridFrame,
    topology: Topology,
    opts: &BuildOptions,
    progress: &ProgressSink,
) -> Result<(Vec<SparseBlock>, VoxelizeStats), BuildError> {
    let stats = VoxelizeStats { triangles: bins.triangles, skipped: bins.skipped };
    if bins.triangles == 0 {
        return Err(VoxelizeError::NoValidTriangle { skipped: bins.skipped }.into());
    }
    let res = frame.resolution as i64;
    let rec = bins.layout.size();
    let voxel_cap = opts.memory_budget / std::mem::size_of::<BuildVoxel>() as u64;
    let voxels = AtomicU64::new(0);
    let done = AtomicU64::new(0);
    let total = bins.blocks.len().max(1) as f64;
    let work: Vec<(&BlockKey, &Vec<usize>)> = bins.blocks.iter().collect();
    let run = || {
        work.par_iter()
            .map(|&(&key, segments)| -> Result<Option<SparseBlock>, BuildError> {
                opts.check_cancelled()?;
                let block = with_block_voxelizer(|vox| -> Result<_, BuildError> {
                    for &s in segments {
                        let (_, raw) = bins.store.read(s).map_err(temp_err)?;
                        for record in raw.chunks_exact(rec) {
                            let (tri, color) = bins.layout.decode(record);
                            // Valid: pass 2 binned only triangles that `to_grid` accepted,
                            // and the same arithmetic gives the same grid triangle here.
                            let g = to_grid_unchecked(tri, frame);
                            vox.add(key, &g, bins.layout.color.then_some(color), res, topology);
                        }
                    }
                    Ok(vox.finish(key))
                })?;
                let n = block.as_ref().map_or(0, |b| b.voxels.len() as u64);
                if voxels.fetch_add(n, Ordering::Relaxed) + n > voxel_cap {
                    return Err(BuildError::Ingest(IngestError::TooLarge(format!(
                        "level 0 holds more than {voxel_cap} voxels ({} bytes each), more than the memory \
                         budget of {} bytes: lower --resolution or raise --memory-budget",
                        std::mem::size_of::<BuildVoxel>(),
                        opts.memory_budget
                    ))));
                }
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress.stage(Stage::Voxelize, 0.3 + 0.7 * d as f64 / total);
                Ok(block)
            })
            .collect::<Result<Vec<Option<SparseBlock>>, BuildError>>()
    };
    // Each in-flight block holds one brick: cap the workers so bricks fit a quarter of the budget.
    let max_workers = ((opts.memory_budget / 4) as usize / BLOCK_VOXELIZER_BYTES).max(1);
    let blocks = if rayon::current_num_threads() > max_workers {
        rayon::ThreadPoolBuilder::new()
            .num_threads(max_workers)
            .build()
            .map_err(|e| BuildError::Temp(format!("thread pool: {e}")))?
            .install(run)?
    } else {
        run()?
    };
    Ok((blocks.into_iter().flatten().collect(), stats))
}
