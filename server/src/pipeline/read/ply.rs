//! PLY (ASCII, binary little- and big-endian) through ply-rs-bw's
//! per-element readers: the header is parsed by the crate, then each element
//! is read one at a time, so faces stream straight into the sink.
//!
//! The vertex element is held as compact arrays (f32 positions when x, y, z
//! are exact in f32, else f64; sRGB u8 colours when red/green/blue exist),
//! which must fit half the memory budget. Before anything is reserved, every
//! element's count is checked against the bytes the file has left: a header
//! claiming 4e9 vertices in a 100-byte file fails at once. Vertex normals
//! and any other property are read past: voxel normals come from the
//! triangles themselves.

use std::io::BufRead;

use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{
    BeginList, ElementDef, Encoding, Header, PropertyAccess, PropertyAccessResult, PropertyType, ScalarType,
};

use super::{IngestError, MeshFormat, ReadOptions, SRGB_TO_LINEAR, TICK_EVERY, TriangleSink, check_polygon};
use crate::pipeline::stream::RecordLayout;

/// One vertex as read: position and colour channels in [0, 1] (NaN = absent).
struct VertexRecord {
    p: [f64; 3],
    c: [f32; 3],
}

impl VertexRecord {
    fn set(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        match name {
            "x" => self.p[0] = v,
            "y" => self.p[1] = v,
            "z" => self.p[2] = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }

    fn set_color(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        match color_channel(name) {
            Some(i) => {
                self.c[i] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }
}

fn color_channel(name: &str) -> Option<usize> {
    match name {
        "red" | "r" | "diffuse_red" => Some(0),
        "green" | "g" | "diffuse_green" => Some(1),
        "blue" | "b" | "diffuse_blue" => Some(2),
        _ => None,
    }
}

impl PropertyAccess for VertexRecord {
    fn new() -> Self {
        Self { p: [0.0; 3], c: [f32::NAN; 3] }
    }
    fn set_char(&mut self, name: &str, v: i8) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        match self.set_color(name, v as f32 / 255.0) {
            PropertyAccessResult::Ignored => self.set(name, v as f64),
            r => r,
        }
    }
    fn set_short(&mut self, name: &str, v: i16) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        match self.set_color(name, v as f32 / 65535.0) {
            PropertyAccessResult::Ignored => self.set(name, v as f64),
            r => r,
        }
    }
    fn set_int(&mut self, name: &str, v: i32) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        match self.set_color(name, v) {
            PropertyAccessResult::Ignored => self.set(name, v as f64),
            r => r,
        }
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        match self.set_color(name, v as f32) {
            PropertyAccessResult::Ignored => self.set(name, v),
            r => r,
        }
    }
}

/// A face's vertex list; negative indices become `u32::MAX` so the range check rejects them.
struct FaceRecord {
    ints: Vec<i32>,
    uints: Vec<u32>,
    other: Vec<u32>,
    which: u8,
}

fn is_index_list(name: &str) -> bool {
    name == "vertex_indices" || name == "vertex_index"
}

impl FaceRecord {
    fn set<T: TryInto<u32> + Copy>(&mut self, name: &str, v: &[T]) -> PropertyAccessResult {
        if !is_index_list(name) {
            return PropertyAccessResult::Ignored;
        }
        self.other.clear();
        self.other.extend(v.iter().map(|&i| i.try_into().unwrap_or(u32::MAX)));
        self.which = 3;
        PropertyAccessResult::Set
    }

    /// The indices, converted; `scratch` holds signed lists after conversion.
    fn indices<'a>(&'a self, scratch: &'a mut Vec<u32>) -> &'a [u32] {
        match self.which {
            1 => {
                scratch.clear();
                scratch.extend(self.ints.iter().map(|&i| u32::try_from(i).unwrap_or(u32::MAX)));
                scratch
            }
            2 => &self.uints,
            3 => &self.other,
            _ => &[],
        }
    }
}

