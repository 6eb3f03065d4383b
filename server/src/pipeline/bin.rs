//! Out-of-core voxelization: the build's three passes over the chunked
//! triangle stream ([`crate::pipeline::stream`]), each within the memory budget.
//!
//! 1. **Stream** ([`StreamSink`]): the reader pushes triangles; valid ones
//!    (finite, non-zero area) are packed into chunks, invalid ones are
//!    counted and dropped. The union of the valid triangles' bounds, kept as
//!    they are pushed, gives the grid frame.
//! 2. **Bin** ([`bin_triangles`]): chunks are read back in order and every
//!    triangle's record is appended to the buffer of each 64³ block its
//!    bounds overlap. A full buffer (one chunk's worth) becomes a segment in
//!    the bin store; when all buffers together pass their share of the
//!    budget, every buffer is flushed. Segments of one block stay in input
//!    order. When the whole stream is in memory, nothing is copied: each
//!    block gets the places of its triangles in the stream (4 bytes a
//!    triangle and block, against a record's 36–84), and the stream itself
//!    becomes the bins' store ([`BlockTriangles::Places`]).
//! 3. **Voxelize** ([`voxelize_bin`]): one block's segments, read one at a
//!    time into a reused dense brick, so a block costs one brick and one
//!    segment however many triangles it has. The pipeline runs blocks in the
//!    Morton order of [`Bins::blocks`], in parallel batches.
//!
//! Determinism: passes 1 and 2 do their work on all cores but append it in
//! input order (pass 1: pieces encoded by the readers' workers; pass 2:
//! chunks grouped by block on all cores, appended one group after another),
//! and in pass 3 each block is one thread's work over its triangles in input
//! order, so the output does not depend on the thread count or on where
//! buffers were flushed. Spilled chunks of passes 1 and 2 are compressed
//! and written behind their producer ([`ChunkStore::push_behind`], at most
//! [`PENDING_CHUNKS`] in flight): their ids are still given in push order,
//! so only the spill files' byte layout varies between runs.
//!
//! Memory (shares from [`crate::pipeline::MemoryPlan`]): stream and bin
//! stores keep their resident share of encoded chunks and spill the rest to
//! files in the build's temp dir; bin buffers, with their per-block
//! bookkeeping, stay within their share (all are flushed when they pass it,
//! and the per-block state is dropped with them). What stays is the bin
//! index: 8 bytes a segment here plus the store's location table, counted by
//! [`Bins::index_bytes`].

use std::path::Path;

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use voxstream_format::{BlockKey, GridFrame};

use crate::pipeline::progress::{ProgressSink, Stage};
use crate::pipeline::pyramid::{LodBlock, LodVoxel, block_coord, block_morton};
use crate::pipeline::read::{IngestError, TriangleSink};
use crate::pipeline::stream::{Bounds, ChunkStore, HEADER_LEN, MAX_CHUNK_TRIANGLES, RecordLayout};
use crate::pipeline::voxelize::{
    EdgeHistogram, Topology, block_range, to_grid, to_grid_unchecked, valid_triangle, with_block_voxelizer,
};
use crate::pipeline::{BuildError, BuildOptions, MAX_RECORD_BYTES};

/// Spilled chunks in flight behind their producer at most
/// ([`ChunkStore::push_behind`]); past that the producer writes its own.
pub(crate) const PENDING_CHUNKS: usize = 8;

/// What the chunks in flight hold at most: records and their encoding.
/// Pass 2 holds them beside its stores out of the pyramid's reserve, idle
/// until pass 3 ([`crate::pipeline::MemoryPlan`]).
pub(crate) const CHUNKS_IN_FLIGHT_BYTES: usize =
    PENDING_CHUNKS * 2 * (MAX_CHUNK_TRIANGLES * MAX_RECORD_BYTES + HEADER_LEN);

/// Triangles checked, encoded and measured together on all cores.
const SINK_BATCH: usize = 1 << 14;

/// One triangle as readers hand it over: source positions and linear colour.
pub type SourceTriangle = ([[f64; 3]; 3], [f32; 3]);

/// Triangles checked and encoded as pass 1's records (valid ones only, with
/// their edges' histogram bins), on whatever thread made them; a
/// [`StreamSink`] appends pieces in order.
#[derive(Debug, Default)]
pub struct EncodedPiece {
    pub bytes: Vec<u8>,
    pub bins: Vec<u16>,
    /// Of the valid triangles, as their records hold them.
    pub bounds: Bounds,
    pub valid: u64,
    pub invalid: u64,
}

impl EncodedPiece {
    pub fn with_capacity(layout: RecordLayout, triangles: usize) -> Self {
        Self {
            bytes: Vec::with_capacity(triangles * layout.size()),
            bins: Vec::with_capacity(triangles * 3),
            bounds: Bounds::EMPTY,
            valid: 0,
            invalid: 0,
        }
    }

    /// Encodes a valid triangle; counts an invalid one (non-finite or zero area).
    #[inline]
    pub fn push(&mut self, layout: RecordLayout, tri: &[[f64; 3]; 3], color: [f32; 3]) {
        if valid_triangle(tri) {
            layout.encode(&mut self.bytes, tri, color);
            EdgeHistogram::bins(tri, &mut self.bins);
            self.bounds.add_triangle(&layout.stored(tri));
            self.valid += 1;
        } else {
            self.invalid += 1;
        }
    }
}

