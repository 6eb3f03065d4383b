//! The chunked triangle stream: how triangles travel between the build's
//! passes without the whole mesh ever sitting in memory.
//!
//! A stream is a sequence of chunks. Each chunk is a fixed 20-byte header
//! followed by its payload:
//!
//! ```text
//! offset size  field
//!      0    4  magic "VXTC"
//!      4    1  flags: bit 0 = positions are f64 (else f32), bit 1 = a colour per triangle
//!      5    1  codec: 0 = raw, 1 = one lz4_flex block
//!      6    2  reserved, 0
//!      8    4  triangle count (u32 LE, 1..=MAX_CHUNK_TRIANGLES)
//!     12    4  raw payload length (u32 LE, = count × record size)
//!     16    4  stored payload length (u32 LE)
//!     20    …  payload
//! ```
//!
//! No bounds: no reader needs a chunk's, and finding them cost a decode of
//! every spilled record (about 4 % of a triangle-bound build).
//!
//! The raw payload is `count` records, each 9 coordinates (v0 xyz, v1 xyz,
//! v2 xyz; f32 or f64 LE) then, with bit 1, a linear RGB colour in [0, 1]
//! as 3 × f32 LE. Readers whose source coordinates are f32 (binary STL,
//! float PLY) store f32, so a stream is a lossless copy of the input at half
//! the bytes; everything else stores f64.
//!
//! Chunks live in a [`ChunkStore`]: in memory (the records' own buffer,
//! no header) until the store's resident limit, then encoded and appended
//! to a spill file. [`ChunkStore::push_behind`] hands a spilling chunk's
//! encoding and write to a pool task, so a producer that must append in
//! input order is not held up by lz4 and the disk: each write reserves its
//! range at the file's atomic end, so chunk ids keep push order while the
//! file's layout may differ from run to run (its content never does).
//! Readers of our own chunks still
//! check every length before allocating: the decompressed size is capped by
//! the header's count, which is capped by [`MAX_CHUNK_TRIANGLES`].

use std::fs::File;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// Triangles per chunk at most (and per bin segment).
pub const MAX_CHUNK_TRIANGLES: usize = 1 << 14;
pub const HEADER_LEN: usize = 20;
const MAGIC: &[u8; 4] = b"VXTC";
const FLAG_F64: u8 = 1;
const FLAG_COLOR: u8 = 2;
const CODEC_RAW: u8 = 0;
const CODEC_LZ4: u8 = 1;

/// What a stream's records hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordLayout {
    /// Coordinates are f64; otherwise f32 (exact for sources read as f32).
    pub f64_positions: bool,
    /// A linear RGB colour follows the coordinates.
    pub color: bool,
}

impl RecordLayout {
    /// The largest record: f64 coordinates and a colour.
    const MAX_SIZE: usize = Self { f64_positions: true, color: true }.size();

    pub const fn size(self) -> usize {
        (if self.f64_positions { 72 } else { 36 }) + if self.color { 12 } else { 0 }
    }

    fn flags(self) -> u8 {
        (if self.f64_positions { FLAG_F64 } else { 0 }) | if self.color { FLAG_COLOR } else { 0 }
    }

    fn from_flags(flags: u8) -> Option<Self> {
        (flags & !(FLAG_F64 | FLAG_COLOR) == 0)
            .then_some(Self { f64_positions: flags & FLAG_F64 != 0, color: flags & FLAG_COLOR != 0 })
    }

    /// Appends one record.
    #[inline]
    pub fn encode(self, out: &mut Vec<u8>, tri: &[[f64; 3]; 3], color: [f32; 3]) {
        // Built on the stack and appended once: one capacity check a record, not one a value.
        let mut rec = [0u8; Self::MAX_SIZE];
        let mut at = 0;
        for c in tri.as_flattened() {
            if self.f64_positions {
                rec[at..at + 8].copy_from_slice(&c.to_le_bytes());
                at += 8;
            } else {
                rec[at..at + 4].copy_from_slice(&(*c as f32).to_le_bytes());
                at += 4;
            }
        }
        if self.color {
            for c in color {
                rec[at..at + 4].copy_from_slice(&c.to_le_bytes());
                at += 4;
            }
        }
        out.extend_from_slice(&rec[..at]);
    }

