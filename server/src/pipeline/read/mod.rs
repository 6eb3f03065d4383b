//! Ingest: mesh files → triangles in f64 source coordinates.
//!
//! Every reader pushes triangles, in file order, into a [`TriangleSink`]:
//! the build's sink writes them into the chunked triangle stream
//! ([`crate::pipeline::stream`]) so a huge scan never sits in memory; the
//! in-memory [`read_mesh`] / [`read_mesh_bytes`] (tests, fuzzing) collect a
//! [`TriangleMesh`].
//!
//! What is streamed and what is held (see ARCHITECTURE.md, "Memory"):
//! - PLY (ASCII, binary little/big endian): the vertex element is held as
//!   compact arrays (f32 or f64 positions, optional sRGB u8 colour) when
//!   they fit half the memory budget, else spilled as the same records to a
//!   temporary file and read through a page cache of a quarter of the
//!   budget; faces are streamed. Element counts are checked against the file
//!   size before anything is reserved.
//! - binary STL: streamed record by record.
//! - ASCII STL, OBJ (tobj) and glTF/GLB: parsed in memory, so the file must
//!   fit the memory budget (a clear error otherwise), then streamed.
//!
//! Invariant of a [`TriangleMesh`]: every index is < `positions.len()`.
//! Triangles may still be degenerate or non-finite; the voxelizer skips and
//! counts those.

mod ahead;
mod gltf;
mod obj;
mod ply;
mod stl;

use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;
use std::sync::Arc;
use std::sync::LazyLock;
use std::sync::atomic::{AtomicU64, Ordering};

pub use crate::pipeline::bin::EncodedPiece;
pub use crate::pipeline::stream::RecordLayout;

/// An indexed triangle mesh in the source file's own coordinates and units.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct TriangleMesh {
    pub positions: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// Linear RGB in [0, 1] per vertex, or empty when the file has no colours.
    pub colors: Vec<[f32; 3]>,
}

impl TriangleMesh {
    pub fn triangle(&self, t: usize) -> [[f64; 3]; 3] {
        self.triangles[t].map(|i| self.positions[i as usize])
    }

    /// The mean of the triangle's vertex colours, if the mesh has colours.
    pub fn triangle_color(&self, t: usize) -> Option<[f32; 3]> {
        if self.colors.len() != self.positions.len() {
            return None;
        }
        let c = self.triangles[t].map(|i| self.colors[i as usize]);
        Some(std::array::from_fn(|a| (c[0][a] + c[1][a] + c[2][a]) / 3.0))
    }

    /// Appends a polygon as a fan, rejecting indices outside the vertex list.
    fn push_polygon(&mut self, poly: &[u32], vertex_count: usize, face: usize) -> Result<(), IngestError> {
        check_polygon(poly, vertex_count, face)?;
        for k in 1..poly.len().saturating_sub(1) {
            self.triangles.push([poly[0], poly[k], poly[k + 1]]);
        }
        Ok(())
    }

    /// Streams every triangle into `sink` (positions as f64, colours when present).
    pub fn stream_into(&self, sink: &mut dyn TriangleSink) -> Result<(), IngestError> {
        let color = self.colors.len() == self.positions.len() && !self.colors.is_empty();
        sink.begin(RecordLayout { f64_positions: true, color })?;
        let mut batch = Vec::with_capacity(TICK_EVERY.min(self.triangles.len()));
        for t in 0..self.triangles.len() {
            batch.push((self.triangle(t), self.triangle_color(t).unwrap_or_default()));
            if batch.len() == TICK_EVERY {
                sink.triangles(&batch)?;
                batch.clear();
                sink.tick()?;
            }
        }
        sink.triangles(&batch)
    }
}

fn check_polygon(poly: &[u32], vertex_count: usize, face: usize) -> Result<(), IngestError> {
    if let Some(&bad) = poly.iter().find(|&&i| i as usize >= vertex_count) {
        return Err(IngestError::Invalid(format!(
            "face {face} uses vertex {bad}, but the file has only {vertex_count} vertices"
        )));
    }
    Ok(())
}