/// Pass 1: packs valid triangles into chunks. Triangles come in batches
/// (readers' own, or gathered here from single ones); each batch is checked,
/// encoded and measured on all cores, then appended in file order, so the
/// chunks are the same as one triangle at a time would give.
pub struct StreamSink<'a, 's> {
    pub store: ChunkStore,
    pub layout: RecordLayout,
    /// Bounds of every valid triangle, as the records hold them.
    pub bounds: Bounds,
    pub triangles: u64,
    pub skipped: u64,
    /// Edge lengths of the valid triangles, for `--resolution auto`.
    pub edges: EdgeHistogram,
    raw: Vec<u8>,
    /// Single triangles gathered into a batch.
    gathered: Vec<SourceTriangle>,
    begun: bool,
    on_tick: &'a mut dyn FnMut() -> Result<(), IngestError>,
    /// Where spilled chunks are compressed and written behind the reader.
    behind: &'a rayon::Scope<'s>,
}

impl<'a, 's> StreamSink<'a, 's> {
    /// Spilled chunks are compressed and written by tasks of `behind`
    /// ([`ChunkStore::push_behind`]); the store must be settled after it ends.
    pub fn new(
        store: ChunkStore,
        on_tick: &'a mut dyn FnMut() -> Result<(), IngestError>,
        behind: &'a rayon::Scope<'s>,
    ) -> Self {
        Self {
            store,
            layout: RecordLayout { f64_positions: true, color: false },
            bounds: Bounds::EMPTY,
            triangles: 0,
            skipped: 0,
            edges: EdgeHistogram::default(),
            raw: Vec::new(),
            gathered: Vec::new(),
            begun: false,
            on_tick,
            behind,
        }
    }

    /// Stores the current chunk (one that spills is written behind the reader).
    fn flush(&mut self) -> Result<(), IngestError> {
        if !self.raw.is_empty() {
            let raw = std::mem::replace(
                &mut self.raw,
                Vec::with_capacity(MAX_CHUNK_TRIANGLES * self.layout.size()),
            );
            self.store.push_behind(self.layout, raw, self.behind, PENDING_CHUNKS).map_err(stream_err)?;
        }
        (self.on_tick)()
    }

    /// Checks, encodes and measures a batch on all cores and appends it in order.
    fn push_batch(&mut self, tris: &[SourceTriangle]) -> Result<(), IngestError> {
        let layout = self.layout;
        let pieces: Vec<EncodedPiece> = tris
            .par_chunks(1024)
            .map(|piece| {
                let mut out = EncodedPiece::with_capacity(layout, piece.len());
                for (tri, color) in piece {
                    out.push(layout, tri, *color);
                }
                out
            })
            .collect();
        self.push_pieces(pieces)
    }

    /// Appends pieces encoded elsewhere (in order) to the chunks.
    pub fn push_pieces(&mut self, pieces: impl IntoIterator<Item = EncodedPiece>) -> Result<(), IngestError> {
        // Earlier single triangles first: file order.
        if !self.gathered.is_empty() {
            let gathered = std::mem::take(&mut self.gathered);
            self.push_batch(&gathered)?;
        }
        let chunk_bytes = MAX_CHUNK_TRIANGLES * self.layout.size();
        let mut parts: Vec<Vec<u8>> = Vec::new();
        for EncodedPiece { bytes, bins, bounds, valid, invalid } in pieces {
            self.edges.count(&bins);
            self.bounds.union(&bounds);
            self.triangles += valid;
            self.skipped += invalid;
            parts.push(bytes);
        }
        let mut rest: Vec<&[u8]> = parts.iter().map(|b| b.as_slice()).filter(|b| !b.is_empty()).collect();
        while !rest.is_empty() {
            let room = chunk_bytes - self.raw.len();
            rest = append_on_all_cores(&mut self.raw, rest, room);
            if self.raw.len() == chunk_bytes {
                self.flush()?;
            }
        }
        Ok(())
    }

    /// Writes the last partial chunk.
    pub fn finish(&mut self) -> Result<(), IngestError> {
        let gathered = std::mem::take(&mut self.gathered);
        self.push_batch(&gathered)?;
        self.flush()
    }
}

/// Appends the front of `parts` (in order, up to `room` bytes) to `raw`,
/// copying the parts on all cores, and returns what is left of them.
///
/// Why not `extend_from_slice`: this copy is where a chunk's fresh pages are
/// first touched, and on the reading thread alone it held pass 1 up behind
/// the page faults while the other cores waited.
fn append_on_all_cores<'p>(raw: &mut Vec<u8>, parts: Vec<&'p [u8]>, room: usize) -> Vec<&'p [u8]> {
    use rayon::prelude::*;
    let mut copies: Vec<(&mut [std::mem::MaybeUninit<u8>], &[u8])> = Vec::new();
    let mut left = Vec::new();
    let mut taken = 0;
    raw.reserve(room);
    let mut spare = &mut raw.spare_capacity_mut()[..room];
    for part in parts {
        let take = part.len().min(room - taken);
        if take > 0 {
            let (dst, tail) = std::mem::take(&mut spare).split_at_mut(take);
            spare = tail;
            copies.push((dst, &part[..take]));
            taken += take;
        }
        if take < part.len() {
            left.push(&part[take..]);
        }
    }
    copies.into_par_iter().for_each(|(dst, src)| {
        for (d, s) in dst.iter_mut().zip(src) {
            d.write(*s);
        }
    });
    // SAFETY: the copies above wrote the first `taken` bytes of the spare
    // capacity, each byte once (their destinations are consecutive splits of
    // it, each as long as its source), and `taken <= room <= spare capacity`.
    unsafe { raw.set_len(raw.len() + taken) };
    left
}