impl PropertyAccess for FaceRecord {
    fn new() -> Self {
        Self { ints: Vec::new(), uints: Vec::new(), other: Vec::new(), which: 0 }
    }
    fn begin_list_int(&mut self, name: &str, _len: usize) -> BeginList<'_, i32> {
        if !is_index_list(name) {
            return BeginList::UseSetter;
        }
        self.which = 1;
        BeginList::Fill(&mut self.ints)
    }
    fn begin_list_uint(&mut self, name: &str, _len: usize) -> BeginList<'_, u32> {
        if !is_index_list(name) {
            return BeginList::UseSetter;
        }
        self.which = 2;
        BeginList::Fill(&mut self.uints)
    }
    fn set_list_short(&mut self, name: &str, v: Vec<i16>) -> PropertyAccessResult {
        self.set(name, &v)
    }
    fn set_list_ushort(&mut self, name: &str, v: Vec<u16>) -> PropertyAccessResult {
        self.set(name, &v)
    }
    fn set_list_char(&mut self, name: &str, v: Vec<i8>) -> PropertyAccessResult {
        self.set(name, &v)
    }
    fn set_list_uchar(&mut self, name: &str, v: Vec<u8>) -> PropertyAccessResult {
        self.set(name, &v)
    }
}

/// Elements other than vertex and face are read past and dropped.
struct Skipped;

impl PropertyAccess for Skipped {
    fn new() -> Self {
        Skipped
    }
}

fn parse_err(e: impl std::fmt::Display) -> IngestError {
    IngestError::Parse { format: MeshFormat::Ply, message: e.to_string() }
}

fn scalar_size(t: &ScalarType) -> u64 {
    match t {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    }
}

/// The fewest bytes one element can take in the file: what a count is checked against.
fn min_element_bytes(def: &ElementDef, encoding: Encoding) -> u64 {
    match encoding {
        // Each property is at least one digit and a separator (or the line break).
        Encoding::Ascii => (2 * def.properties.len() as u64).max(1),
        _ => def
            .properties
            .values()
            .map(|p| match &p.data_type {
                PropertyType::Scalar(t) => scalar_size(t),
                PropertyType::List(count, _) => scalar_size(count),
            })
            .sum(),
    }
}

/// Bytes of one binary element when it has no list property.
fn fixed_element_size(def: &ElementDef) -> Option<usize> {
    def.properties
        .values()
        .map(|p| match &p.data_type {
            PropertyType::Scalar(t) => Some(scalar_size(t) as usize),
            PropertyType::List(..) => None,
        })
        .sum::<Option<usize>>()
        .filter(|&n| n > 0)
}

/// The byte length of the binary element at the start of `bytes`, if it is all there.
fn element_len(def: &ElementDef, bytes: &[u8], big: bool) -> Option<usize> {
    let mut at = 0usize;
    for p in def.properties.values() {
        match &p.data_type {
            PropertyType::Scalar(t) => at += scalar_size(t) as usize,
            PropertyType::List(count_type, item) => {
                let w = scalar_size(count_type) as usize;
                let raw = bytes.get(at..at + w)?;
                let mut word = [0u8; 8];
                if big {
                    word[8 - w..].copy_from_slice(raw);
                } else {
                    word[..w].copy_from_slice(raw);
                }
                // Read unsigned: a negative count turns huge, never fits, and the crate reports it.
                let count = if big { u64::from_be_bytes(word) } else { u64::from_le_bytes(word) };
                let items = usize::try_from(count).ok()?.checked_mul(scalar_size(item) as usize)?;
                at = at.checked_add(w)?.checked_add(items)?;
            }
        }
        if at > bytes.len() {
            return None;
        }
    }
    Some(at)
}

/// Reads elements one at a time in the file's encoding.
struct ElementReader<R: BufRead> {
    reader: Reader<R>,
    encoding: Encoding,
    line: String,
}

/// Longest ASCII element line accepted (a face of ~100k vertices).
const MAX_LINE: u64 = 1 << 20;
/// Elements read per batch; ASCII batches are parsed in parallel.
const BATCH: usize = 1 << 14;