/// How often readers call [`TriangleSink::tick`] (elements or triangles).
pub(crate) const TICK_EVERY: usize = 1 << 16;

/// Where readers put triangles, in file order.
pub trait TriangleSink {
    /// Called once, before the first triangle: what the triangles carry.
    fn begin(&mut self, layout: RecordLayout) -> Result<(), IngestError>;
    /// One triangle in source coordinates, with its linear colour (zeros without colours).
    fn triangle(&mut self, tri: [[f64; 3]; 3], color: [f32; 3]) -> Result<(), IngestError>;
    /// Many triangles, in order (readers that parse in batches hand them over whole).
    fn triangles(&mut self, tris: &[([[f64; 3]; 3], [f32; 3])]) -> Result<(), IngestError> {
        for &(tri, color) in tris {
            self.triangle(tri, color)?;
        }
        Ok(())
    }
    /// The record layout when this sink takes triangles already checked and
    /// encoded ([`Self::pieces`]), which readers then do on their worker
    /// threads; `None`: it takes triangles.
    fn encoded_layout(&self) -> Option<RecordLayout> {
        None
    }
    /// Encoded pieces, in order; only called when [`Self::encoded_layout`] is `Some`.
    fn pieces(&mut self, _pieces: Vec<EncodedPiece>) -> Result<(), IngestError> {
        Err(IngestError::Invalid("this sink takes triangles, not encoded records".into()))
    }
    /// Called now and then during long reads: report progress, stop when cancelled.
    fn tick(&mut self) -> Result<(), IngestError> {
        Ok(())
    }
}

/// Collects an unwelded [`TriangleMesh`] (three vertices per triangle).
#[derive(Default)]
struct MeshBuilder {
    mesh: TriangleMesh,
    color: bool,
}

impl TriangleSink for MeshBuilder {
    fn begin(&mut self, layout: RecordLayout) -> Result<(), IngestError> {
        self.color = layout.color;
        Ok(())
    }

    fn triangle(&mut self, tri: [[f64; 3]; 3], color: [f32; 3]) -> Result<(), IngestError> {
        let base = self.mesh.positions.len();
        if base as u64 + 3 > u64::from(u32::MAX) + 1 {
            return Err(IngestError::Invalid(format!(
                "more than {} vertices do not fit 32-bit indices",
                u64::from(u32::MAX) + 1
            )));
        }
        self.mesh.positions.extend(tri);
        if self.color {
            self.mesh.colors.extend([color; 3]);
        }
        let base = base as u32;
        self.mesh.triangles.push([base, base + 1, base + 2]);
        Ok(())
    }
}

/// sRGB-encoded 8-bit channel → linear [0, 1].
pub(crate) static SRGB_TO_LINEAR: LazyLock<[f32; 256]> =
    LazyLock::new(|| std::array::from_fn(|i| srgb_to_linear(i as f32 / 255.0)));

/// sRGB-encoded channel in [0, 1] → linear (clamped; NaN becomes 0).
pub(crate) fn srgb_to_linear(c: f32) -> f32 {
    let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// Limits and reporting for a streaming read.
#[derive(Debug, Clone)]
pub struct ReadOptions {
    /// Bytes the reader may hold (PLY vertex table: half of it, else a page
    /// cache of a quarter; whole-file formats: the file must fit).
    pub memory_budget: u64,
    /// Where the PLY vertex table spills (an unnamed file); the system's temporary directory when `None`.
    pub temp_dir: Option<std::path::PathBuf>,
    /// Bytes the PLY vertex table may take in memory before it is paged from
    /// disk through a cache of half as many; `None`: half the memory budget.
    /// Tests set it to force the paged path.
    pub vertex_memory: Option<u64>,
    /// Input bytes consumed so far, updated as the file is read.
    pub bytes_read: Arc<AtomicU64>,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self {
            memory_budget: 1 << 30,
            bytes_read: Arc::new(AtomicU64::new(0)),
            temp_dir: None,
            vertex_memory: None,
        }
    }
}