impl TriangleSink for StreamSink<'_, '_> {
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
        self.gathered.push((tri, color));
        if self.gathered.len() >= SINK_BATCH {
            let gathered = std::mem::take(&mut self.gathered);
            self.push_batch(&gathered)?;
            self.gathered = gathered;
            self.gathered.clear();
        }
        Ok(())
    }

    fn triangles(&mut self, tris: &[SourceTriangle]) -> Result<(), IngestError> {
        // Earlier single triangles first: file order.
        if !self.gathered.is_empty() {
            let gathered = std::mem::take(&mut self.gathered);
            self.push_batch(&gathered)?;
        }
        self.push_batch(tris)
    }

    fn encoded_layout(&self) -> Option<RecordLayout> {
        self.begun.then_some(self.layout)
    }

    fn pieces(&mut self, pieces: Vec<EncodedPiece>) -> Result<(), IngestError> {
        self.push_pieces(pieces)
    }

    fn tick(&mut self) -> Result<(), IngestError> {
        (self.on_tick)()
    }
}

/// One block's records not yet stored as a segment.
struct BinBuffer {
    morton: u64,
    raw: Vec<u8>,
}

/// Bookkeeping bytes of one active buffer (entry, map slot), counted against the buffer share.
const BUFFER_ENTRY_BYTES: usize = std::mem::size_of::<BinBuffer>() + 32;

/// Segment ids take the low bits of an index entry, the block's Morton code the rest.
const SEGMENT_BITS: u32 = 34;

/// A triangle's place in a resident stream: `chunk << PLACE_CHUNK_SHIFT | record`.
const PLACE_CHUNK_SHIFT: u32 = 14;
const _: () = assert!(MAX_CHUNK_TRIANGLES == 1 << PLACE_CHUNK_SHIFT, "a record index fills the low bits");

/// The most chunks a stream may have for its triangles' places to fit a u32.
const MAX_PLACED_CHUNKS: usize = 1 << (32 - PLACE_CHUNK_SHIFT);

/// Pass 2's result over a stream held whole in memory: the stream is the
/// bins' store, and each block lists the places of its triangles in it.
struct PlaceLists {
    /// Per block, in Morton order: its Morton code and its range of `places`.
    blocks: Vec<(u64, std::ops::Range<usize>)>,
    /// Each block's triangles' places, in input order.
    places: Vec<u32>,
}