impl<R: BufRead> ElementReader<R> {
    /// Reads elements `start..start + n` into `out` (cleared first), in order.
    /// ASCII lines are gathered first and parsed on all cores: ply-rs-bw's
    /// `read_ascii_element` is a pure function of one line.
    fn read_batch<E: PropertyAccess + Send + Sync>(
        &mut self,
        parser: &Parser<E>,
        def: &ElementDef,
        start: usize,
        n: usize,
        out: &mut Vec<E>,
    ) -> Result<(), IngestError> {
        use rayon::prelude::*;
        out.clear();
        if self.encoding != Encoding::Ascii {
            let Some(size) = fixed_element_size(def) else {
                return self.read_framed_batch(parser, def, start, n, out);
            };
            // Fixed-size elements (no lists): read the batch's bytes, parse them on all cores.
            let mut bytes = vec![0u8; n * size];
            std::io::Read::read_exact(self.reader.get_mut(), &mut bytes).map_err(|e| {
                parse_err(format!(
                    "{} {start}..{}: {e} (the header declares {})",
                    def.name,
                    start + n,
                    def.count
                ))
            })?;
            let big = self.encoding == Encoding::BinaryBigEndian;
            let parsed: Result<Vec<E>, IngestError> = bytes
                .par_chunks_exact(size)
                .enumerate()
                .with_min_len(1024)
                .map(|(k, mut b)| {
                    let e = if big {
                        parser.read_big_endian_element(&mut b, def)
                    } else {
                        parser.read_little_endian_element(&mut b, def)
                    };
                    e.map_err(|e| parse_err(format!("{} {}: {e}", def.name, start + k)))
                })
                .collect();
            *out = parsed?;
            return Ok(());
        }
        let mut text = String::new();
        let mut ends = Vec::with_capacity(n);
        for i in start..start + n {
            self.read_line(def, i, &mut text)?;
            ends.push(text.len());
        }
        let parsed: Result<Vec<E>, IngestError> = (0..n)
            .into_par_iter()
            .with_min_len(256)
            .map(|k| {
                let line = &text[if k == 0 { 0 } else { ends[k - 1] }..ends[k]];
                parser
                    .read_ascii_element(line, def)
                    .map_err(|e| parse_err(format!("{} {}: {e}", def.name, start + k)))
            })
            .collect();
        *out = parsed?;
        Ok(())
    }

    /// Binary elements with lists: whole elements found in the reader's buffer
    /// (their lengths from the list counts) are parsed on all cores straight
    /// from it; an element straddling the buffer's end is read on its own.
    fn read_framed_batch<E: PropertyAccess + Send + Sync>(
        &mut self,
        parser: &Parser<E>,
        def: &ElementDef,
        start: usize,
        n: usize,
        out: &mut Vec<E>,
    ) -> Result<(), IngestError> {
        use rayon::prelude::*;
        let big = self.encoding == Encoding::BinaryBigEndian;
        let mut ends: Vec<usize> = Vec::new();
        while out.len() < n {
            let i = start + out.len();
            let buf =
                self.reader.get_mut().fill_buf().map_err(|e| parse_err(format!("{} {i}: {e}", def.name)))?;
            ends.clear();
            let mut at = 0;
            while out.len() + ends.len() < n {
                match element_len(def, &buf[at..], big) {
                    Some(len) => {
                        at += len;
                        ends.push(at);
                    }
                    None => break,
                }
            }
            if ends.is_empty() {
                // Straddles the buffer's end (or is malformed): the crate reads it and says what is wrong.
                out.push(self.read(parser, def, i)?);
                continue;
            }
            let parsed: Result<Vec<E>, IngestError> = (0..ends.len())
                .into_par_iter()
                .with_min_len(1024)
                .map(|k| {
                    let mut b = &buf[if k == 0 { 0 } else { ends[k - 1] }..ends[k]];
                    let e = if big {
                        parser.read_big_endian_element(&mut b, def)
                    } else {
                        parser.read_little_endian_element(&mut b, def)
                    };
                    e.map_err(|e| parse_err(format!("{} {}: {e}", def.name, i + k)))
                })
                .collect();
            out.extend(parsed?);
            self.reader.get_mut().consume(at);
        }
        Ok(())
    }

    /// Appends one ASCII element line to `text`.
    fn read_line(&mut self, def: &ElementDef, i: usize, text: &mut String) -> Result<(), IngestError> {
        let at = |e: &dyn std::fmt::Display| parse_err(format!("{} {i}: {e}", def.name));
        let before = text.len();
        let n = std::io::Read::take(self.reader.get_mut(), MAX_LINE).read_line(text).map_err(|e| at(&e))?;
        if n == 0 {
            return Err(at(&format!("the file ends early (the header declares {})", def.count)));
        }
        if n as u64 == MAX_LINE && !text[before..].ends_with('\n') {
            return Err(at(&"line longer than 1 MiB"));
        }
        Ok(())
    }