/// Counts bytes read through it into a shared counter.
struct CountingReader<R> {
    inner: R,
    count: Arc<AtomicU64>,
}

impl<R: Read> Read for CountingReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.count.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

impl<R: std::io::Seek> std::io::Seek for CountingReader<R> {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        let p = self.inner.seek(pos)?;
        self.count.store(p, Ordering::Relaxed);
        Ok(p)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Obj,
    Ply,
    Stl,
    /// glTF 2.0 JSON with embedded (`data:`) buffers.
    Gltf,
    /// Binary glTF 2.0.
    Glb,
}

impl fmt::Display for MeshFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MeshFormat::Obj => "obj",
            MeshFormat::Ply => "ply",
            MeshFormat::Stl => "stl",
            MeshFormat::Gltf => "gltf",
            MeshFormat::Glb => "glb",
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("unsupported mesh format {0:?}: expected .obj, .ply, .stl, .gltf or .glb")]
    UnsupportedFormat(String),
    #[error("not a valid {format} file: {message}")]
    Parse { format: MeshFormat, message: String },
    #[error("unsupported {format} content: {message}")]
    Unsupported { format: MeshFormat, message: String },
    #[error("invalid mesh: {0}")]
    Invalid(String),
    #[error("input too large for the memory budget: {0}")]
    TooLarge(String),
    #[error("reading was cancelled")]
    Cancelled,
}

impl MeshFormat {
    /// Picks the parser from the file's magic bytes, falling back to its extension.
    pub fn detect(path: &Path, head: &[u8]) -> Result<Self, IngestError> {
        // STL and glTF JSON have no reliable magic: "solid" also opens binary STL headers.
        if head.starts_with(b"glTF") {
            return Ok(MeshFormat::Glb);
        }
        if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
            return Ok(MeshFormat::Ply);
        }
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        match ext.as_str() {
            "obj" => Ok(MeshFormat::Obj),
            "ply" => Ok(MeshFormat::Ply),
            "stl" => Ok(MeshFormat::Stl),
            "gltf" => Ok(MeshFormat::Gltf),
            "glb" => Ok(MeshFormat::Glb),
            _ => Err(IngestError::UnsupportedFormat(path.display().to_string())),
        }
    }
}

/// Reads a mesh file into memory. OBJ never follows `mtllib`: materials are not needed.
pub fn read_mesh(path: &Path) -> Result<(TriangleMesh, MeshFormat), IngestError> {
    let io = |source| IngestError::Io { path: path.display().to_string(), source };
    let bytes = std::fs::read(path).map_err(io)?;
    let format = MeshFormat::detect(path, &bytes[..bytes.len().min(8)])?;
    let mesh = read_mesh_bytes(&bytes, format)?;
    Ok((mesh, format))
}

/// Parses a whole file held in memory (the fuzzing entry point). PLY and STL
/// come back unwelded, three vertices per triangle.
pub fn read_mesh_bytes(bytes: &[u8], format: MeshFormat) -> Result<TriangleMesh, IngestError> {
    let mesh = match format {
        MeshFormat::Obj => obj::read(bytes)?,
        // The glTF reader tells JSON from GLB by the magic itself.
        MeshFormat::Gltf | MeshFormat::Glb => gltf::read(bytes)?,
        MeshFormat::Ply | MeshFormat::Stl => {
            let mut builder = MeshBuilder::default();
            stream_mesh_bytes(
                bytes,
                format,
                &mut builder,
                &ReadOptions { memory_budget: u64::MAX, ..Default::default() },
            )?;
            builder.mesh
        }
    };
    if mesh.triangles.is_empty() {
        return Err(IngestError::Invalid("the file holds no triangles".into()));
    }
    Ok(mesh)
}