/// One block's triangles, as [`Bins::blocks`] gives them to [`voxelize_bin`].
#[derive(Debug, Clone, Copy)]
pub enum BlockTriangles<'a> {
    /// Index entries of its segments in the bin store, in input order.
    Segments(&'a [u64]),
    /// Places of its triangles in the resident stream, in input order.
    Places(&'a [u32]),
}

/// The bins: for each non-empty block, its triangles in input order, either
/// as segments of copied records in the bin store or as places in the
/// stream, which is then the store.
pub struct Bins {
    pub store: ChunkStore,
    pub layout: RecordLayout,
    /// `block_morton << SEGMENT_BITS | segment`, sorted: blocks in Morton
    /// order, each block's segments in input order. Empty with `places`.
    index: Vec<u64>,
    places: Option<PlaceLists>,
    /// Triangles that became degenerate or non-finite in grid units.
    pub skipped: u64,
    pub triangles: u64,
}

impl Bins {
    /// The non-empty level-0 blocks in Morton order, each with its triangles.
    pub fn blocks(&self) -> impl Iterator<Item = (BlockKey, BlockTriangles<'_>)> {
        let key = |m: u64| {
            let c = block_coord(m);
            BlockKey::new(0, c[0], c[1], c[2])
        };
        let segments = self
            .index
            .chunk_by(|a, b| a >> SEGMENT_BITS == b >> SEGMENT_BITS)
            .map(move |segs| (key(segs[0] >> SEGMENT_BITS), BlockTriangles::Segments(segs)));
        let places = self.places.iter().flat_map(move |p| {
            p.blocks.iter().map(move |(m, range)| (key(*m), BlockTriangles::Places(&p.places[range.clone()])))
        });
        segments.chain(places)
    }

    /// Whether the blocks list places in the resident stream (no records were copied).
    pub fn placed(&self) -> bool {
        self.places.is_some()
    }

    pub fn block_count(&self) -> usize {
        self.blocks().count()
    }

    /// Memory the index holds while the blocks are voxelized (it grows with the input).
    pub fn index_bytes(&self) -> usize {
        let places = self.places.as_ref().map_or(0, |p| {
            p.places.capacity() * 4
                + p.blocks.capacity() * std::mem::size_of::<(u64, std::ops::Range<usize>)>()
        });
        self.index.capacity() * 8 + places + self.store.index_bytes()
    }
}

/// A failure of pass 1's temporary triangle stream, as the reader reports it.
pub(crate) fn stream_err(e: crate::pipeline::stream::ChunkError) -> IngestError {
    IngestError::Invalid(format!("temporary triangle stream: {e}"))
}

fn temp_err(e: crate::pipeline::stream::ChunkError) -> BuildError {
    BuildError::Temp(e.to_string())
}

/// Stream chunks read, placed and grouped by block together, on all cores.
const BIN_GROUP_PER_THREAD: usize = 2;

/// A chunk whose triangles make more block records than this is binned one
/// triangle at a time instead (its grouped copy would hold them all).
const LOCAL_RECORDS: usize = 2 * MAX_CHUNK_TRIANGLES;

/// The most one chunk takes while it is grouped: the chunk as stored and
/// decoded, and its records grouped by block (capacity up to twice).
pub const BIN_CHUNK_BYTES: usize = 2 * (HEADER_LEN + MAX_CHUNK_TRIANGLES * MAX_RECORD_BYTES)
    + 2 * LOCAL_RECORDS * MAX_RECORD_BYTES
    + (64 << 10);

/// One stream chunk's valid records grouped by the blocks they overlap:
/// blocks in first-hit order, each block's records in input order.
struct Grouped {
    /// (block Morton code, records)
    blocks: Vec<(u64, Vec<u8>)>,
    triangles: u64,
    skipped: u64,
}

/// A chunk ready to be appended to the bins.
enum Placed {
    Grouped(Grouped),
    /// Too many block records to group: appended one triangle at a time.
    Raw(Vec<u8>),
}

/// The bin buffers and store of pass 2 (appends are serial, in input order).
struct Binner {
    layout: RecordLayout,
    store: ChunkStore,
    /// Buffers in first-hit order, found through a map.
    buffers: Vec<BinBuffer>,
    lookup: FxHashMap<u64, usize>,
    buffered: usize,
    buffer_limit: usize,
    index: Vec<u64>,
    /// Full buffers wait here (block, records) and are stored together.
    pending: Vec<(u64, Vec<u8>)>,
    /// Emptied stream chunks, each a segment's full capacity, for new buffers
    /// to fill: memory already touched, where a fresh buffer costs a page
    /// fault every 4 KiB.
    spare: Vec<Vec<u8>>,
    triangles: u64,
    skipped: u64,
}

/// Blocks in the closed range `blo..=bhi` (saturating: a range can hold more than a usize counts).
fn blocks_in((blo, bhi): ([u32; 3], [u32; 3])) -> usize {
    (0..3).map(|a| (bhi[a] - blo[a] + 1) as usize).fold(1, usize::saturating_mul)
}

/// Where one triangle goes: its block range (closed); `None` when invalid in grid units.
#[inline]
fn place(layout: RecordLayout, record: &[u8], frame: &GridFrame) -> Option<([u32; 3], [u32; 3])> {
    let (tri, _) = layout.decode(record);
    let g = to_grid(tri, frame)?;
    Some(block_range(&g, frame.resolution as i64))
}

impl Binner {
    fn new(layout: RecordLayout, store: ChunkStore, buffer_limit: usize) -> Self {
        Self {
            layout,
            store,
            buffers: Vec::new(),
            lookup: FxHashMap::default(),
            buffered: 0,
            buffer_limit,
            index: Vec::new(),
            pending: Vec::new(),
            spare: Vec::new(),
            triangles: 0,
            skipped: 0,
        }
    }

    /// The bins, once every buffer is flushed and the scope the segments
    /// were written behind in has ended.
    fn into_bins(mut self) -> Result<Bins, BuildError> {
        self.store.settle_behind().map_err(temp_err)?;
        let Binner { store, layout, mut index, triangles, skipped, .. } = self;
        index.sort_unstable();
        index.shrink_to_fit();
        Ok(Bins { store, layout, index, places: None, skipped, triangles })
    }

    fn take(b: &mut BinBuffer, pending: &mut Vec<(u64, Vec<u8>)>) {
        if !b.raw.is_empty() {
            // Moved out, not cleared: idle blocks must not keep their high-water capacity.
            pending.push((b.morton, std::mem::take(&mut b.raw)));
        }
    }

    /// Stores the full buffers as segments; those that spill are compressed
    /// and written by tasks of `scope`, beside the appends.
    fn drain(&mut self, scope: &rayon::Scope<'_>) -> Result<(), BuildError> {
        for (m, raw) in self.pending.drain(..) {
            let id = self.store.push_behind(self.layout, raw, scope, PENDING_CHUNKS).map_err(temp_err)?;
            if id as u64 >= 1 << SEGMENT_BITS {
                return Err(BuildError::Temp(format!("more than 2^{SEGMENT_BITS} bin segments")));
            }
            self.index.push(m << SEGMENT_BITS | id as u64);
        }
        Ok(())
    }

    /// Every buffer goes, bookkeeping included, so many blocks cost no more than few.
    fn flush_all(&mut self, scope: &rayon::Scope<'_>) -> Result<(), BuildError> {
        for buf in &mut self.buffers {
            Self::take(buf, &mut self.pending);
        }
        self.drain(scope)?;
        self.buffers = Vec::new();
        self.lookup = FxHashMap::default();
        self.buffered = 0;
        Ok(())
    }

    /// Appends whole records of block `m`,
    /// storing a buffer as a segment when it is full and flushing every
    /// buffer as soon as they pass their limit, as one record at a time would.
    fn append(&mut self, m: u64, records: &[u8], scope: &rayon::Scope<'_>) -> Result<(), BuildError> {
        let rec = self.layout.size();
        let full = MAX_CHUNK_TRIANGLES * rec;
        let mut rest = records;
        while !rest.is_empty() {
            let i = match self.lookup.get(&m) {
                Some(&i) => i,
                None => {
                    self.buffers.push(BinBuffer { morton: m, raw: Vec::new() });
                    self.buffered += BUFFER_ENTRY_BYTES;
                    self.lookup.insert(m, self.buffers.len() - 1);
                    self.buffers.len() - 1
                }
            };
            let buf = &mut self.buffers[i];
            if buf.raw.capacity() == 0
                && let Some(mut spare) = self.spare.pop()
            {
                spare.clear();
                buf.raw = spare;
            }
            // Up to the buffer's end, and up to the record that passes the limit.
            let allowed = (self.buffer_limit.saturating_sub(self.buffered) / rec + 1) * rec;
            let take = (full - buf.raw.len()).min(allowed).min(rest.len());
            let (now, later) = rest.split_at(take);
            buf.raw.extend_from_slice(now);
            self.buffered += take;
            rest = later;
            if buf.raw.len() >= full {
                self.buffered -= buf.raw.len();
                Self::take(buf, &mut self.pending);
                self.drain(scope)?;
            }
            if self.buffered > self.buffer_limit {
                self.flush_all(scope)?;
            }
        }
        Ok(())
    }

    fn append_placed(
        &mut self,
        placed: Placed,
        frame: &GridFrame,
        scope: &rayon::Scope<'_>,
    ) -> Result<(), BuildError> {
        match placed {
            Placed::Grouped(g) => {
                self.triangles += g.triangles;
                self.skipped += g.skipped;
                for (m, records) in &g.blocks {
                    self.append(*m, records, scope)?;
                }
            }
            Placed::Raw(raw) => {
                for record in raw.chunks_exact(self.layout.size()) {
                    let Some((blo, bhi)) = place(self.layout, record, frame) else {
                        self.skipped += 1;
                        continue;
                    };
                    self.triangles += 1;
                    for bz in blo[2]..=bhi[2] {
                        for by in blo[1]..=bhi[1] {
                            for bx in blo[0]..=bhi[0] {
                                self.append(block_morton([bx, by, bz]), record, scope)?;
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// The blocks a chunk's triangles reach, in first-hit order: each block's
/// slot found through a map, the last hit cached (neighbouring triangles
/// mostly share a block).
#[derive(Default)]
struct BlockSlots {
    lookup: FxHashMap<u64, usize>,
    last: Option<(u64, usize)>,
}

impl BlockSlots {
    /// Calls `f` with the Morton code and slot in `blocks` of every block in
    /// the closed range `blo..=bhi`; a block seen first gets `new(m)` pushed.
    fn each<T>(
        &mut self,
        (blo, bhi): ([u32; 3], [u32; 3]),
        blocks: &mut Vec<T>,
        new: impl Fn(u64) -> T,
        mut f: impl FnMut(&mut T),
    ) {
        for bz in blo[2]..=bhi[2] {
            for by in blo[1]..=bhi[1] {
                for bx in blo[0]..=bhi[0] {
                    let m = block_morton([bx, by, bz]);
                    let i = match self.last {
                        Some((k, i)) if k == m => i,
                        _ => {
                            let i = *self.lookup.entry(m).or_insert_with(|| {
                                blocks.push(new(m));
                                blocks.len() - 1
                            });
                            self.last = Some((m, i));
                            i
                        }
                    };
                    f(&mut blocks[i]);
                }
            }
        }
    }
}

/// Groups one stream chunk's records by block (on a worker thread).
fn group_chunk(layout: RecordLayout, raw: &[u8], frame: &GridFrame) -> Placed {
    let rec = layout.size();
    let mut blocks: Vec<(u64, Vec<u8>)> = Vec::new();
    let mut slots = BlockSlots::default();
    let (mut triangles, mut skipped, mut records) = (0u64, 0u64, 0usize);
    for record in raw.chunks_exact(rec) {
        let Some((blo, bhi)) = place(layout, record, frame) else {
            skipped += 1;
            continue;
        };
        triangles += 1;
        records = records.saturating_add(blocks_in((blo, bhi)));
        if records > LOCAL_RECORDS {
            return Placed::Raw(raw.to_vec());
        }
        slots.each((blo, bhi), &mut blocks, |m| (m, Vec::new()), |b| b.1.extend_from_slice(record));
    }
    Placed::Grouped(Grouped { blocks, triangles, skipped })
}

/// One chunk's triangles' places grouped by the blocks they overlap (blocks
/// in first-hit order, each block's places in input order).
struct ChunkPlaces {
    blocks: Vec<(u64, Vec<u32>)>,
    places: usize,
    triangles: u64,
    skipped: u64,
}

/// [`ChunkPlaces`] of stream chunk `chunk`; `None` when they pass `cap` places.
fn place_chunk(
    layout: RecordLayout,
    raw: &[u8],
    chunk: usize,
    frame: &GridFrame,
    cap: usize,
) -> Option<ChunkPlaces> {
    let mut out = ChunkPlaces { blocks: Vec::new(), places: 0, triangles: 0, skipped: 0 };
    let mut slots = BlockSlots::default();
    for (r, record) in raw.chunks_exact(layout.size()).enumerate() {
        let Some((blo, bhi)) = place(layout, record, frame) else {
            out.skipped += 1;
            continue;
        };
        out.triangles += 1;
        // Counted before any is pushed: one large triangle can reach millions of blocks.
        out.places = out.places.saturating_add(blocks_in((blo, bhi)));
        if out.places > cap {
            return None;
        }
        let at = (chunk as u32) << PLACE_CHUNK_SHIFT | r as u32;
        slots.each((blo, bhi), &mut out.blocks, |m| (m, Vec::new()), |b| b.1.push(at));
    }
    Some(out)
}

/// Pass 2 over a stream held whole in memory: every chunk's places grouped
/// on all cores, then laid out block by block (Morton order), each block's
/// in input order. `None` (the stream untouched) when the places would take
/// more than `limit` bytes, grouped and laid out together.
fn place_lists(
    stream: &ChunkStore,
    layout: RecordLayout,
    frame: &GridFrame,
    limit: usize,
) -> Result<Option<(PlaceLists, u64, u64)>, BuildError> {
    // Grouped and laid out, each place is held twice for a moment.
    let cap = limit / 8;
    let grouped: Option<Vec<ChunkPlaces>> = (0..stream.len())
        .into_par_iter()
        .map(|id| {
            let raw = stream.resident_records(id).expect("every chunk is resident");
            place_chunk(layout, raw, id, frame, cap)
        })
        .collect();
    let Some(grouped) = grouped else { return Ok(None) };
    let total: usize = grouped.iter().map(|g| g.places).sum();
    if total > cap {
        return Ok(None);
    }
    let mut counts: FxHashMap<u64, usize> = FxHashMap::default();
    for g in &grouped {
        for (m, list) in &g.blocks {
            *counts.entry(*m).or_default() += list.len();
        }
    }
    let mut mortons: Vec<u64> = counts.keys().copied().collect();
    mortons.sort_unstable();
    let mut blocks = Vec::with_capacity(mortons.len());
    let mut start = 0;
    for m in mortons {
        let n = counts[&m];
        counts.insert(m, start);
        blocks.push((m, start..start + n));
        start += n;
    }
    // `counts` now holds each block's next free place.
    let mut places = vec![0u32; total];
    let (mut triangles, mut skipped) = (0, 0);
    for g in grouped {
        triangles += g.triangles;
        skipped += g.skipped;
        for (m, list) in g.blocks {
            let at = counts.get_mut(&m).expect("counted");
            places[*at..*at + list.len()].copy_from_slice(&list);
            *at += list.len();
        }
    }
    Ok(Some((PlaceLists { blocks, places }, triangles, skipped)))
}

/// Pass 2: bins the stream's triangles by the 64³ blocks they overlap.
/// `resident` bytes of segments stay in memory; buffers and their
/// bookkeeping are flushed when they pass `buffer_limit` bytes (counted by
/// length; capacities reach at most twice that). Chunks are read and grouped
/// by block on all cores, `group_bytes` of them at a time (three groups
/// alive: one grouping, one waiting and one being appended in input order on
/// a thread of its own, [`append_in_order`]); a budget too small for three
/// chunks bins one chunk at a time.
pub fn bin_triangles(
    stream: &mut ChunkStore,
    layout: RecordLayout,
    frame: &GridFrame,
    spill_path: &Path,
    (resident, buffer_limit, group_bytes): (usize, usize, usize),
    opts: &BuildOptions,
    progress: &ProgressSink,
) -> Result<Bins, BuildError> {
    if stream.all_resident() && stream.len() <= MAX_PLACED_CHUNKS {
        opts.check_cancelled()?;
        if let Some((places, triangles, skipped)) = place_lists(stream, layout, frame, resident)? {
            progress.stage(Stage::Voxelize, 0.3);
            // The stream is the store now; the caller keeps an empty one.
            let store = std::mem::replace(stream, ChunkStore::new(spill_path, 0));
            return Ok(Bins { store, layout, index: Vec::new(), places: Some(places), skipped, triangles });
        }
    }
    let mut binner = Binner::new(layout, ChunkStore::new(spill_path, resident), buffer_limit);
    // Three groups alive at most: one grouping, one waiting, one being appended.
    let group = (group_bytes / 3 / BIN_CHUNK_BYTES).min(BIN_GROUP_PER_THREAD * rayon::current_num_threads());
    let read_group = |stream: &ChunkStore, ids: std::ops::Range<usize>| -> Result<Vec<Placed>, BuildError> {
        ids.into_par_iter()
            .map(|id| stream.with_records(id, |raw| Ok(group_chunk(layout, raw, frame))).map_err(temp_err))
            .collect()
    };
    let total = stream.len();
    if group == 0 {
        // Spilled segments are compressed and written by tasks of this scope; it
        // ends when the last is written.
        rayon::scope(|scope| -> Result<(), BuildError> {
            for id in 0..total {
                opts.check_cancelled()?;
                let raw = stream.read(id).map_err(temp_err)?;
                binner.append_placed(Placed::Raw(raw), frame, scope)?;
                progress.stage(Stage::Voxelize, 0.3 * (id + 1) as f64 / total as f64);
            }
            binner.flush_all(scope)
        })?;
        return binner.into_bins();
    }
    // A full chunk's buffer: the capacity a spare must have to hold a whole segment.
    let segment_bytes = MAX_CHUNK_TRIANGLES * layout.size();
    let (to_appender, batches) = std::sync::mpsc::sync_channel::<AppendBatch>(1);
    // The scope is this thread's, so the appender's spilled segments are written on the
    // pool the build runs in (the one `install`ed, or the global one), not the global one.
    let (produced, appended) = rayon::in_place_scope(|scope| {
        std::thread::scope(|s| {
            let appender = s.spawn(move || -> Result<Binner, BuildError> {
                append_in_order(&mut binner, batches, frame, scope)?;
                Ok(binner)
            });
            let produced = (|| -> Result<(), BuildError> {
                let mut next = 0;
                while next < total {
                    opts.check_cancelled()?;
                    let ids = next..(next + group).min(total);
                    next = ids.end;
                    let grouped = read_group(stream, ids.clone())?;
                    // Grouped copies hold these chunks' records now.
                    let spares = ids
                        .filter_map(|id| {
                            stream.take_resident(id).filter(|raw| raw.capacity() == segment_bytes)
                        })
                        .collect();
                    if to_appender.send((grouped, spares)).is_err() {
                        return Ok(()); // the appender stopped: its error is the build's
                    }
                    progress.stage(Stage::Voxelize, 0.3 * next as f64 / total.max(1) as f64);
                }
                Ok(())
            })();
            drop(to_appender);
            (produced, appender.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
        })
    });
    // The appender's error first: the producer only saw its channel close.
    let binner = appended?;
    produced?;
    binner.into_bins()
}

/// Groups to append in order, and emptied resident chunks for new buffers.
type AppendBatch = (Vec<Placed>, Vec<Vec<u8>>);

/// The appending half of pass 2, on a thread of its own: appends each batch
/// of groups in order (and takes its spare buffers) while the producer reads
/// and groups the next; spilled segments are compressed and written by
/// tasks of `scope`, behind the appends. Flushes every buffer once the batches end.
fn append_in_order(
    binner: &mut Binner,
    batches: std::sync::mpsc::Receiver<AppendBatch>,
    frame: &GridFrame,
    scope: &rayon::Scope<'_>,
) -> Result<(), BuildError> {
    for (placed, spares) in batches {
        binner.spare.extend(spares);
        for p in placed {
            binner.append_placed(p, frame, scope)?;
        }
    }
    binner.flush_all(scope)
}

/// Pass 3 for one block: voxelizes its segments (in input order) into a
/// level-0 block in pyramid form, faces not yet marked; `None` when empty.
pub fn voxelize_bin(
    bins: &Bins,
    key: BlockKey,
    triangles: BlockTriangles,
    frame: &GridFrame,
    topology: Topology,
) -> Result<Option<LodBlock>, BuildError> {
    let res = frame.resolution as i64;
    let rec = bins.layout.size();
    with_block_voxelizer(|vox| -> Result<_, BuildError> {
        let mut add = |record: &[u8]| {
            let (tri, color) = bins.layout.decode(record);
            // Valid: pass 2 binned only triangles that `to_grid` accepted,
            // and the same arithmetic gives the same grid triangle here.
            let g = to_grid_unchecked(tri, frame);
            vox.add(key, &g, bins.layout.color.then_some(color), res, topology);
        };
        match triangles {
            BlockTriangles::Segments(index) => {
                for &entry in index {
                    let segment = (entry & ((1 << SEGMENT_BITS) - 1)) as usize;
                    bins.store
                        .with_records(segment, |raw| {
                            raw.chunks_exact(rec).for_each(&mut add);
                            Ok(())
                        })
                        .map_err(temp_err)?;
                }
            }
            BlockTriangles::Places(places) => {
                let (mut chunk, mut raw) = (usize::MAX, &[][..]);
                for &at in places {
                    let (c, r) =
                        ((at >> PLACE_CHUNK_SHIFT) as usize, (at & ((1 << PLACE_CHUNK_SHIFT) - 1)) as usize);
                    if c != chunk {
                        raw = bins
                            .store
                            .resident_records(c)
                            .ok_or_else(|| BuildError::Temp(format!("stream chunk {c} is not in memory")))?;
                        chunk = c;
                    }
                    let record = raw
                        .get(r * rec..(r + 1) * rec)
                        .ok_or_else(|| BuildError::Temp(format!("stream chunk {c} has no record {r}")))?;
                    add(record);
                }
            }
        }
        let voxels = vox.finish_map(|voxel| LodVoxel { voxel, solid: 1, error: 0.0 });
        Ok((!voxels.is_empty()).then_some(LodBlock { key, voxels }))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::Resolution;
    use crate::pipeline::voxelize::choose_resolution;

    /// 40,000 triangles of three sizes: slivers inside one voxel, and ones
    /// across block faces and corners, with colours.
    fn triangles() -> Vec<SourceTriangle> {
        let mut out = Vec::new();
        let mut s = 1u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..40_000 {
            let size = [0.002, 0.02, 0.3][i % 3];
            let a = [rnd(), rnd(), rnd()];
            let tri = [
                a,
                [a[0] + size * rnd(), a[1] + size * rnd(), a[2]],
                [a[0], a[1] + size * rnd(), a[2] + size],
            ];
            out.push((tri, [rnd() as f32, 0.5, 0.25]));
        }
        out
    }

    fn stream(dir: &Path, tris: &[SourceTriangle]) -> (ChunkStore, RecordLayout, GridFrame) {
        let mut tick = || Ok(());
        let (mut store, layout, bounds) = rayon::scope(|scope| {
            let store = ChunkStore::new(&dir.join("stream.vxt"), 1 << 30);
            let mut sink = StreamSink::new(store, &mut tick, scope);
            sink.begin(RecordLayout { f64_positions: false, color: true }).unwrap();
            sink.triangles(tris).unwrap();
            sink.finish().unwrap();
            (sink.store, sink.layout, sink.bounds)
        });
        store.settle_behind().unwrap();
        let (frame, _) = choose_resolution(&bounds, Resolution::Explicit(256), None, 256, 0).unwrap();
        (store, layout, frame)
    }

    fn bin(dir: &Path, tris: &[SourceTriangle], resident: usize) -> (Bins, GridFrame) {
        let (mut store, layout, frame) = stream(dir, tris);
        let progress = ProgressSink::new(&|_| {});
        let limits = (resident, 1 << 20, 64 << 20);
        let bins = bin_triangles(
            &mut store,
            layout,
            &frame,
            &dir.join("bins.vxt"),
            limits,
            &BuildOptions::default(),
            &progress,
        )
        .unwrap();
        (bins, frame)
    }

    /// Fails if a resident stream is not binned by places, if a budget too
    /// small for the places does not fall back to copied segments, or if the
    /// two give any block other voxels (the order of a block's triangles
    /// decides the sums' rounding, so an order change shows).
    #[test]
    fn places_in_the_stream_bin_like_copied_segments() {
        let dir = tempfile::tempdir().unwrap();
        let tris = triangles();
        let (placed, frame) = bin(dir.path(), &tris, 64 << 20);
        let small = dir.path().join("small");
        std::fs::create_dir(&small).unwrap();
        let (copied, _) = bin(&small, &tris, 4 << 10);
        assert!(placed.placed() && !copied.placed());
        assert!(copied.store.spilled_bytes() > 0, "the small budget spills segments");
        assert_eq!((placed.triangles, placed.skipped), (copied.triangles, copied.skipped));
        let a: Vec<_> = placed.blocks().collect();
        let b: Vec<_> = copied.blocks().collect();
        assert_eq!(a.iter().map(|x| x.0).collect::<Vec<_>>(), b.iter().map(|x| x.0).collect::<Vec<_>>());
        assert!(a.len() > 8, "the triangles reach many blocks: {}", a.len());
        for ((key, pa), (_, pb)) in a.into_iter().zip(b) {
            let va = voxelize_bin(&placed, key, pa, &frame, Topology::Conservative).unwrap();
            let vb = voxelize_bin(&copied, key, pb, &frame, Topology::Conservative).unwrap();
            assert_eq!(va.map(|b| b.voxels), vb.map(|b| b.voxels), "block {key:?}");
        }
    }

    /// Fails if a failure of the appending thread (here: its spill file cannot
    /// be created) is lost or panics instead of failing pass 2.
    #[test]
    fn an_append_that_fails_fails_the_pass() {
        let dir = tempfile::tempdir().unwrap();
        let (mut store, layout, frame) = stream(dir.path(), &triangles());
        let progress = ProgressSink::new(&|_| {});
        let got = bin_triangles(
            &mut store,
            layout,
            &frame,
            &dir.path().join("missing").join("bins.vxt"),
            (4 << 10, 1 << 20, 64 << 20),
            &BuildOptions::default(),
            &progress,
        );
        assert!(matches!(&got, Err(BuildError::Temp(m)) if m.contains("bins.vxt")), "{:?}", got.err());
    }

    /// Fails if appending parts on all cores loses, repeats or reorders a
    /// byte, passes the room, or hands back other leftovers than the parts'
    /// unappended tails: compared with one serial concatenation, for parts of
    /// many sizes (empty ones too) and rooms that end inside, between and past them.
    #[test]
    fn appending_on_all_cores_is_one_concatenation() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(21);
        for _ in 0..300 {
            let parts: Vec<Vec<u8>> = (0..rng.random_range(1..20))
                .map(|_| (0..rng.random_range(0..3000)).map(|_| rng.random()).collect())
                .collect();
            let whole: Vec<u8> = parts.concat();
            let mut raw: Vec<u8> = (0..rng.random_range(0..100)).map(|_| rng.random()).collect();
            let mut expected = raw.clone();
            let room = rng.random_range(0..whole.len() + 50);
            let taken = room.min(whole.len());
            expected.extend_from_slice(&whole[..taken]);
            let left = append_on_all_cores(&mut raw, parts.iter().map(|p| p.as_slice()).collect(), room);
            assert_eq!(raw, expected);
            assert_eq!(left.concat(), whole[taken..]);
            assert!(left.iter().all(|p| !p.is_empty()));
        }
    }

    /// Fails if a place that points past its chunk panics instead of failing the build.
    #[test]
    fn a_place_outside_the_stream_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let (bins, frame) = bin(dir.path(), &triangles(), 64 << 20);
        let (key, _) = bins.blocks().next().unwrap();
        // Three chunks: two full ones and 40,000 − 32,768 records in the last.
        assert_eq!(bins.store.len(), 3);
        for bad in [3u32 << PLACE_CHUNK_SHIFT, 2 << PLACE_CHUNK_SHIFT | 7_232] {
            let err =
                voxelize_bin(&bins, key, BlockTriangles::Places(&[bad]), &frame, Topology::Conservative);
            assert!(matches!(err, Err(BuildError::Temp(_))), "{bad}: {err:?}");
        }
    }
}