    fn read<E: PropertyAccess>(
        &mut self,
        parser: &Parser<E>,
        def: &ElementDef,
        i: usize,
    ) -> Result<E, IngestError> {
        let at = |e: &dyn std::fmt::Display| parse_err(format!("{} {i}: {e}", def.name));
        match self.encoding {
            Encoding::Ascii => {
                let mut line = std::mem::take(&mut self.line);
                line.clear();
                let read = self.read_line(def, i, &mut line);
                let parsed = read.and_then(|()| parser.read_ascii_element(&line, def).map_err(|e| at(&e)));
                self.line = line;
                parsed
            }
            Encoding::BinaryBigEndian => {
                parser.read_big_endian_element(self.reader.get_mut(), def).map_err(|e| at(&e))
            }
            Encoding::BinaryLittleEndian => {
                parser.read_little_endian_element(self.reader.get_mut(), def).map_err(|e| at(&e))
            }
        }
    }
}

enum Positions {
    F32(Vec<[f32; 3]>),
    F64(Vec<[f64; 3]>),
}

struct VertexTable {
    positions: Positions,
    colors: Option<Vec<[u8; 3]>>,
}

impl VertexTable {
    fn len(&self) -> usize {
        match &self.positions {
            Positions::F32(v) => v.len(),
            Positions::F64(v) => v.len(),
        }
    }

    fn position(&self, i: u32) -> [f64; 3] {
        match &self.positions {
            Positions::F32(v) => v[i as usize].map(f64::from),
            Positions::F64(v) => v[i as usize],
        }
    }

    fn color(&self, i: u32) -> [f32; 3] {
        match &self.colors {
            Some(c) => c[i as usize].map(|b| SRGB_TO_LINEAR[b as usize]),
            None => [0.0; 3],
        }
    }
}

/// Whether a property type holds every value exactly in f32.
fn exact_in_f32(t: &PropertyType) -> bool {
    matches!(
        t,
        PropertyType::Scalar(
            ScalarType::Float | ScalarType::Char | ScalarType::UChar | ScalarType::Short | ScalarType::UShort
        )
    )
}

fn read_vertices<R: BufRead>(
    input: &mut ElementReader<R>,
    def: &ElementDef,
    sink: &mut dyn TriangleSink,
    budget: u64,
) -> Result<VertexTable, IngestError> {
    for axis in ["x", "y", "z"] {
        match def.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            Some(PropertyType::List(..)) => {
                return Err(IngestError::Invalid(format!("vertex property {axis} is a list")));
            }
            None => return Err(IngestError::Invalid(format!("the vertex element has no {axis} property"))),
        }
    }
    let f32_exact = ["x", "y", "z"].iter().all(|a| exact_in_f32(&def.properties[*a].data_type));
    let has_color = def
        .properties
        .keys()
        .filter_map(|k| color_channel(k))
        .collect::<std::collections::BTreeSet<_>>()
        .len()
        == 3;
    let per_vertex = if f32_exact { 12 } else { 24 } + if has_color { 3 } else { 0 };
    let needed = def.count as u64 * per_vertex;
    if needed > budget / 2 {
        return Err(IngestError::TooLarge(format!(
            "the PLY's {} vertices take {needed} bytes in memory, more than half the memory budget of {budget} \
             bytes: raise --memory-budget",
            def.count
        )));
    }
    // Reserving by the count is safe here: it was checked against the file size and the budget.
    let mut positions = if f32_exact {
        Positions::F32(Vec::with_capacity(def.count))
    } else {
        Positions::F64(Vec::with_capacity(def.count))
    };
    let mut colors = has_color.then(|| Vec::with_capacity(def.count));
    let parser = Parser::<VertexRecord>::new();
    let mut batch = Vec::new();
    for start in (0..def.count).step_by(BATCH) {
        input.read_batch(&parser, def, start, BATCH.min(def.count - start), &mut batch)?;
        for v in &batch {
            match &mut positions {
                Positions::F32(p) => p.push(v.p.map(|c| c as f32)),
                Positions::F64(p) => p.push(v.p),
            }
            if let Some(c) = &mut colors {
                c.push(v.c.map(|x| if x.is_nan() { 0 } else { (x.clamp(0.0, 1.0) * 255.0).round() as u8 }));
            }
        }
        sink.tick()?;
    }
    Ok(VertexTable { positions, colors })
}