/// Streams the triangles of a file held in memory into `sink`.
pub fn stream_mesh_bytes(
    bytes: &[u8],
    format: MeshFormat,
    sink: &mut dyn TriangleSink,
    opts: &ReadOptions,
) -> Result<(), IngestError> {
    let len = bytes.len() as u64;
    let input =
        BufReader::new(CountingReader { inner: std::io::Cursor::new(bytes), count: opts.bytes_read.clone() });
    match format {
        MeshFormat::Ply => ply::stream(input, len, sink, opts),
        MeshFormat::Stl => stl::stream(input, len, sink, opts),
        MeshFormat::Obj => obj::read(bytes)?.stream_into(sink),
        MeshFormat::Gltf | MeshFormat::Glb => gltf::read(bytes)?.stream_into(sink),
    }
}

/// Streams a mesh file's triangles into `sink` in file order, within
/// `opts.memory_budget`; returns the format read.
pub fn stream_mesh(
    path: &Path,
    sink: &mut dyn TriangleSink,
    opts: &ReadOptions,
) -> Result<MeshFormat, IngestError> {
    let io = |source| IngestError::Io { path: path.display().to_string(), source };
    let mut file = File::open(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    let mut head = Vec::with_capacity(8);
    file.by_ref().take(8).read_to_end(&mut head).map_err(io)?;
    let format = MeshFormat::detect(path, &head)?;
    std::io::Seek::rewind(&mut file).map_err(io)?;
    match format {
        MeshFormat::Ply | MeshFormat::Stl => {
            let counted = CountingReader { inner: file, count: opts.bytes_read.clone() };
            if format == MeshFormat::Ply {
                // The file is read ahead on its own thread while the blocks before are parsed.
                std::thread::scope(|s| {
                    let input = ahead::ReadAhead::spawn(s, counted).map_err(io)?;
                    ply::stream(input, len, sink, opts)
                })?;
            } else {
                stl::stream(BufReader::with_capacity(1 << 20, counted), len, sink, opts)?;
            }
        }
        MeshFormat::Obj | MeshFormat::Gltf | MeshFormat::Glb => {
            // Parsed in memory by their crates: roughly 4× the file's size at the peak.
            if len.saturating_mul(4) > opts.memory_budget {
                return Err(IngestError::TooLarge(format!(
                    "{format} files are parsed in memory, and this {len}-byte file needs about {} bytes, \
                     more than the memory budget of {} bytes: raise --memory-budget or convert it to binary PLY",
                    len.saturating_mul(4),
                    opts.memory_budget
                )));
            }
            let mut bytes = Vec::with_capacity(len as usize);
            file.read_to_end(&mut bytes).map_err(io)?;
            opts.bytes_read.store(len, Ordering::Relaxed);
            stream_mesh_bytes(
                &bytes,
                format,
                sink,
                &ReadOptions { bytes_read: Arc::new(AtomicU64::new(0)), ..opts.clone() },
            )?;
        }
    }
    Ok(format)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn detect_by_magic_then_extension() {
        let detect = |name: &str, head: &[u8]| MeshFormat::detect(Path::new(name), head);
        assert_eq!(detect("scan.bin", b"glTF\x02\0\0\0").unwrap(), MeshFormat::Glb);
        assert_eq!(detect("scan.obj", b"ply\nform").unwrap(), MeshFormat::Ply);
        assert_eq!(detect("part.STL", b"solid x").unwrap(), MeshFormat::Stl);
        assert_eq!(detect("a.gltf", b"{").unwrap(), MeshFormat::Gltf);
        assert_eq!(detect("a.glb", b"").unwrap(), MeshFormat::Glb);
        assert_eq!(detect("a.obj", b"v 0 0 0").unwrap(), MeshFormat::Obj);
        let e = detect("notes.txt", b"hello").unwrap_err().to_string();
        for ext in [".obj", ".ply", ".stl", ".gltf", ".glb"] {
            assert!(e.contains(ext), "{e}");
        }
    }

    #[test]
    fn formats_display_as_their_extension() {
        let names: Vec<String> =
            [MeshFormat::Obj, MeshFormat::Ply, MeshFormat::Stl, MeshFormat::Gltf, MeshFormat::Glb]
                .map(|f| f.to_string())
                .into();
        assert_eq!(names, ["obj", "ply", "stl", "gltf", "glb"]);
    }
}