    /// A triangle's corners as its record holds them (f32-rounded unless
    /// the layout keeps f64): what [`Self::decode`] gives back.
    #[inline]
    pub fn stored(self, tri: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
        if self.f64_positions { *tri } else { tri.map(|p| p.map(|c| c as f32 as f64)) }
    }

    /// Decodes one record of exactly [`Self::size`] bytes.
    pub fn decode(self, rec: &[u8]) -> ([[f64; 3]; 3], [f32; 3]) {
        let mut tri = [[0.0; 3]; 3];
        let w = if self.f64_positions { 8 } else { 4 };
        for (k, c) in tri.as_flattened_mut().iter_mut().enumerate() {
            let b = &rec[k * w..(k + 1) * w];
            *c = if self.f64_positions {
                f64::from_le_bytes(b.try_into().expect("8 bytes"))
            } else {
                f32::from_le_bytes(b.try_into().expect("4 bytes")) as f64
            };
        }
        let mut color = [0.0f32; 3];
        if self.color {
            let at = 9 * w;
            for (k, c) in color.iter_mut().enumerate() {
                *c = f32::from_le_bytes(rec[at + 4 * k..at + 4 * k + 4].try_into().expect("4 bytes"));
            }
        }
        (tri, color)
    }
}

/// Bounds of vertices, in f64 source coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Default for Bounds {
    fn default() -> Self {
        Bounds::EMPTY
    }
}

impl Bounds {
    pub const EMPTY: Bounds = Bounds { min: [f64::INFINITY; 3], max: [f64::NEG_INFINITY; 3] };

    pub fn is_empty(&self) -> bool {
        self.min[0].partial_cmp(&self.max[0]).is_none_or(|o| o.is_gt())
    }

    pub fn add_triangle(&mut self, tri: &[[f64; 3]; 3]) {
        for p in tri {
            self.union(&Bounds { min: *p, max: *p });
        }
    }