/// One triangle for the sink: positions and linear colour.
type Tri = ([[f64; 3]; 3], [f32; 3]);

/// Fans a polygon into `out`.
fn fan(poly: &[u32], table: &VertexTable, face: usize, out: &mut Vec<Tri>) -> Result<(), IngestError> {
    check_polygon(poly, table.len(), face)?;
    for k in 1..poly.len().saturating_sub(1) {
        let idx = [poly[0], poly[k], poly[k + 1]];
        let tri = idx.map(|i| table.position(i));
        let color = if table.colors.is_some() {
            let c = idx.map(|i| table.color(i));
            std::array::from_fn(|a| (c[0][a] + c[1][a] + c[2][a]) / 3.0)
        } else {
            [0.0; 3]
        };
        out.push((tri, color));
    }
    Ok(())
}

/// Fans a batch of faces (the first is face `start`) on all cores and hands
/// the triangles to the sink in file order; the first bad face in file order
/// is the error.
fn emit_faces(
    faces: &[FaceRecord],
    start: usize,
    table: &VertexTable,
    sink: &mut dyn TriangleSink,
) -> Result<(), IngestError> {
    use rayon::prelude::*;
    const PIECE: usize = 1024;
    let pieces: Vec<Result<Vec<Tri>, IngestError>> = faces
        .par_chunks(PIECE)
        .enumerate()
        .map(|(p, piece)| {
            let mut scratch = Vec::new();
            let mut out = Vec::with_capacity(piece.len());
            for (k, f) in piece.iter().enumerate() {
                fan(f.indices(&mut scratch), table, start + p * PIECE + k, &mut out)?;
            }
            Ok(out)
        })
        .collect();
    for piece in pieces {
        sink.triangles(&piece?)?;
    }
    Ok(())
}

/// Streams a PLY's triangles into `sink`. `len` is the whole input's size.
pub(super) fn stream<R: BufRead>(
    input: R,
    len: u64,
    sink: &mut dyn TriangleSink,
    opts: &ReadOptions,
) -> Result<(), IngestError> {
    let mut reader = Reader::new(input);
    let header: Header = Parser::<Skipped>::new().read_header(&mut reader).map_err(parse_err)?;
    let Some(vertex_def) = header.elements.get("vertex") else {
        return Err(IngestError::Invalid("the PLY header declares no vertex element".into()));
    };
    let mut total_min = 0u64;
    for def in header.elements.values() {
        total_min = total_min
            .saturating_add(min_element_bytes(def, header.encoding).saturating_mul(def.count as u64));
        if total_min > len {
            return Err(parse_err(format!(
                "the header declares {} {} elements (and those before them), which need at least {total_min} bytes, \
                 but the file has only {len} bytes",
                def.count, def.name
            )));
        }
    }
    let has_color = vertex_def
        .properties
        .keys()
        .filter_map(|k| color_channel(k))
        .collect::<std::collections::BTreeSet<_>>()
        .len()
        == 3;
    let f32_exact = ["x", "y", "z"]
        .iter()
        .all(|a| vertex_def.properties.get(*a).is_some_and(|p| exact_in_f32(&p.data_type)));
    sink.begin(RecordLayout { f64_positions: !f32_exact, color: has_color })?;

    let mut input = ElementReader { reader, encoding: header.encoding, line: String::new() };
    let mut table: Option<VertexTable> = None;
    // Faces that come before the vertices (rare): their fans are held until the vertices are read.
    let mut early: Vec<[u32; 3]> = Vec::new();
    let mut scratch = Vec::new();
    // Elements must be read in header order.
    for (name, def) in &header.elements {
        match name.as_str() {
            "vertex" => table = Some(read_vertices(&mut input, def, sink, opts.memory_budget)?),
            "face" => {
                let parser = Parser::<FaceRecord>::new();
                let mut batch = Vec::new();
                for start in (0..def.count).step_by(BATCH) {
                    input.read_batch(&parser, def, start, BATCH.min(def.count - start), &mut batch)?;
                    if let Some(t) = &table {
                        emit_faces(&batch, start, t, sink)?;
                        sink.tick()?;
                        continue;
                    }
                    for (k, f) in batch.iter().enumerate() {
                        let i = start + k;
                        let poly = f.indices(&mut scratch);
                        if poly.iter().any(|&v| v as usize >= vertex_def.count) {
                            check_polygon(poly, vertex_def.count, i)?;
                        }
                        for k in 1..poly.len().saturating_sub(1) {
                            early.push([poly[0], poly[k], poly[k + 1]]);
                        }
                        if early.len() as u64 * 12 > opts.memory_budget / 4 {
                            return Err(IngestError::TooLarge(
                                "the PLY's faces come before its vertices and do not fit a quarter of \
                                 the memory budget: raise --memory-budget"
                                    .into(),
                            ));
                        }
                    }
                    sink.tick()?;
                }
            }
            _ if def.properties.is_empty() => {} // nothing stored, nothing to read
            _ => {
                let parser = Parser::<Skipped>::new();
                for i in 0..def.count {
                    input.read(&parser, def, i)?;
                    if i % TICK_EVERY == TICK_EVERY - 1 {
                        sink.tick()?;
                    }
                }
            }
        }
    }
    if let Some(t) = &table {
        let mut out = Vec::new();
        for (c, tris) in early.chunks(BATCH).enumerate() {
            out.clear();
            for (k, tri) in tris.iter().enumerate() {
                fan(tri, t, c * BATCH + k, &mut out)?;
            }
            sink.triangles(&out)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::{TriangleMesh, read_mesh_bytes};
    use super::*;

    fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
        read_mesh_bytes(bytes, MeshFormat::Ply)
    }

    const ASCII: &[u8] =
        b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";

    #[test]
    fn ascii_polygon_is_fanned() {
        let m = read(ASCII).unwrap();
        assert_eq!(m.triangles.len(), 2);
        assert_eq!(m.triangle(0), [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]);
        assert_eq!(m.triangle(1), [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]);
    }

    #[test]
    fn truncated_and_out_of_range_are_errors() {
        for len in [10, 60, ASCII.len() - 4] {
            assert!(read(&ASCII[..len]).is_err(), "len {len}");
        }
        let bad = String::from_utf8(ASCII.to_vec()).unwrap().replace("4 0 1 2 3", "3 0 1 9");
        assert!(matches!(read(bad.as_bytes()), Err(IngestError::Invalid(_))));
        let neg = String::from_utf8(ASCII.to_vec()).unwrap().replace("4 0 1 2 3", "3 0 1 -1");
        assert!(read(neg.as_bytes()).is_err());
    }

    #[test]
    fn reads_elements_in_header_order() {
        // Binary little-endian with an extra element between vertex and face.
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\n\
property double z\nelement edge 1\nproperty int a\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n"
            .to_vec();
        for v in [[0.0f64, 0.0, 0.0], [1e7, 0.0, 0.0], [0.0, 1.0, 0.0]] {
            for c in v {
                b.extend_from_slice(&c.to_le_bytes());
            }
        }
        b.extend_from_slice(&7i32.to_le_bytes());
        b.push(3);
        for i in [0u32, 1, 2] {
            b.extend_from_slice(&i.to_le_bytes());
        }
        let m = read(&b).unwrap();
        assert_eq!(m.triangle(0), [[0.0, 0.0, 0.0], [1e7, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    }

    #[test]
    fn faces_before_vertices_are_held_then_emitted() {
        let b = b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n\
element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n3 0 1 2\n0 0 0\n1 0 0\n0 1 0\n";
        let m = read(b).unwrap();
        assert_eq!(m.triangle(0), [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    }

    #[test]
    fn huge_counts_fail_before_allocating() {
        for count in ["4000000000", "18446744073709551615"] {
            let b = format!(
                "ply\nformat binary_little_endian 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n\
property float z\nend_header\n"
            );
            let e = read(b.as_bytes()).unwrap_err().to_string();
            assert!(e.contains("but the file has only"), "{e}");
        }
    }
}