    pub fn union(&mut self, other: &Bounds) {
        for a in 0..3 {
            self.min[a] = self.min[a].min(other.min[a]);
            self.max[a] = self.max[a].max(other.max[a]);
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChunkHeader {
    pub layout: RecordLayout,
    pub triangles: u32,
    codec: u8,
    raw_len: u32,
    stored_len: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum ChunkError {
    #[error("{action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: io::Error },
    #[error("damaged triangle chunk: {0}")]
    Damaged(String),
}

/// Encodes `raw` (whole records of `layout`) as one chunk: lz4, or raw when
/// lz4 saves nothing.
pub fn encode_chunk(layout: RecordLayout, raw: &[u8]) -> Vec<u8> {
    let triangles = raw.len() / layout.size();
    debug_assert!(raw.len().is_multiple_of(layout.size()) && triangles <= MAX_CHUNK_TRIANGLES);
    let packed = lz4_flex::block::compress(raw);
    let (codec, payload) = if packed.len() < raw.len() { (CODEC_LZ4, &packed[..]) } else { (CODEC_RAW, raw) };
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[layout.flags(), codec, 0, 0]);
    for n in [triangles, raw.len(), payload.len()] {
        out.extend_from_slice(&(n as u32).to_le_bytes());
    }
    out.extend_from_slice(payload);
    out
}

pub fn decode_header(bytes: &[u8]) -> Result<ChunkHeader, ChunkError> {
    let damaged = |m: &str| ChunkError::Damaged(m.to_string());
    let h = bytes.get(..HEADER_LEN).ok_or_else(|| damaged("shorter than its header"))?;
    if &h[..4] != MAGIC {
        return Err(damaged("bad magic"));
    }
    let layout = RecordLayout::from_flags(h[4]).ok_or_else(|| damaged("unknown flags"))?;
    let u32_at = |o: usize| u32::from_le_bytes(h[o..o + 4].try_into().expect("4 bytes"));
    let (triangles, raw_len, stored_len) = (u32_at(8), u32_at(12), u32_at(16));
    if triangles == 0
        || triangles as usize > MAX_CHUNK_TRIANGLES
        || raw_len as usize != triangles as usize * layout.size()
        || (h[5] == CODEC_RAW && stored_len != raw_len)
        || h[5] > CODEC_LZ4
    {
        return Err(damaged("inconsistent counts"));
    }
    Ok(ChunkHeader { layout, triangles, codec: h[5], raw_len, stored_len })
}

/// Decodes a whole chunk into its header and raw records.
pub fn decode_chunk(bytes: &[u8]) -> Result<(ChunkHeader, Vec<u8>), ChunkError> {
    let header = decode_header(bytes)?;
    let payload = &bytes[HEADER_LEN..];
    if payload.len() != header.stored_len as usize {
        return Err(ChunkError::Damaged("payload length differs from the header".into()));
    }
    let raw = match header.codec {
        CODEC_RAW => payload.to_vec(),
        _ => {
            // The output size is the header's raw length, itself capped by the triangle count.
            let mut raw = vec![0u8; header.raw_len as usize];
            let n = lz4_flex::block::decompress_into(payload, &mut raw)
                .map_err(|e| ChunkError::Damaged(format!("lz4: {e}")))?;
            if n != raw.len() {
                return Err(ChunkError::Damaged("short lz4 payload".into()));
            }
            raw
        }
    };
    Ok((header, raw))
}

#[derive(Debug, Clone, Copy)]
enum Location {
    Memory(usize),
    Disk {
        offset: u64,
        len: u32,
    },
    /// A resident chunk whose buffer [`ChunkStore::take_resident`] handed out.
    Taken,
    /// A chunk [`ChunkStore::push_behind`] is still encoding and writing.
    Pending,
}

/// What the spill file's writers share: its end (each write reserves its
/// range there, so writes need no lock and may finish in any order) and the
/// chunks written behind their producer, until [`ChunkStore::settle_behind`].
#[derive(Default)]
struct SpillShared {
    end: AtomicU64,
    in_flight: AtomicUsize,
    written: Mutex<Written>,
}

#[derive(Default)]
struct Written {
    /// (id, offset, length) of chunks written behind.
    placed: Vec<(usize, u64, u32)>,
    /// The first write that failed.
    error: Option<ChunkError>,
}

impl SpillShared {
    /// Encodes `raw` and writes it at a range reserved at the file's end.
    fn write(
        &self,
        file: &File,
        path: &Path,
        layout: RecordLayout,
        raw: &[u8],
    ) -> Result<(u64, u32), ChunkError> {
        let chunk = encode_chunk(layout, raw);
        let offset = self.end.fetch_add(chunk.len() as u64, Ordering::Relaxed);
        write_all_at(file, &chunk, offset).map_err(|source| ChunkError::Io {
            action: "write",
            path: path.to_path_buf(),
            source,
        })?;
        Ok((offset, chunk.len() as u32))
    }

    /// [`SpillShared::write`] for chunk `id`, its outcome kept for [`ChunkStore::settle_behind`].
    fn write_behind(&self, file: &File, path: &Path, id: usize, layout: RecordLayout, raw: &[u8]) {
        let outcome = self.write(file, path, layout, raw);
        let mut w = self.written.lock().unwrap_or_else(|e| e.into_inner());
        match outcome {
            Ok((offset, len)) => w.placed.push((id, offset, len)),
            Err(e) => {
                w.error.get_or_insert(e);
            }
        }
    }
}

/// Chunks of records, kept in memory up to a resident limit and appended to
/// a spill file beyond it. Reads are positional, so many threads can read
/// chunks at once.
///
/// A resident chunk is its records' own buffer, moved in and lent out as is:
/// neither stored nor read through a copy (its header is counted, not kept).
/// Only spilled chunks are encoded, as lz4 with their header.
pub struct ChunkStore {
    spill_path: PathBuf,
    spill: Option<Arc<File>>,
    shared: Arc<SpillShared>,
    resident: Vec<Vec<u8>>,
    resident_bytes: usize,
    resident_limit: usize,
    chunks: Vec<Location>,
}

impl ChunkStore {
    /// A store that spills to `spill_path` (created only when needed) once
    /// more than `resident_limit` bytes are held.
    pub fn new(spill_path: &Path, resident_limit: usize) -> Self {
        Self {
            spill_path: spill_path.to_path_buf(),
            spill: None,
            shared: Arc::default(),
            resident: Vec::new(),
            resident_bytes: 0,
            resident_limit,
            chunks: Vec::new(),
        }
    }

    fn io(&self, action: &'static str) -> impl FnOnce(io::Error) -> ChunkError + '_ {
        move |source| ChunkError::Io { action, path: self.spill_path.clone(), source }
    }

    /// Whether a chunk of `raw_len` record bytes stays in memory next to `resident` bytes.
    fn fits(&self, resident: usize, raw_len: usize) -> bool {
        resident + HEADER_LEN + raw_len <= self.resident_limit
    }

    /// Keeps records in memory (the caller checked that they fit).
    fn keep(&mut self, mut raw: Vec<u8>) -> usize {
        // The budget counts lengths: a buffer grown by doubling gives its slack back.
        raw.shrink_to_fit();
        self.resident_bytes += HEADER_LEN + raw.len();
        self.chunks.push(Location::Memory(self.resident.len()));
        self.resident.push(raw);
        self.chunks.len() - 1
    }

    /// The spill file, created on first use.
    fn spill_file(&mut self) -> Result<Arc<File>, ChunkError> {
        if self.spill.is_none() {
            let f = File::options()
                .read(true)
                .write(true)
                .create_new(true)
                .open(&self.spill_path)
                .map_err(self.io("create"))?;
            self.spill = Some(Arc::new(f));
        }
        Ok(self.spill.clone().expect("opened above"))
    }

    /// Encodes records and appends them to the spill file.
    fn spill_chunk(&mut self, layout: RecordLayout, raw: &[u8]) -> Result<usize, ChunkError> {
        let file = self.spill_file()?;
        let (offset, len) = self.shared.write(&file, &self.spill_path, layout, raw)?;
        self.chunks.push(Location::Disk { offset, len });
        Ok(self.chunks.len() - 1)
    }

    /// Stores records as one chunk and returns its id (ids count up from 0, in
    /// order): the buffer itself while it fits (no CPU spent on a copy or on
    /// compression), lz4 when spilled (fewer bytes to write and read). A chunk
    /// that spills is encoded and written by a task of
    /// `scope` while the caller goes on; at most `in_flight` such tasks at once
    /// (past that the caller encodes and writes it itself), so the chunks in
    /// flight hold at most `in_flight` × (records + encoded) bytes.
    ///
    /// Why: a producer that appends in input order on one thread (pass 2)
    /// would otherwise spend its turn compressing and writing while the
    /// cores it feeds wait. The chunk reads as an error until
    /// [`ChunkStore::settle_behind`] is called after `scope` ends.
    pub fn push_behind(
        &mut self,
        layout: RecordLayout,
        raw: Vec<u8>,
        scope: &rayon::Scope<'_>,
        in_flight: usize,
    ) -> Result<usize, ChunkError> {
        if self.fits(self.resident_bytes, raw.len()) {
            return Ok(self.keep(raw));
        }
        if let Some(e) = self.shared.written.lock().unwrap_or_else(|e| e.into_inner()).error.take() {
            return Err(e);
        }
        let file = self.spill_file()?;
        if self.shared.in_flight.load(Ordering::Acquire) >= in_flight {
            return self.spill_chunk(layout, &raw);
        }
        let id = self.chunks.len();
        self.chunks.push(Location::Pending);
        let (shared, path) = (self.shared.clone(), self.spill_path.clone());
        shared.in_flight.fetch_add(1, Ordering::AcqRel);
        scope.spawn(move |_| {
            shared.write_behind(&file, &path, id, layout, &raw);
            drop(raw);
            shared.in_flight.fetch_sub(1, Ordering::AcqRel);
        });
        Ok(id)
    }

    /// Places the chunks [`ChunkStore::push_behind`] wrote; call once their
    /// scope has ended. The first failed write is the error.
    pub fn settle_behind(&mut self) -> Result<(), ChunkError> {
        let mut w = self.shared.written.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(e) = w.error.take() {
            return Err(e);
        }
        for (id, offset, len) in w.placed.drain(..) {
            self.chunks[id] = Location::Disk { offset, len };
        }
        drop(w);
        match self.chunks.iter().position(|c| matches!(c, Location::Pending)) {
            Some(id) => Err(ChunkError::Damaged(format!("chunk {id} was never written"))),
            None => Ok(()),
        }
    }

    pub fn len(&self) -> usize {
        self.chunks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.chunks.is_empty()
    }

    /// Bytes of bookkeeping per chunk (locations), apart from the chunks' bytes.
    pub fn index_bytes(&self) -> usize {
        self.chunks.capacity() * std::mem::size_of::<Location>()
            + self.resident.capacity() * std::mem::size_of::<Vec<u8>>()
    }

    /// Bytes written to the spill file so far.
    pub fn spilled_bytes(&self) -> u64 {
        self.shared.end.load(Ordering::Relaxed)
    }

    /// Calls `f` with chunk `id`'s records: a resident chunk's own bytes, a
    /// spilled one read back and decoded.
    pub fn with_records<T>(
        &self,
        id: usize,
        f: impl FnOnce(&[u8]) -> Result<T, ChunkError>,
    ) -> Result<T, ChunkError> {
        match self.chunks.get(id) {
            None => Err(ChunkError::Damaged(format!("no chunk {id}"))),
            Some(Location::Taken) => Err(ChunkError::Damaged(format!("chunk {id} was taken"))),
            Some(Location::Pending) => Err(ChunkError::Damaged(format!("chunk {id} is still being written"))),
            Some(Location::Memory(i)) => f(&self.resident[*i]),
            Some(&Location::Disk { offset, len }) => {
                let file = self.spill.as_ref().expect("a disk chunk implies a spill file");
                let mut buf = vec![0u8; len as usize];
                read_exact_at(file, &mut buf, offset).map_err(self.io("read"))?;
                f(&decode_chunk(&buf)?.1)
            }
        }
    }

    /// Takes resident chunk `id`'s buffer out of the store (its records are
    /// then gone: reading it again is an error), for a pass that has consumed
    /// it to reuse; `None` for a spilled or already taken chunk. The store
    /// keeps counting its bytes, so its holder's share of the budget does not
    /// shrink while the buffer lives on elsewhere.
    pub fn take_resident(&mut self, id: usize) -> Option<Vec<u8>> {
        let Some(Location::Memory(i)) = self.chunks.get(id).copied() else {
            return None;
        };
        self.chunks[id] = Location::Taken;
        Some(std::mem::take(&mut self.resident[i]))
    }

    /// Resident chunk `id`'s records, lent as they lie; `None` for a spilled
    /// or taken one.
    pub fn resident_records(&self, id: usize) -> Option<&[u8]> {
        match self.chunks.get(id) {
            Some(Location::Memory(i)) => Some(&self.resident[*i]),
            _ => None,
        }
    }

    /// Whether every chunk is in memory (none spilled or taken).
    pub fn all_resident(&self) -> bool {
        self.chunks.iter().all(|c| matches!(c, Location::Memory(_)))
    }

    /// Chunk `id`'s records, copied.
    pub fn read(&self, id: usize) -> Result<Vec<u8>, ChunkError> {
        self.with_records(id, |raw| Ok(raw.to_vec()))
    }
}

#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(unix)]
fn write_all_at(file: &File, buf: &[u8], offset: u64) -> io::Result<()> {
    std::os::unix::fs::FileExt::write_all_at(file, buf, offset)
}

#[cfg(windows)]
fn write_all_at(file: &File, mut buf: &[u8], mut offset: u64) -> io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_write(buf, offset)? {
            0 => return Err(io::ErrorKind::WriteZero.into()),
            n => {
                buf = &buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
}

#[cfg(windows)]
fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_read(buf, offset)? {
            0 => return Err(io::ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri(k: f64) -> [[f64; 3]; 3] {
        [[k, 0.5, -1.0], [k + 1.0, 2.0, 3.0], [0.25, k * 3.0, 1e7]]
    }

    #[test]
    fn records_round_trip_in_both_precisions() {
        for layout in [
            RecordLayout { f64_positions: true, color: true },
            RecordLayout { f64_positions: false, color: false },
        ] {
            let mut raw = Vec::new();
            for k in 0..100 {
                layout.encode(&mut raw, &tri(k as f64), [0.1, 0.2, k as f32 / 100.0]);
            }
            assert_eq!(raw.len(), 100 * layout.size());
            let chunk = encode_chunk(layout, &raw);
            let (h, back) = decode_chunk(&chunk).unwrap();
            assert_eq!((h.triangles, h.layout), (100, layout));
            assert_eq!(back, raw);
            let (t, c) = layout.decode(&back[7 * layout.size()..8 * layout.size()]);
            assert_eq!(t, tri(7.0));
            assert_eq!(c, if layout.color { [0.1, 0.2, 0.07] } else { [0.0; 3] });
        }
    }

    #[test]
    fn damaged_chunks_are_errors_not_panics() {
        let layout = RecordLayout { f64_positions: false, color: false };
        let mut raw = Vec::new();
        layout.encode(&mut raw, &tri(1.0), [0.0; 3]);
        let chunk = encode_chunk(layout, &raw);
        for len in 0..chunk.len() {
            assert!(decode_chunk(&chunk[..len]).is_err(), "{len}");
        }
        let mut huge = chunk.clone();
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_chunk(&huge).is_err());
    }

    #[test]
    fn store_spills_past_its_limit_and_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let layout = RecordLayout { f64_positions: true, color: false };
        let mut store = ChunkStore::new(&dir.path().join("spill"), 300);
        let mut chunks = Vec::new();
        for k in 0..5 {
            let mut raw = Vec::new();
            layout.encode(&mut raw, &tri(k as f64), [0.0; 3]);
            chunks.push(raw);
        }
        rayon::scope(|scope| {
            for (k, raw) in chunks.iter().enumerate() {
                assert_eq!(store.push_behind(layout, raw.clone(), scope, 0).unwrap(), k);
            }
        });
        store.settle_behind().unwrap();
        assert!(store.spilled_bytes() > 0 && dir.path().join("spill").exists());
        for (k, raw) in chunks.iter().enumerate() {
            assert_eq!(&store.read(k).unwrap(), raw);
        }
        assert!(store.read(5).is_err());

        // A resident chunk's buffer can be taken once, whole; a spilled one cannot.
        let taken = store.take_resident(0).expect("chunk 0 is resident");
        assert_eq!(taken, chunks[0]);
        assert!(store.read(0).is_err(), "a taken chunk reads as an error, not as empty records");
        assert!(store.take_resident(0).is_none());
        assert!(store.take_resident(4).is_none(), "chunk 4 is spilled");
        assert_eq!(&store.read(4).unwrap(), &chunks[4]);
        assert_eq!(&store.read(1).unwrap(), &chunks[1]);
    }

    #[test]
    fn chunks_written_behind_read_back_after_settling() {
        let dir = tempfile::tempdir().unwrap();
        let layout = RecordLayout { f64_positions: false, color: true };
        let mut store = ChunkStore::new(&dir.path().join("spill"), 200);
        let chunks: Vec<Vec<u8>> = (0..40)
            .map(|k| {
                let mut raw = Vec::new();
                for j in 0..=k % 7 {
                    layout.encode(&mut raw, &tri((k * 8 + j) as f64), [k as f32 / 40.0, 0.5, 0.0]);
                }
                raw
            })
            .collect();
        rayon::scope(|scope| {
            for (k, raw) in chunks.iter().enumerate() {
                // A cap of 2 makes some chunks go inline and some behind.
                assert_eq!(store.push_behind(layout, raw.clone(), scope, 2).unwrap(), k);
            }
            let pending = (0..chunks.len()).find(|&k| matches!(store.chunks[k], Location::Pending));
            if let Some(k) = pending {
                assert!(store.read(k).is_err(), "a chunk still in flight reads as an error");
            }
        });
        assert!(store.spilled_bytes() > 0);
        store.settle_behind().unwrap();
        for (k, raw) in chunks.iter().enumerate() {
            assert_eq!(&store.read(k).unwrap(), raw, "chunk {k}");
        }

        // Control: a chunk whose write never landed, or a failed write, is an
        // error at settle, not a silent hole.
        let mut lost = ChunkStore::new(&dir.path().join("lost"), 0);
        rayon::scope(|scope| {
            lost.push_behind(layout, chunks[3].clone(), scope, 4).unwrap();
        });
        lost.shared.written.lock().unwrap().placed.clear();
        assert!(matches!(lost.settle_behind(), Err(ChunkError::Damaged(_))));
        let mut failed = ChunkStore::new(&dir.path().join("failed"), 0);
        failed.shared.written.lock().unwrap().error = Some(ChunkError::Damaged("disk full".into()));
        let e = rayon::scope(|scope| failed.push_behind(layout, chunks[3].clone(), scope, 4));
        assert!(e.is_err(), "a failed write surfaces at the next push");
    }
}
