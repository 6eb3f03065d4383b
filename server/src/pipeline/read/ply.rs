//! PLY (ASCII, binary little- and big-endian) through ply-rs-bw's
//! per-element readers: the header is parsed by the crate, then each element
//! is read one at a time, so faces stream straight into the sink.
//!
//! The vertex element is held as compact arrays (f32 positions when x, y, z
//! are exact in f32, else f64; sRGB u8 colours when red/green/blue exist)
//! when they fit half the memory budget. Otherwise the same compact records
//! are written to an unnamed temporary file (gone when closed: on success,
//! error, cancellation and crash) and read back through a page cache of a
//! quarter of the budget: faces are taken in sub-batches whose vertex pages
//! fit the cache, the missing pages are read with positioned reads on all
//! cores (least recently used evicted), and the sub-batch is fanned on all
//! cores as before. Both paths convert each vertex by the same code, so the
//! triangles are bit-identical. Before anything is reserved, every
//! element's count is checked against the bytes the file has left: a header
//! claiming 4e9 vertices in a 100-byte file fails at once. Vertex normals
//! and any other property are read past: voxel normals come from the
//! triangles themselves.

use std::fs::File;
use std::io::{BufRead, Write};
use std::os::unix::fs::FileExt;

use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{
    BeginList, ElementDef, Encoding, Header, PropertyAccess, PropertyAccessResult, PropertyType, ScalarType,
};

use super::{
    EncodedPiece, IngestError, MeshFormat, ReadOptions, SRGB_TO_LINEAR, TICK_EVERY, TriangleSink,
    check_polygon,
};
use crate::pipeline::stream::RecordLayout;

/// Where one scalar vertex property goes, as [`VertexRecord`]'s setters decide.
#[derive(Clone, Copy)]
enum VertexTarget {
    Position(usize),
    Color(usize),
    Ignored,
}

impl VertexTarget {
    /// Where [`VertexRecord`]'s setter for a `t` property called `name` stores its value.
    fn of(name: &str, t: &ScalarType) -> Self {
        let position = match name {
            "x" => VertexTarget::Position(0),
            "y" => VertexTarget::Position(1),
            "z" => VertexTarget::Position(2),
            _ => VertexTarget::Ignored,
        };
        match t {
            ScalarType::UChar | ScalarType::UShort | ScalarType::Float | ScalarType::Double => {
                color_channel(name).map_or(position, VertexTarget::Color)
            }
            _ => position,
        }
    }
}

/// How vertex batches are decoded: fixed-size binary records, common ASCII
/// lines, or element by element through the crate.
enum VertexDecoder {
    Records(VertexRecords),
    Ascii(AsciiVertices),
    General,
}

/// Binary vertex elements of scalar properties only: fixed-size records,
/// decoded straight from their bytes into the values the crate's setters
/// would store (same conversions, properties applied in header order).
struct VertexRecords {
    size: usize,
    big: bool,
    fields: Vec<(usize, ScalarType, VertexTarget)>,
}

impl VertexRecords {
    fn of(def: &ElementDef, encoding: Encoding) -> Option<Self> {
        if encoding == Encoding::Ascii {
            return None;
        }
        let mut fields = Vec::new();
        let mut at = 0usize;
        for (name, p) in &def.properties {
            let PropertyType::Scalar(t) = &p.data_type else {
                return None;
            };
            fields.push((at, t.clone(), VertexTarget::of(name, t)));
            at += scalar_size(t) as usize;
        }
        (at > 0).then_some(Self { size: at, big: encoding == Encoding::BinaryBigEndian, fields })
    }

    fn decode(&self, r: &[u8]) -> VertexRecord {
        fn word<const N: usize>(r: &[u8], at: usize) -> [u8; N] {
            r[at..at + N].try_into().expect("in the record")
        }
        let mut v = VertexRecord::new();
        for &(at, ref t, target) in &self.fields {
            if let VertexTarget::Ignored = target {
                continue;
            }
            let big = self.big;
            // (as f64 for a position, the setter's colour value for a channel)
            let (p, c): (f64, f32) = match t {
                ScalarType::Char => (r[at] as i8 as f64, 0.0),
                ScalarType::UChar => (r[at] as f64, r[at] as f32 / 255.0),
                ScalarType::Short => {
                    let w = word::<2>(r, at);
                    ((if big { i16::from_be_bytes(w) } else { i16::from_le_bytes(w) }) as f64, 0.0)
                }
                ScalarType::UShort => {
                    let w = word::<2>(r, at);
                    let x = if big { u16::from_be_bytes(w) } else { u16::from_le_bytes(w) };
                    (x as f64, x as f32 / 65535.0)
                }
                ScalarType::Int => {
                    let w = word::<4>(r, at);
                    ((if big { i32::from_be_bytes(w) } else { i32::from_le_bytes(w) }) as f64, 0.0)
                }
                ScalarType::UInt => {
                    let w = word::<4>(r, at);
                    ((if big { u32::from_be_bytes(w) } else { u32::from_le_bytes(w) }) as f64, 0.0)
                }
                ScalarType::Float => {
                    let w = word::<4>(r, at);
                    let x = if big { f32::from_be_bytes(w) } else { f32::from_le_bytes(w) };
                    (x as f64, x)
                }
                ScalarType::Double => {
                    let w = word::<8>(r, at);
                    let x = if big { f64::from_be_bytes(w) } else { f64::from_le_bytes(w) };
                    (x, x as f32)
                }
            };
            match target {
                VertexTarget::Position(a) => v.p[a] = p,
                VertexTarget::Color(i) => v.c[i] = c,
                VertexTarget::Ignored => {}
            }
        }
        v
    }
}

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
}

/// A polygon's vertex indices: a face as read, or a fanned triangle held
/// while the vertices are still to come.
trait Polygon {
    /// The indices, converted; `scratch` holds signed lists after conversion.
    fn indices<'a>(&'a self, scratch: &'a mut Vec<u32>) -> &'a [u32];
}

impl Polygon for [u32; 3] {
    fn indices<'a>(&'a self, _scratch: &'a mut Vec<u32>) -> &'a [u32] {
        self
    }
}

impl Polygon for FaceRecord {
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

/// A face as [`ElementReader::read_faces`] reads it: a triangle decoded
/// straight from its fixed-size record, or any other face as the crate reads it.
enum Face {
    Triangle([u32; 3]),
    Other(Box<FaceRecord>),
}

impl Polygon for Face {
    fn indices<'a>(&'a self, scratch: &'a mut Vec<u32>) -> &'a [u32] {
        match self {
            Face::Triangle(t) => t,
            Face::Other(r) => r.indices(scratch),
        }
    }
}

/// The common binary face element: one property, a list of vertex indices
/// with a one-byte count and 4-byte items (`list uchar int|uint vertex_indices`).
/// Its triangles are fixed-size records of 13 bytes, decoded here exactly as
/// the crate's setters would store them; every other face goes to the crate.
#[derive(Clone, Copy)]
struct TriangleRecords {
    signed: bool,
    big: bool,
}

const TRIANGLE_RECORD: usize = 13;

impl TriangleRecords {
    fn of(def: &ElementDef, encoding: Encoding) -> Option<Self> {
        if encoding == Encoding::Ascii || def.properties.len() != 1 {
            return None;
        }
        let (name, p) = def.properties.iter().next()?;
        let PropertyType::List(ScalarType::UChar, item) = &p.data_type else {
            return None;
        };
        let signed = match item {
            ScalarType::Int => true,
            ScalarType::UInt => false,
            _ => return None,
        };
        is_index_list(name).then_some(Self { signed, big: encoding == Encoding::BinaryBigEndian })
    }

    /// The indices of one 13-byte record whose count byte is 3; negative
    /// `int`s become `u32::MAX`, as [`FaceRecord::indices`] makes them.
    #[inline]
    fn decode(self, r: &[u8]) -> [u32; 3] {
        std::array::from_fn(|k| {
            let b: [u8; 4] = r[1 + 4 * k..5 + 4 * k].try_into().expect("4 bytes");
            let v = if self.big { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) };
            if self.signed && (v as i32) < 0 { u32::MAX } else { v }
        })
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
    /// The ASCII lines of one batch, and where each ends.
    text: Vec<u8>,
    ends: Vec<usize>,
    /// The next batch's lines, read while this one is parsed: its first
    /// element, its count and how the read ended (an error is the next batch's).
    ahead: Option<(usize, usize, Result<(), IngestError>)>,
    ahead_text: Vec<u8>,
    ahead_ends: Vec<usize>,
}

/// Longest ASCII element line accepted (a face of ~100k vertices).
const MAX_LINE: u64 = 1 << 20;
/// Elements read per batch; ASCII batches are parsed in parallel.
const BATCH: usize = 1 << 14;

impl<R: BufRead + Send> ElementReader<R> {
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
        self.read_lines(def, start, n)?;
        *out = self.parse_lines(def, start, |line, i| ascii_element(parser, line, def, i))?;
        Ok(())
    }

    /// Reads the next `n` ASCII lines (elements `start..start + n`) into
    /// `self.text`, line breaks kept, each line's end in `self.ends`: runs of
    /// lines are copied from the reader's buffer at once, their breaks found
    /// by `memchr`, and nothing past the `n`th line is consumed. A line is
    /// what `BufRead::read_line` reads (up to and with `\n`, or the file's
    /// last bytes); one longer than 1 MiB is an error, as is the file ending
    /// before the `n`th line. UTF-8 is checked by [`Self::parse_lines`].
    fn read_lines(&mut self, def: &ElementDef, start: usize, n: usize) -> Result<(), IngestError> {
        if let Some((first, count, read)) = self.ahead.take() {
            if (first, count) != (start, n) {
                // The batch read ahead is always the next one asked for.
                return Err(parse_err(format!("{} {start}: lines read out of order", def.name)));
            }
            std::mem::swap(&mut self.text, &mut self.ahead_text);
            std::mem::swap(&mut self.ends, &mut self.ahead_ends);
            return read;
        }
        Self::read_lines_into(&mut self.reader, def, start, n, &mut self.text, &mut self.ends)
    }

    /// [`Self::read_lines`] into the given buffers.
    fn read_lines_into(
        reader: &mut Reader<R>,
        def: &ElementDef,
        start: usize,
        n: usize,
        text: &mut Vec<u8>,
        ends: &mut Vec<usize>,
    ) -> Result<(), IngestError> {
        let too_long = |i: usize| parse_err(format!("{} {i}: line longer than 1 MiB", def.name));
        text.clear();
        ends.clear();
        let mut line_start = 0usize;
        while ends.len() < n {
            let i = start + ends.len();
            let buf = reader.get_mut().fill_buf().map_err(|e| parse_err(format!("{} {i}: {e}", def.name)))?;
            if buf.is_empty() {
                if text.len() > line_start {
                    // The file's last line, without a break.
                    line_start = text.len();
                    ends.push(line_start);
                    continue;
                }
                return Err(parse_err(format!(
                    "{} {i}: the file ends early (the header declares {})",
                    def.name, def.count
                )));
            }
            let base = text.len();
            let mut used = buf.len();
            for nl in memchr::memchr_iter(b'\n', buf) {
                let end = base + nl + 1;
                if end - line_start > MAX_LINE as usize {
                    return Err(too_long(start + ends.len()));
                }
                ends.push(end);
                line_start = end;
                if ends.len() == n {
                    used = nl + 1;
                    break;
                }
            }
            text.extend_from_slice(&buf[..used]);
            reader.get_mut().consume(used);
            if text.len() - line_start >= MAX_LINE as usize {
                return Err(too_long(start + ends.len()));
            }
        }
        Ok(())
    }

    /// Parses the lines [`Self::read_lines`] read on all cores, in order: `f`
    /// takes each line (checked to be UTF-8, as `read_line` checks it) and
    /// its element's index. Meanwhile the next batch of the same element
    /// (elements are read in batches of [`BATCH`]) is read ahead, so the
    /// reader's thread does not split lines while the others wait.
    fn parse_lines<T: Send>(
        &mut self,
        def: &ElementDef,
        start: usize,
        f: impl Fn(&str, usize) -> Result<T, IngestError> + Sync + Send,
    ) -> Result<Vec<T>, IngestError> {
        use rayon::prelude::*;
        let (text, ends) = (&self.text, &self.ends);
        let parse = || {
            (0..ends.len())
                .into_par_iter()
                .with_min_len(256)
                .map(|k| {
                    let bytes = &text[if k == 0 { 0 } else { ends[k - 1] }..ends[k]];
                    let line = std::str::from_utf8(bytes).map_err(|_| {
                        parse_err(format!("{} {}: stream did not contain valid UTF-8", def.name, start + k))
                    })?;
                    f(line, start + k)
                })
                .collect()
        };
        let next = start + ends.len();
        let next_n = BATCH.min(def.count.saturating_sub(next));
        if next_n == 0 {
            return parse();
        }
        let (reader, ahead_text, ahead_ends) = (&mut self.reader, &mut self.ahead_text, &mut self.ahead_ends);
        let (read, parsed) =
            rayon::join(|| Self::read_lines_into(reader, def, next, next_n, ahead_text, ahead_ends), parse);
        self.ahead = Some((next, next_n, read));
        parsed
    }

    /// Reads ASCII faces `start..start + n` into `out`, in order: triangles
    /// of the common face element decoded by `triangles`, any other line
    /// parsed as [`Self::read_batch`] parses it (or its error).
    fn read_ascii_faces(
        &mut self,
        parser: &Parser<FaceRecord>,
        def: &ElementDef,
        triangles: AsciiTriangles,
        start: usize,
        n: usize,
        out: &mut Vec<Face>,
    ) -> Result<(), IngestError> {
        self.read_lines(def, start, n)?;
        *out = self.parse_lines(def, start, |line, i| match triangles.decode(line) {
            Some(t) => Ok(Face::Triangle(t)),
            None => Ok(Face::Other(Box::new(ascii_element(parser, line, def, i)?))),
        })?;
        Ok(())
    }

    /// [`Self::read_batch`] for vertices; fixed-size binary records are decoded
    /// by `records` on all cores.
    fn read_vertex_batch(
        &mut self,
        parser: &Parser<VertexRecord>,
        def: &ElementDef,
        decoder: &VertexDecoder,
        start: usize,
        n: usize,
        out: &mut Vec<VertexRecord>,
    ) -> Result<(), IngestError> {
        use rayon::prelude::*;
        let records = match decoder {
            VertexDecoder::Records(records) => records,
            VertexDecoder::Ascii(ascii) => {
                self.read_lines(def, start, n)?;
                *out = self.parse_lines(def, start, |line, i| match ascii.decode(line) {
                    Some(v) => Ok(v),
                    None => ascii_element(parser, line, def, i),
                })?;
                return Ok(());
            }
            VertexDecoder::General => return self.read_batch(parser, def, start, n, out),
        };
        out.clear();
        let mut bytes = vec![0u8; n * records.size];
        std::io::Read::read_exact(self.reader.get_mut(), &mut bytes).map_err(|e| {
            parse_err(format!("{} {start}..{}: {e} (the header declares {})", def.name, start + n, def.count))
        })?;
        out.par_extend(bytes.par_chunks_exact(records.size).with_min_len(1024).map(|r| records.decode(r)));
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

    /// Reads faces `start..start + n` into `out` (cleared first), in order:
    /// runs of triangles whole in the reader's buffer are decoded on all cores
    /// straight from it; any other face (a polygon, a record straddling the
    /// buffer's end, a bad count, the file's end) is read by the crate, which
    /// parses it or says what is wrong.
    fn read_faces(
        &mut self,
        parser: &Parser<FaceRecord>,
        def: &ElementDef,
        records: TriangleRecords,
        start: usize,
        n: usize,
        out: &mut Vec<Face>,
    ) -> Result<(), IngestError> {
        use rayon::prelude::*;
        out.clear();
        while out.len() < n {
            let i = start + out.len();
            let buf =
                self.reader.get_mut().fill_buf().map_err(|e| parse_err(format!("{} {i}: {e}", def.name)))?;
            let whole = (buf.len() / TRIANGLE_RECORD).min(n - out.len());
            let run = (0..whole).take_while(|&k| buf[k * TRIANGLE_RECORD] == 3).count();
            if run == 0 {
                out.push(Face::Other(Box::new(self.read(parser, def, i)?)));
                continue;
            }
            let bytes = &buf[..run * TRIANGLE_RECORD];
            out.par_extend(
                bytes
                    .par_chunks_exact(TRIANGLE_RECORD)
                    .with_min_len(4096)
                    .map(|r| Face::Triangle(records.decode(r))),
            );
            self.reader.get_mut().consume(run * TRIANGLE_RECORD);
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

/// One ASCII element line, element `i`: [`numeric_ascii_element`], else the crate's parse (or its error).
fn ascii_element<E: PropertyAccess>(
    parser: &Parser<E>,
    line: &str,
    def: &ElementDef,
    i: usize,
) -> Result<E, IngestError> {
    if let Some(e) = numeric_ascii_element(line, def) {
        return Ok(e);
    }
    parser.read_ascii_element(line, def).map_err(|e| parse_err(format!("{} {i}: {e}", def.name)))
}

/// A narrow fast path for ASCII body lines, in front of the crate's
/// `Parser::read_ascii_element` (not a PLY parser: the header, and any line
/// this does not take, stay ply-rs-bw's). The crate matches each line with
/// its PEG grammar, which was most of an ASCII read's parse time (about
/// 13 % of all CPU building the dragon); here a line the grammar accepts, a
/// line break and `[ \t]`-separated numbers `[-+]?[0-9]+(.[0-9]+)?([eE][-+]?[0-9]+)?`,
/// is split directly, and the tokens go through the same `str::parse` into
/// the same setters in the same order as the crate does, so the element is
/// the same. Anything else returns `None` (a token the grammar rejects, a
/// value that does not parse, too few tokens, a list the element takes
/// through a `set_list_*` setter, an unsupported type), and the caller
/// hands the line to the crate, which parses it or says what is wrong.
fn numeric_ascii_element<E: PropertyAccess>(line: &str, def: &ElementDef) -> Option<E> {
    let body = line_body(line);
    let mut tokens = body.split([' ', '\t']).filter(|t| !t.is_empty());
    // The grammar checks every token of the line, used or not.
    if !body.split([' ', '\t']).all(|t| t.is_empty() || is_ply_number(t)) {
        return None;
    }
    let mut e = E::new();
    for (name, prop) in &def.properties {
        let token = tokens.next()?;
        match &prop.data_type {
            PropertyType::Scalar(t) => {
                let set = match t {
                    ScalarType::Char => e.set_char(name, token.parse().ok()?),
                    ScalarType::UChar => e.set_uchar(name, token.parse().ok()?),
                    ScalarType::Short => e.set_short(name, token.parse().ok()?),
                    ScalarType::UShort => e.set_ushort(name, token.parse().ok()?),
                    ScalarType::Int => e.set_int(name, token.parse().ok()?),
                    ScalarType::UInt => e.set_uint(name, token.parse().ok()?),
                    ScalarType::Float => e.set_float(name, token.parse().ok()?),
                    ScalarType::Double => e.set_double(name, token.parse().ok()?),
                };
                if let PropertyAccessResult::UnsupportedType = set {
                    return None;
                }
            }
            PropertyType::List(_, t) => {
                let count: usize = token.parse().ok()?;
                match t {
                    ScalarType::Char => fill_list(e.begin_list_char(name, count), &mut tokens, count)?,
                    ScalarType::UChar => fill_list(e.begin_list_uchar(name, count), &mut tokens, count)?,
                    ScalarType::Short => fill_list(e.begin_list_short(name, count), &mut tokens, count)?,
                    ScalarType::UShort => fill_list(e.begin_list_ushort(name, count), &mut tokens, count)?,
                    ScalarType::Int => fill_list(e.begin_list_int(name, count), &mut tokens, count)?,
                    ScalarType::UInt => fill_list(e.begin_list_uint(name, count), &mut tokens, count)?,
                    ScalarType::Float => fill_list(e.begin_list_float(name, count), &mut tokens, count)?,
                    ScalarType::Double => fill_list(e.begin_list_double(name, count), &mut tokens, count)?,
                }
            }
        }
    }
    Some(e)
}

/// Whether `t` is a number as ply-rs-bw's data-line grammar has it:
/// `[-+]?[0-9]+(.[0-9]+)?([eE][-+]?[0-9]+)?`.
fn is_ply_number(t: &str) -> bool {
    fn digits(b: &[u8]) -> usize {
        b.iter().take_while(|c| c.is_ascii_digit()).count()
    }
    let mut b = t.as_bytes();
    if let [b'-' | b'+', rest @ ..] = b {
        b = rest;
    }
    let n = digits(b);
    if n == 0 {
        return false;
    }
    b = &b[n..];
    if let [b'.', rest @ ..] = b {
        let n = digits(rest);
        if n == 0 {
            return false;
        }
        b = &rest[n..];
    }
    if let [b'e' | b'E', rest @ ..] = b {
        let rest = match rest {
            [b'-' | b'+', r @ ..] => r,
            r => r,
        };
        let n = digits(rest);
        if n == 0 {
            return false;
        }
        b = &rest[n..];
    }
    b.is_empty()
}

/// A line without its line break (`\r\n`, `\n` or `\r`), as the crate's grammar takes it.
fn line_body(line: &str) -> &str {
    line.strip_suffix("\r\n")
        .or_else(|| line.strip_suffix('\n'))
        .or_else(|| line.strip_suffix('\r'))
        .unwrap_or(line)
}

/// ASCII vertex lines of scalar properties only, decoded straight into a
/// [`VertexRecord`]: the tokens [`numeric_ascii_element`] would take (every
/// token a PLY number, at least one a property), each parsed by the same
/// `str::parse` for its property's type and stored where that type's setter
/// stores it (targets found once, from the header). `None` for any other
/// line, which then takes the general path (and its errors).
struct AsciiVertices {
    fields: Vec<(ScalarType, VertexTarget)>,
}

impl AsciiVertices {
    fn of(def: &ElementDef, encoding: Encoding) -> Option<Self> {
        if encoding != Encoding::Ascii || def.properties.is_empty() {
            return None;
        }
        let fields = def
            .properties
            .iter()
            .map(|(name, p)| match &p.data_type {
                PropertyType::Scalar(t) => Some((t.clone(), VertexTarget::of(name, t))),
                PropertyType::List(..) => None,
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Self { fields })
    }

    fn decode(&self, line: &str) -> Option<VertexRecord> {
        let mut v = VertexRecord::new();
        let mut fields = self.fields.iter();
        for token in line_body(line).split([' ', '\t']).filter(|t| !t.is_empty()) {
            if !is_ply_number(token) {
                return None;
            }
            // Tokens past the properties are checked, not used (as by the crate).
            let Some((t, target)) = fields.next() else { continue };
            // (as f64 for a position, the setter's colour value for a channel)
            let (p, c): (f64, f32) = match t {
                ScalarType::Char => (token.parse::<i8>().ok()? as f64, 0.0),
                ScalarType::UChar => {
                    let x = token.parse::<u8>().ok()?;
                    (x as f64, x as f32 / 255.0)
                }
                ScalarType::Short => (token.parse::<i16>().ok()? as f64, 0.0),
                ScalarType::UShort => {
                    let x = token.parse::<u16>().ok()?;
                    (x as f64, x as f32 / 65535.0)
                }
                ScalarType::Int => (token.parse::<i32>().ok()? as f64, 0.0),
                ScalarType::UInt => (token.parse::<u32>().ok()? as f64, 0.0),
                ScalarType::Float => {
                    let x = token.parse::<f32>().ok()?;
                    (x as f64, x)
                }
                ScalarType::Double => {
                    let x = token.parse::<f64>().ok()?;
                    (x, x as f32)
                }
            };
            match *target {
                VertexTarget::Position(a) => v.p[a] = p,
                VertexTarget::Color(i) => v.c[i] = c,
                VertexTarget::Ignored => {}
            }
        }
        // Too few tokens: the crate says which is missing.
        fields.next().is_none().then_some(v)
    }
}

/// The common ASCII face element: one property, a list of vertex indices
/// with `int` or `uint` items. A line holding a triangle (count 3) is
/// decoded straight to its indices, as [`numeric_ascii_element`] and
/// [`FaceRecord::indices`] would make them (count parsed as `usize`, items
/// as `i32`/`u32`, a negative `int` becoming `u32::MAX`); any other line
/// (a polygon, a token that is not a PLY number) returns `None` and takes
/// the general path.
#[derive(Clone, Copy)]
struct AsciiTriangles {
    signed: bool,
}

impl AsciiTriangles {
    fn of(def: &ElementDef, encoding: Encoding) -> Option<Self> {
        if encoding != Encoding::Ascii || def.properties.len() != 1 {
            return None;
        }
        let (name, p) = def.properties.iter().next()?;
        let signed = match &p.data_type {
            PropertyType::List(_, ScalarType::Int) => true,
            PropertyType::List(_, ScalarType::UInt) => false,
            _ => return None,
        };
        is_index_list(name).then_some(Self { signed })
    }

    fn decode(self, line: &str) -> Option<[u32; 3]> {
        self.decode_digits(line).or_else(|| self.decode_tokens(line))
    }

    /// The common line, digits and blanks only, in one pass over its bytes;
    /// `None` for any other, which [`Self::decode_tokens`] then takes. Every
    /// line accepted here is one that [`Self::decode_tokens`] decodes to the
    /// same indices: its tokens are PLY numbers, the count parses as 3 and
    /// each index fits the list's item type.
    fn decode_digits(self, line: &str) -> Option<[u32; 3]> {
        let body = line_body(line).as_bytes();
        let mut values = [0u64; 4];
        let (mut k, mut i) = (0usize, 0usize);
        while i < body.len() {
            match body[i] {
                b' ' | b'\t' => i += 1,
                b'0'..=b'9' => {
                    let start = i;
                    let mut v = 0u64;
                    while i < body.len() && body[i].is_ascii_digit() {
                        // Longer tokens (leading zeros, overflow) take the general path.
                        if i - start == 10 {
                            return None;
                        }
                        v = v * 10 + u64::from(body[i] - b'0');
                        i += 1;
                    }
                    if let Some(slot) = values.get_mut(k) {
                        *slot = v;
                    }
                    k += 1;
                }
                _ => return None,
            }
        }
        let max = if self.signed { i32::MAX as u64 } else { u32::MAX as u64 };
        (k >= 4 && values[0] == 3 && values[1..].iter().all(|&v| v <= max))
            .then(|| [values[1] as u32, values[2] as u32, values[3] as u32])
    }

    fn decode_tokens(self, line: &str) -> Option<[u32; 3]> {
        let mut tokens = line_body(line).split([' ', '\t']).filter(|t| !t.is_empty());
        let mut out = [0u32; 3];
        let mut k = 0usize;
        for token in tokens.by_ref() {
            if !is_ply_number(token) {
                return None;
            }
            if k == 0 {
                if token.parse::<usize>().ok()? != 3 {
                    return None;
                }
            } else {
                out[k - 1] = if self.signed {
                    u32::try_from(token.parse::<i32>().ok()?).unwrap_or(u32::MAX)
                } else {
                    token.parse::<u32>().ok()?
                };
            }
            k += 1;
            if k == 4 {
                break;
            }
        }
        // Tokens past the list are checked, not used (as by the crate).
        (k == 4 && tokens.all(is_ply_number)).then_some(out)
    }
}

/// The crate's in-place list read: the list cleared and filled with `count`
/// parsed tokens; `None` for a list taken through a setter, or bad tokens.
fn fill_list<'t, T: std::str::FromStr>(
    list: BeginList<'_, T>,
    tokens: &mut impl Iterator<Item = &'t str>,
    count: usize,
) -> Option<()> {
    let BeginList::Fill(out) = list else {
        return None;
    };
    out.clear();
    // Capacity only (the crate caps its reservation likewise); the values decide.
    out.reserve(count.min(1 << 16));
    for _ in 0..count {
        out.push(tokens.next()?.parse().ok()?);
    }
    Some(())
}

enum Positions {
    F32(Vec<[f32; 3]>),
    F64(Vec<[f64; 3]>),
}

struct VertexTable {
    positions: Positions,
    colors: Option<Vec<[u8; 3]>>,
}

/// Random access to the vertex table, in memory or paged.
trait Vertices: Sync {
    fn len(&self) -> usize;
    fn has_color(&self) -> bool;
    /// Vertex `i`'s position; `i` < `len()`.
    fn position(&self, i: u32) -> [f64; 3];
    /// Vertex `i`'s linear colour (zeros without colours); `i` < `len()`.
    fn color(&self, i: u32) -> [f32; 3];
}

impl VertexTable {
    fn new(f32_exact: bool, has_color: bool, capacity: usize) -> Self {
        let positions = if f32_exact {
            Positions::F32(Vec::with_capacity(capacity))
        } else {
            Positions::F64(Vec::with_capacity(capacity))
        };
        Self { positions, colors: has_color.then(|| Vec::with_capacity(capacity)) }
    }

    /// Appends vertices as read: the only conversion, in memory or spilled.
    /// On all cores, because this is where the table's fresh pages are first
    /// touched, and the reading thread alone held the read up behind them.
    fn extend(&mut self, batch: &[VertexRecord]) {
        use rayon::prelude::*;
        const MIN: usize = 4096;
        match &mut self.positions {
            Positions::F32(p) => {
                p.par_extend(batch.par_iter().with_min_len(MIN).map(|v| v.p.map(|c| c as f32)))
            }
            Positions::F64(p) => p.par_extend(batch.par_iter().with_min_len(MIN).map(|v| v.p)),
        }
        if let Some(c) = &mut self.colors {
            c.par_extend(batch.par_iter().with_min_len(MIN).map(|v| {
                v.c.map(|x| if x.is_nan() { 0 } else { (x.clamp(0.0, 1.0) * 255.0).round() as u8 })
            }));
        }
    }

    fn clear(&mut self) {
        match &mut self.positions {
            Positions::F32(p) => p.clear(),
            Positions::F64(p) => p.clear(),
        }
        if let Some(c) = &mut self.colors {
            c.clear();
        }
    }

    /// Appends every vertex as a fixed-size little-endian record (positions, then colour).
    fn write_records(&self, out: &mut Vec<u8>) {
        for i in 0..Vertices::len(self) {
            match &self.positions {
                Positions::F32(p) => p[i].iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes())),
                Positions::F64(p) => p[i].iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes())),
            }
            if let Some(c) = &self.colors {
                out.extend_from_slice(&c[i]);
            }
        }
    }

    /// The table of the records [`Self::write_records`] wrote.
    fn from_records(bytes: &[u8], f32_exact: bool, has_color: bool) -> Self {
        let at = if f32_exact { 12 } else { 24 };
        let size = record_size(f32_exact, has_color);
        let mut t = Self::new(f32_exact, has_color, bytes.len() / size);
        for r in bytes.chunks_exact(size) {
            match &mut t.positions {
                Positions::F32(p) => {
                    p.push(std::array::from_fn(|a| f32::from_le_bytes([0, 1, 2, 3].map(|k| r[4 * a + k]))))
                }
                Positions::F64(p) => p.push(std::array::from_fn(|a| {
                    f64::from_le_bytes([0, 1, 2, 3, 4, 5, 6, 7].map(|k| r[8 * a + k]))
                })),
            }
            if let Some(c) = &mut t.colors {
                c.push([r[at], r[at + 1], r[at + 2]]);
            }
        }
        t
    }
}

/// Bytes of one compact vertex, in memory and in the spill file.
fn record_size(f32_exact: bool, has_color: bool) -> usize {
    (if f32_exact { 12 } else { 24 }) + if has_color { 3 } else { 0 }
}

impl Vertices for VertexTable {
    fn len(&self) -> usize {
        match &self.positions {
            Positions::F32(v) => v.len(),
            Positions::F64(v) => v.len(),
        }
    }

    fn has_color(&self) -> bool {
        self.colors.is_some()
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

/// log2 of the vertices in a page of the paged table.
const PAGE_SHIFT: u32 = 12;
const PAGE: usize = 1 << PAGE_SHIFT;

fn spill_err(source: std::io::Error) -> IngestError {
    IngestError::Io { path: "the temporary file of the PLY's vertices".into(), source }
}

/// The vertex table in a temporary file of fixed-size records, read through
/// a least-recently-used cache of at most `cap` pages of [`PAGE`] vertices.
struct PagedTable {
    file: File,
    len: usize,
    f32_exact: bool,
    has_color: bool,
    cap: usize,
    /// By page index: the page when resident.
    pages: Vec<Option<Box<VertexTable>>>,
    /// By page index: the sub-batch that last used it.
    last_used: Vec<u64>,
    /// By page index: `epoch` when the current sub-batch needs it.
    mark: Vec<u64>,
    resident: Vec<u32>,
    epoch: u64,
}

impl PagedTable {
    /// Vertices `first..first + n`, read from the file.
    fn read_range(&self, first: usize, n: usize) -> Result<VertexTable, IngestError> {
        let size = record_size(self.f32_exact, self.has_color);
        let mut bytes = vec![0u8; n * size];
        self.file.read_exact_at(&mut bytes, (first * size) as u64).map_err(spill_err)?;
        Ok(VertexTable::from_records(&bytes, self.f32_exact, self.has_color))
    }

    /// The vertices of one polygon (all in range), in its order.
    fn read_polygon(&self, poly: &[u32]) -> Result<VertexTable, IngestError> {
        let size = record_size(self.f32_exact, self.has_color);
        let mut bytes = vec![0u8; poly.len() * size];
        for (k, &v) in poly.iter().enumerate() {
            self.file
                .read_exact_at(&mut bytes[k * size..(k + 1) * size], v as u64 * size as u64)
                .map_err(spill_err)?;
        }
        Ok(VertexTable::from_records(&bytes, self.f32_exact, self.has_color))
    }

    /// Makes the pages in `need` (at most `cap`) resident: the least recently
    /// used of the others are dropped first, the missing read on all cores.
    fn load(&mut self, need: &[u32]) -> Result<(), IngestError> {
        use rayon::prelude::*;
        let missing: Vec<u32> = need.iter().copied().filter(|&p| self.pages[p as usize].is_none()).collect();
        let over = (self.resident.len() + missing.len()).saturating_sub(self.cap);
        if over > 0 {
            let (mark, last, epoch) = (&self.mark, &self.last_used, self.epoch);
            let (mut old, keep): (Vec<u32>, Vec<u32>) =
                self.resident.iter().partition(|&&p| mark[p as usize] != epoch);
            old.sort_unstable_by_key(|&p| last[p as usize]);
            for &p in &old[..over] {
                self.pages[p as usize] = None;
            }
            self.resident = keep;
            self.resident.extend_from_slice(&old[over..]);
        }
        let read: Result<Vec<(u32, VertexTable)>, IngestError> = missing
            .par_iter()
            .map(|&p| {
                let first = (p as usize) << PAGE_SHIFT;
                Ok((p, self.read_range(first, PAGE.min(self.len - first))?))
            })
            .collect();
        for (p, page) in read? {
            self.pages[p as usize] = Some(Box::new(page));
            self.resident.push(p);
        }
        for &p in need {
            self.last_used[p as usize] = self.epoch;
        }
        Ok(())
    }

    fn view(&self) -> PagedView<'_> {
        PagedView { pages: &self.pages, len: self.len, has_color: self.has_color }
    }
}

/// The resident pages of a [`PagedTable`], read-only, for fanning on all cores.
struct PagedView<'a> {
    pages: &'a [Option<Box<VertexTable>>],
    len: usize,
    has_color: bool,
}

impl PagedView<'_> {
    fn page(&self, i: u32) -> &VertexTable {
        self.pages[(i >> PAGE_SHIFT) as usize]
            .as_deref()
            .expect("a sub-batch's pages are loaded before it is fanned")
    }
}

impl Vertices for PagedView<'_> {
    fn len(&self) -> usize {
        self.len
    }

    fn has_color(&self) -> bool {
        self.has_color
    }

    fn position(&self, i: u32) -> [f64; 3] {
        self.page(i).position(i & (PAGE as u32 - 1))
    }

    fn color(&self, i: u32) -> [f32; 3] {
        self.page(i).color(i & (PAGE as u32 - 1))
    }
}

/// The vertex table: in memory, or paged from a temporary file.
enum Table {
    Memory(VertexTable),
    Paged(PagedTable),
}

impl Table {
    /// Fans `faces` (the first is face `start`) into `sink` in file order.
    fn emit<P: Polygon + Sync>(
        &mut self,
        faces: &[P],
        start: usize,
        sink: &mut dyn TriangleSink,
    ) -> Result<(), IngestError> {
        let t = match self {
            Table::Memory(t) => return emit_faces(faces, start, t, sink),
            Table::Paged(t) => t,
        };
        let mut scratch = Vec::new();
        let mut need: Vec<u32> = Vec::new();
        let mut i = 0;
        while i < faces.len() {
            // The longest run of faces from i whose pages fit the cache.
            t.epoch += 1;
            let epoch = t.epoch;
            need.clear();
            let mut j = i;
            while j < faces.len() {
                let before = need.len();
                for &v in faces[j].indices(&mut scratch) {
                    // Out-of-range indices need no page: fanning reports them.
                    if (v as usize) < t.len {
                        let p = (v >> PAGE_SHIFT) as usize;
                        if t.mark[p] != epoch {
                            t.mark[p] = epoch;
                            need.push(p as u32);
                        }
                    }
                }
                if need.len() > t.cap && j > i {
                    for p in need.drain(before..) {
                        t.mark[p as usize] = 0;
                    }
                    break;
                }
                j += 1;
                if need.len() > t.cap {
                    break;
                }
            }
            if need.len() > t.cap {
                // One face spans more pages than the cache holds: its vertices are read one by one.
                let poly = faces[i].indices(&mut scratch);
                check_polygon(poly, t.len, start + i)?;
                let local = t.read_polygon(poly)?;
                let order: Vec<u32> = (0..poly.len() as u32).collect();
                let mut out = Vec::new();
                fan(&order, &local, start + i, &mut out)?;
                sink.triangles(&out)?;
            } else {
                t.load(&need)?;
                emit_faces(&faces[i..j], start + i, &t.view(), sink)?;
            }
            i = j;
        }
        Ok(())
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

fn read_vertices<R: BufRead + Send>(
    input: &mut ElementReader<R>,
    def: &ElementDef,
    sink: &mut dyn TriangleSink,
    opts: &ReadOptions,
) -> Result<Table, IngestError> {
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
    let per_vertex = record_size(f32_exact, has_color) as u64;
    let needed = def.count as u64 * per_vertex;
    let limit = opts.vertex_memory.unwrap_or(opts.memory_budget / 2);
    let parser = Parser::<VertexRecord>::new();
    let decoder = match (VertexRecords::of(def, input.encoding), AsciiVertices::of(def, input.encoding)) {
        (Some(records), _) => VertexDecoder::Records(records),
        (None, Some(ascii)) => VertexDecoder::Ascii(ascii),
        (None, None) => VertexDecoder::General,
    };
    let mut batch = Vec::new();
    if needed <= limit {
        // Reserving by the count is safe here: it was checked against the file size and the budget.
        let mut table = VertexTable::new(f32_exact, has_color, def.count);
        for start in (0..def.count).step_by(BATCH) {
            input.read_vertex_batch(
                &parser,
                def,
                &decoder,
                start,
                BATCH.min(def.count - start),
                &mut batch,
            )?;
            table.extend(&batch);
            sink.tick()?;
        }
        return Ok(Table::Memory(table));
    }
    // Too large to hold: spill compact records to an unnamed temporary file.
    let file = match &opts.temp_dir {
        Some(dir) => tempfile::tempfile_in(dir),
        None => tempfile::tempfile(),
    }
    .map_err(spill_err)?;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, &file);
    let mut chunk = VertexTable::new(f32_exact, has_color, BATCH);
    let mut bytes = Vec::with_capacity(BATCH * per_vertex as usize);
    for start in (0..def.count).step_by(BATCH) {
        input.read_vertex_batch(&parser, def, &decoder, start, BATCH.min(def.count - start), &mut batch)?;
        chunk.clear();
        chunk.extend(&batch);
        bytes.clear();
        chunk.write_records(&mut bytes);
        out.write_all(&bytes).map_err(spill_err)?;
        sink.tick()?;
    }
    out.flush().map_err(spill_err)?;
    drop(out);
    let page_count = def.count.div_ceil(PAGE);
    let cap = (limit / 2 / (PAGE as u64 * per_vertex)).max(1) as usize;
    Ok(Table::Paged(PagedTable {
        file,
        len: def.count,
        f32_exact,
        has_color,
        cap,
        pages: (0..page_count).map(|_| None).collect(),
        last_used: vec![0; page_count],
        mark: vec![0; page_count],
        resident: Vec::new(),
        epoch: 0,
    }))
}

/// One triangle for the sink: positions and linear colour.
type Tri = ([[f64; 3]; 3], [f32; 3]);

/// Fans a polygon, calling `f` with each triangle and its colour.
#[inline]
fn fan_each<V: Vertices>(
    poly: &[u32],
    table: &V,
    face: usize,
    mut f: impl FnMut([[f64; 3]; 3], [f32; 3]),
) -> Result<(), IngestError> {
    check_polygon(poly, table.len(), face)?;
    for k in 1..poly.len().saturating_sub(1) {
        let idx = [poly[0], poly[k], poly[k + 1]];
        let tri = idx.map(|i| table.position(i));
        let color = if table.has_color() {
            let c = idx.map(|i| table.color(i));
            std::array::from_fn(|a| (c[0][a] + c[1][a] + c[2][a]) / 3.0)
        } else {
            [0.0; 3]
        };
        f(tri, color);
    }
    Ok(())
}

/// Fans a polygon into `out`.
fn fan<V: Vertices>(poly: &[u32], table: &V, face: usize, out: &mut Vec<Tri>) -> Result<(), IngestError> {
    fan_each(poly, table, face, |tri, color| out.push((tri, color)))
}

/// Fans a batch of faces (the first is face `start`) on all cores and hands
/// the triangles to the sink in file order; the first bad face in file order
/// is the error. A sink that takes encoded records gets them checked and
/// encoded here, on the same cores.
fn emit_faces<P: Polygon + Sync, V: Vertices>(
    faces: &[P],
    start: usize,
    table: &V,
    sink: &mut dyn TriangleSink,
) -> Result<(), IngestError> {
    use rayon::prelude::*;
    const PIECE: usize = 1024;
    if let Some(layout) = sink.encoded_layout() {
        let pieces: Vec<Result<EncodedPiece, IngestError>> = faces
            .par_chunks(PIECE)
            .enumerate()
            .map(|(p, piece)| {
                let mut scratch = Vec::new();
                let mut out = EncodedPiece::with_capacity(layout, piece.len());
                for (k, f) in piece.iter().enumerate() {
                    fan_each(f.indices(&mut scratch), table, start + p * PIECE + k, |tri, color| {
                        out.push(layout, &tri, color)
                    })?;
                }
                Ok(out)
            })
            .collect();
        let pieces = pieces.into_iter().collect::<Result<Vec<_>, _>>()?;
        return sink.pieces(pieces);
    }
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

/// One batch of faces read: fanned into the sink, or held (as triangles)
/// when the vertices are still to come.
struct FaceBatch<'a> {
    /// Its first face's index.
    start: usize,
    table: &'a mut Option<Table>,
    early: &'a mut Vec<[u32; 3]>,
    /// The header's vertex count.
    vertices: usize,
}

impl FaceBatch<'_> {
    fn take<P: Polygon + Sync>(
        &mut self,
        batch: &[P],
        sink: &mut dyn TriangleSink,
        opts: &ReadOptions,
    ) -> Result<(), IngestError> {
        if let Some(t) = self.table {
            return t.emit(batch, self.start, sink);
        }
        let mut scratch = Vec::new();
        for (k, f) in batch.iter().enumerate() {
            let i = self.start + k;
            let poly = f.indices(&mut scratch);
            if poly.iter().any(|&v| v as usize >= self.vertices) {
                check_polygon(poly, self.vertices, i)?;
            }
            for k in 1..poly.len().saturating_sub(1) {
                self.early.push([poly[0], poly[k], poly[k + 1]]);
            }
            if self.early.len() as u64 * 12 > opts.memory_budget / 4 {
                return Err(IngestError::TooLarge(
                    "the PLY's faces come before its vertices and do not fit a quarter of \
                     the memory budget: raise --memory-budget"
                        .into(),
                ));
            }
        }
        Ok(())
    }
}

/// Streams a PLY's triangles into `sink`. `len` is the whole input's size.
pub(super) fn stream<R: BufRead + Send>(
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

    let mut input = ElementReader {
        reader,
        encoding: header.encoding,
        line: String::new(),
        text: Vec::new(),
        ends: Vec::new(),
        ahead: None,
        ahead_text: Vec::new(),
        ahead_ends: Vec::new(),
    };
    let mut table: Option<Table> = None;
    // Faces that come before the vertices (rare): their fans are held until the vertices are read.
    let mut early: Vec<[u32; 3]> = Vec::new();
    // Elements must be read in header order.
    for (name, def) in &header.elements {
        match name.as_str() {
            "vertex" => table = Some(read_vertices(&mut input, def, sink, opts)?),
            "face" => {
                let parser = Parser::<FaceRecord>::new();
                let records = TriangleRecords::of(def, header.encoding);
                let ascii = AsciiTriangles::of(def, header.encoding);
                let (mut fast, mut crate_read) = (Vec::new(), Vec::new());
                for start in (0..def.count).step_by(BATCH) {
                    let n = BATCH.min(def.count - start);
                    let mut faces =
                        FaceBatch { start, table: &mut table, early: &mut early, vertices: vertex_def.count };
                    match (records, ascii) {
                        (Some(r), _) => {
                            input.read_faces(&parser, def, r, start, n, &mut fast)?;
                            faces.take(&fast, sink, opts)?;
                        }
                        (None, Some(t)) => {
                            input.read_ascii_faces(&parser, def, t, start, n, &mut fast)?;
                            faces.take(&fast, sink, opts)?;
                        }
                        (None, None) => {
                            input.read_batch(&parser, def, start, n, &mut crate_read)?;
                            faces.take(&crate_read, sink, opts)?;
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
    if let Some(t) = &mut table {
        for (c, tris) in early.chunks(BATCH).enumerate() {
            t.emit(tris, c * BATCH, sink)?;
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

    /// Fails if the fixed-size record decoders give a vertex or a triangle
    /// other than the crate's parse of the same bytes: every scalar type in
    /// both byte orders (positions, colour channels, ignored properties),
    /// random bytes (NaN, infinities, negative indices included).
    #[test]
    fn record_decoders_match_the_crate() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(8);
        let header = |format: &str, props: &str| {
            let text = format!("ply\nformat {format} 1.0\nelement vertex 1\n{props}end_header\n");
            let mut r = Reader::new(std::io::BufReader::new(text.as_bytes()));
            Parser::<Skipped>::new().read_header(&mut r).unwrap()
        };
        let vertex_props = "property double x\nproperty float y\nproperty int z\nproperty uchar red\n\
             property ushort green\nproperty float blue\nproperty short extra\nproperty char x2\n\
             property uint u\nproperty double diffuse_red\n";
        let other_props =
            "property uchar x\nproperty ushort y\nproperty char z\nproperty short r\nproperty int g\n";
        for format in ["binary_little_endian", "binary_big_endian"] {
            for props in [vertex_props, other_props] {
                let h = header(format, props);
                let def = &h.elements["vertex"];
                let records = VertexRecords::of(def, h.encoding).unwrap();
                let parser = Parser::<VertexRecord>::new();
                for _ in 0..2000 {
                    let bytes: Vec<u8> = (0..records.size).map(|_| rng.random()).collect();
                    let mut b = &bytes[..];
                    let want = if h.encoding == Encoding::BinaryBigEndian {
                        parser.read_big_endian_element(&mut b, def)
                    } else {
                        parser.read_little_endian_element(&mut b, def)
                    }
                    .unwrap();
                    let got = records.decode(&bytes);
                    assert_eq!(got.p.map(f64::to_bits), want.p.map(f64::to_bits), "{format} {bytes:?}");
                    assert_eq!(got.c.map(f32::to_bits), want.c.map(f32::to_bits), "{format} {bytes:?}");
                }
            }
            for item in ["int", "uint"] {
                let h = header(format, &format!("property list uchar {item} vertex_indices\n"));
                let def = &h.elements["vertex"];
                let records = TriangleRecords::of(def, h.encoding).unwrap();
                let parser = Parser::<FaceRecord>::new();
                for k in 0..2000 {
                    let mut bytes: Vec<u8> = (0..TRIANGLE_RECORD).map(|_| rng.random()).collect();
                    bytes[0] = 3;
                    if k % 3 == 0 {
                        bytes[1..5].copy_from_slice(&[0x80, 0, 0, 0x80]); // negative either way
                    }
                    let mut b = &bytes[..];
                    let want = if h.encoding == Encoding::BinaryBigEndian {
                        parser.read_big_endian_element(&mut b, def)
                    } else {
                        parser.read_little_endian_element(&mut b, def)
                    }
                    .unwrap();
                    let mut scratch = Vec::new();
                    assert_eq!(
                        &records.decode(&bytes)[..],
                        want.indices(&mut scratch),
                        "{format} {item} {bytes:?}"
                    );
                }
            }
        }
        // Not the common layout: the crate reads them.
        let h = header("binary_little_endian", "property list uchar short vertex_indices\n");
        assert!(TriangleRecords::of(&h.elements["vertex"], h.encoding).is_none());
        let h = header("ascii", "property list uchar int vertex_indices\n");
        assert!(TriangleRecords::of(&h.elements["vertex"], h.encoding).is_none());
        assert!(VertexRecords::of(&h.elements["vertex"], h.encoding).is_none());
    }

    const ASCII: &[u8] =
        b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";

    /// Fails if the numeric fast path gives an element the crate would not:
    /// where the crate parses a line, the fast path must give the same element
    /// or step aside; where the crate rejects it, the fast path must step aside.
    #[test]
    fn numeric_fast_path_agrees_with_the_crate() {
        use ply_rs_bw::ply::{Addable, DefaultElement, PropertyDef};
        let mut scalars = ElementDef::new("v".into());
        for (name, t) in [
            ("a", ScalarType::Char),
            ("b", ScalarType::UChar),
            ("c", ScalarType::Short),
            ("d", ScalarType::UShort),
            ("e", ScalarType::Int),
            ("f", ScalarType::UInt),
            ("g", ScalarType::Float),
            ("h", ScalarType::Double),
        ] {
            scalars.properties.add(PropertyDef::new(name.into(), PropertyType::Scalar(t)));
        }
        let mut faces = ElementDef::new("face".into());
        faces.properties.add(PropertyDef::new(
            "vertex_indices".into(),
            PropertyType::List(ScalarType::UChar, ScalarType::Int),
        ));
        let scalar_lines = [
            "1 2 3 4 5 6 7.5 8e3\n",
            "-1 255 -3 4 -5 6 -7.25 8.5E-3\r\n",
            "\t 1\t2 3  4 5 6 +7.5 -8e+3 \t\r",
            "1 2 3 4 5 6 7 8 9 10 extra\n",
            "1 2 3 4 5 6 7 8 9 10 11\n",
            "1 2 3 4 5 6 1e400 -1e-400\n",
            "0.12345678901234567 2 3 4 5 6 0.1 0.1\n",
            "1 -2 3 4 5 6 7 8\n",
            "1 2 3 4 5 6 7 8",
            "1 2 3 4 5 6 7.\n",
            "1 2 3 4 5 6 .5 8\n",
            "1 2 3 4 5 6 7e 8\n",
            "1 2 3 4 5 6 nan 8\n",
            "1 2 3 4 5 6 inf 8\n",
            "1 2 3 4 5 6 7,5 8\n",
            "1 2 3 4 5 6 7\n",
            "1 2 3 4 5 6 7 8\n\n",
            "1 2 3 4 5 6 7 8\r\r\n",
            "128 2 3 4 5 6 7 8\n",
            "\n",
            "",
        ];
        let parser = Parser::<DefaultElement>::new();
        let mut taken = 0;
        for line in scalar_lines {
            let fast = numeric_ascii_element::<DefaultElement>(line, &scalars);
            match parser.read_ascii_element(line, &scalars) {
                Ok(want) => {
                    if let Some(got) = fast {
                        assert_eq!(got, want, "{line:?}");
                        taken += 1;
                    }
                }
                Err(_) => assert!(fast.is_none(), "{line:?}: the crate rejects it"),
            }
        }
        assert!(taken >= 6, "the fast path took only {taken} lines");
        let face_lines = [
            "3 0 1 2\n",
            "4 10 -11 12 13 \r\n",
            "3 0 1 2 9 9\n",
            "3 0 1\n",
            "3 0 1.5 2\n",
            "0\n",
            "300 1 2 3\n",
            "3 0 1 99999999999\n",
        ];
        let parser = Parser::<FaceRecord>::new();
        let mut scratch = (Vec::new(), Vec::new());
        for line in face_lines {
            let fast = numeric_ascii_element::<FaceRecord>(line, &faces);
            match parser.read_ascii_element(line, &faces) {
                Ok(want) => {
                    let got = fast.unwrap_or_else(|| panic!("{line:?}: the fast path stepped aside"));
                    assert_eq!(got.indices(&mut scratch.0), want.indices(&mut scratch.1), "{line:?}");
                }
                Err(_) => assert!(fast.is_none(), "{line:?}: the crate rejects it"),
            }
        }
    }

    /// A random ASCII token for a value of type `t`: integers and floats in
    /// the grammar's forms (leading `+`, exponents, `E`), sometimes out of
    /// the type's range or not a PLY number at all.
    fn ascii_token(rng: &mut impl rand::Rng, t: &ScalarType) -> String {
        let sign = ["", "-", "+"][rng.random_range(0..3)];
        match rng.random_range(0..20) {
            0 => ["1.", ".5", "nan", "inf", "1e", "0x1", "1,5", "--1"][rng.random_range(0..8)].to_string(),
            1 => format!("{sign}{}", rng.random_range(0u64..100_000)),
            _ => match t {
                ScalarType::Float | ScalarType::Double => match rng.random_range(0..4) {
                    0 => format!("{sign}{}", rng.random::<f32>() * 10.0),
                    1 => format!("{sign}{}e{}", rng.random_range(1..10), rng.random_range(-40..40)),
                    2 => format!(
                        "{sign}{}.{}E+{}",
                        rng.random_range(0..100),
                        rng.random_range(0..1000),
                        rng.random_range(0..3)
                    ),
                    _ => format!("{sign}{}", rng.random_range(0..300)),
                },
                _ => format!("{sign}{}", rng.random_range(0..300)),
            },
        }
    }

    /// Joins tokens with random runs of spaces and tabs, and a random line ending.
    fn ascii_line(rng: &mut impl rand::Rng, tokens: &[String]) -> String {
        let gap = |rng: &mut dyn rand::RngCore| [" ", "  ", "\t", " \t "][(rng.next_u32() % 4) as usize];
        let mut line = String::new();
        if rng.random_range(0..4) == 0 {
            line.push_str(gap(rng));
        }
        for (k, t) in tokens.iter().enumerate() {
            if k > 0 {
                line.push_str(gap(rng));
            }
            line.push_str(t);
        }
        if rng.random_range(0..4) == 0 {
            line.push_str(gap(rng));
        }
        line.push_str(["\n", "\r\n", "\r", ""][rng.random_range(0..4)]);
        line
    }

    #[test]
    fn ascii_decoders_agree_with_the_crate() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let header = |props: &str| {
            let text = format!("ply\nformat ascii 1.0\nelement vertex 1\n{props}end_header\n");
            let mut r = Reader::new(std::io::BufReader::new(text.as_bytes()));
            Parser::<Skipped>::new().read_header(&mut r).unwrap()
        };
        let vertex_props = [
            "property float x\nproperty float y\nproperty float z\n",
            "property double x\nproperty float y\nproperty int z\nproperty uchar red\n\
             property ushort green\nproperty float blue\nproperty short extra\nproperty char x2\n\
             property uint u\nproperty double diffuse_red\n",
            "property uchar x\nproperty ushort y\nproperty char z\nproperty short r\nproperty int g\n",
            "property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n\
             property float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n",
        ];
        let parser = Parser::<VertexRecord>::new();
        let (mut taken, mut rejected) = (0, 0);
        for props in vertex_props {
            let h = header(props);
            let def = &h.elements["vertex"];
            let fast = AsciiVertices::of(def, h.encoding).unwrap();
            let types: Vec<ScalarType> = def
                .properties
                .values()
                .map(|p| match &p.data_type {
                    PropertyType::Scalar(t) => t.clone(),
                    PropertyType::List(..) => unreachable!(),
                })
                .collect();
            for _ in 0..4000 {
                let mut n = types.len();
                match rng.random_range(0..10) {
                    0 => n -= 1,
                    1 => n += rng.random_range(1..3),
                    _ => {}
                }
                let tokens: Vec<String> =
                    (0..n).map(|k| ascii_token(&mut rng, &types[k.min(types.len() - 1)])).collect();
                let line = ascii_line(&mut rng, &tokens);
                let got = fast.decode(&line);
                match parser.read_ascii_element(&line, def) {
                    Ok(want) => {
                        if let Some(got) = got {
                            assert_eq!(got.p.map(f64::to_bits), want.p.map(f64::to_bits), "{line:?}");
                            assert_eq!(got.c.map(f32::to_bits), want.c.map(f32::to_bits), "{line:?}");
                            taken += 1;
                        }
                    }
                    Err(_) => {
                        assert!(got.is_none(), "{line:?}: the crate rejects it");
                        rejected += 1;
                    }
                }
            }
        }
        assert!(taken > 3000 && rejected > 1000, "taken {taken}, rejected {rejected}");

        let parser = Parser::<FaceRecord>::new();
        let (mut triangles, mut polygons) = (0, 0);
        for list in ["uchar int", "uchar uint", "int int", "uint uint"] {
            let h = header(&format!("property list {list} vertex_indices\n"));
            let def = &h.elements["vertex"];
            let fast = AsciiTriangles::of(def, h.encoding).unwrap();
            let item = if list.ends_with("uint") { ScalarType::UInt } else { ScalarType::Int };
            for _ in 0..4000 {
                let count: usize = [3, 3, 3, 3, 4, 5, 0, 1, 2][rng.random_range(0..9)];
                let mut tokens = vec![match rng.random_range(0..12) {
                    0 => format!("+{count}"),
                    1 => "3.0".to_string(),
                    _ => count.to_string(),
                }];
                let items = match rng.random_range(0..10) {
                    0 => count.saturating_sub(1),
                    1 => count + 2,
                    _ => count,
                };
                tokens.extend((0..items).map(|_| ascii_token(&mut rng, &item)));
                let line = ascii_line(&mut rng, &tokens);
                let got = fast.decode(&line);
                match parser.read_ascii_element(&line, def) {
                    Ok(want) => {
                        let mut scratch = Vec::new();
                        let want = want.indices(&mut scratch);
                        match got {
                            Some(t) => {
                                assert_eq!(&t[..], want, "{line:?}");
                                triangles += 1;
                            }
                            // Only polygons (and degenerate lists) step aside.
                            None => {
                                assert_ne!(want.len(), 3, "{line:?}: a triangle stepped aside");
                                polygons += 1;
                            }
                        }
                    }
                    Err(_) => assert!(got.is_none(), "{line:?}: the crate rejects it"),
                }
            }
        }
        assert!(triangles > 2000 && polygons > 1000, "triangles {triangles}, polygons {polygons}");
        // Not the common layout: the general path reads them.
        let h = header("property list uchar short vertex_indices\n");
        assert!(AsciiTriangles::of(&h.elements["vertex"], h.encoding).is_none());
        let h = header("property list uchar int vertex_indices\nproperty uchar flags\n");
        assert!(AsciiTriangles::of(&h.elements["vertex"], h.encoding).is_none());
        let h = header("property list uchar float x\n");
        assert!(AsciiVertices::of(&h.elements["vertex"], h.encoding).is_none());
        let h = header("property float x\n");
        let text = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n";
        let mut r = Reader::new(std::io::BufReader::new(text.as_bytes()));
        let b = Parser::<Skipped>::new().read_header(&mut r).unwrap();
        assert!(AsciiVertices::of(&h.elements["vertex"], b.encoding).is_none());
    }

    #[test]
    fn digit_triangles_agree_with_the_token_path() {
        let lines = [
            "3 1 2 3\n",
            "3 1 2 3\r\n",
            "3\t10 20\t30  \n",
            "  3 0 0 0",
            "03 1 2 3\n",
            "3 0001 2 3\n",
            "3 4294967295 0 1\n",
            "3 4294967296 0 1\n",
            "3 2147483647 0 1\n",
            "3 2147483648 0 1\n",
            "3 9999999999 0 1\n",
            "3 99999999999 0 1\n",
            "3 1 2 3 4 5\n",
            "3 1 2\n",
            "4 1 2 3 4\n",
            "3 1 2 3\r\r\n",
            "3 1 2 3x\n",
            "3 -1 2 3\n",
            "\n",
        ];
        for signed in [true, false] {
            let t = AsciiTriangles { signed };
            for line in lines {
                if let Some(got) = t.decode_digits(line) {
                    assert_eq!(Some(got), t.decode_tokens(line), "{line:?} signed {signed}");
                }
                assert_eq!(t.decode(line), t.decode_tokens(line), "{line:?} signed {signed}");
            }
            assert_eq!(t.decode_digits("3\t10 20\t30  \n"), Some([10, 20, 30]));
        }
    }

    /// A random ASCII PLY (spanning several batches, polygons among the
    /// triangles, colours, CRLF and LF, extra spaces, blank trailing lines)
    /// read by the reader and by the crate's serial whole-file parse give the
    /// same triangles, bit for bit.
    #[test]
    fn ascii_file_matches_the_crate_serial_parse() {
        use ply_rs_bw::ply::{DefaultElement, Property};
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(10);
        let (nv, nf) = (BATCH + 1234, 2 * BATCH + 77);
        for (item, eol) in [("int", "\n"), ("uint", "\r\n")] {
            let mut text = format!(
                "ply{eol}format ascii 1.0{eol}element vertex {nv}{eol}property float x{eol}property double y{eol}\
                 property float z{eol}property uchar red{eol}property uchar green{eol}property uchar blue{eol}\
                 element face {nf}{eol}property list uchar {item} vertex_indices{eol}end_header{eol}"
            );
            for _ in 0..nv {
                let x: f32 = rng.random_range(-1.0..1.0);
                let y = format!("{:e}", rng.random_range(-1.0e3..1.0e3f64));
                let z = format!("+{}", rng.random::<f32>());
                let sep = if rng.random_range(0..8) == 0 { " \t " } else { " " };
                let (r, g, b) = (rng.random::<u8>(), rng.random::<u8>(), rng.random::<u8>());
                text.push_str(&format!("{x}{sep}{y} {z} {r} {g} {b} {eol}"));
            }
            for _ in 0..nf {
                let n = if rng.random_range(0..10) == 0 { rng.random_range(4..7) } else { 3 };
                text.push_str(&n.to_string());
                for _ in 0..n {
                    text.push_str(&format!(" {}", rng.random_range(0..nv)));
                }
                text.push_str(eol);
            }
            text.push_str(eol);
            text.push_str(eol);
            let got = read(text.as_bytes()).unwrap();

            let mut r = std::io::BufReader::new(text.as_bytes());
            let ply = Parser::<DefaultElement>::new().read_ply(&mut r).unwrap();
            let num = |p: &Property| match p {
                Property::Float(v) => *v as f64,
                Property::Double(v) => *v,
                Property::UChar(v) => *v as f64,
                _ => unreachable!(),
            };
            let vertices: Vec<[f64; 3]> =
                ply.payload["vertex"].iter().map(|v| ["x", "y", "z"].map(|a| num(&v[a]))).collect();
            let mut want = Vec::new();
            for f in &ply.payload["face"] {
                let idx: Vec<usize> = match &f["vertex_indices"] {
                    Property::ListInt(v) => v.iter().map(|&i| i as usize).collect(),
                    Property::ListUInt(v) => v.iter().map(|&i| i as usize).collect(),
                    _ => unreachable!(),
                };
                for k in 1..idx.len() - 1 {
                    want.push([idx[0], idx[k], idx[k + 1]].map(|i| vertices[i]));
                }
            }
            assert_eq!(got.triangles.len(), want.len(), "{item}");
            for (t, w) in want.iter().enumerate() {
                assert_eq!(
                    got.triangle(t).map(|p| p.map(f64::to_bits)),
                    w.map(|p| p.map(f64::to_bits)),
                    "{item} {t}"
                );
            }
            assert!(got.triangle_color(0).is_some());
        }
    }

    /// A malformed line is an error naming its element and line, from any
    /// batch, never a panic; so are a file that ends early and bytes that
    /// are not UTF-8.
    #[test]
    fn ascii_errors_name_the_line() {
        let (nv, nf) = (BATCH + 10, 3);
        let mut text = format!(
            "ply\nformat ascii 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n\
             element face {nf}\nproperty list uchar int vertex_indices\nend_header\n"
        );
        for i in 0..nv {
            text.push_str(&format!("{i} 0 1\n"));
        }
        text.push_str("3 0 1 2\n3 1 2 3\n4 0 1 2 3\n");
        assert_eq!(read(text.as_bytes()).unwrap().triangles.len(), 4);
        let message = |bytes: &[u8]| match read(bytes) {
            Err(IngestError::Parse { message, .. }) => message,
            other => panic!("{:?}", other.map(|m| m.triangles.len())),
        };
        let at = BATCH + 5;
        let bad = text.replace(&format!("\n{at} 0 1\n"), &format!("\n{at} 0 x1\n"));
        let m = message(bad.as_bytes());
        assert!(m.starts_with(&format!("vertex {at}: ")), "{m}");
        let bad = text.replace("3 1 2 3\n", "3 1 2 3e\n");
        let m = message(bad.as_bytes());
        assert!(m.starts_with("face 1: "), "{m}");
        let bad = text.replace("3 1 2 3\n", "3 1 2\n");
        assert!(message(bad.as_bytes()).starts_with("face 1: "));
        let m = message(text.replace("4 0 1 2 3\n", "").as_bytes());
        assert!(m.starts_with("face 2: the file ends early"), "{m}");
        let mut bytes = text.clone().into_bytes();
        let p = text.find("\n7 0 1\n").unwrap() + 1;
        bytes[p] = 0xff;
        let m = message(&bytes);
        assert!(m.starts_with("vertex 7: ") && m.contains("UTF-8"), "{m}");
        let long = text.replace("\n9 0 1\n", &format!("\n9 0 1{}\n", " ".repeat(MAX_LINE as usize)));
        let m = message(long.as_bytes());
        assert!(m.starts_with("vertex 9: line longer than 1 MiB"), "{m}");
    }

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
    fn a_paged_table_gives_the_held_triangles_with_faces_before_or_after() {
        let before = b"ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int vertex_indices\n\
element vertex 4\nproperty double x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n\
property uchar blue\nend_header\n4 0 1 2 3\n3 3 2 1\n0 0 0 1 2 3\n1e9 0 0 4 5 6\n1 1 0 7 8 9\n0 1 0 1 1 1\n";
        for bytes in [ASCII, &before[..]] {
            let read = |vertex_memory| {
                let mut sink = super::super::MeshBuilder::default();
                let opts = ReadOptions { vertex_memory, ..Default::default() };
                super::super::stream_mesh_bytes(bytes, MeshFormat::Ply, &mut sink, &opts).map(|()| sink.mesh)
            };
            let held = read(None).unwrap();
            assert!(!held.triangles.is_empty());
            assert_eq!(read(Some(1)).unwrap(), held);
        }
        // An index past the vertices is still the error naming it.
        let bad = String::from_utf8(before.to_vec()).unwrap().replace("3 3 2 1", "3 3 2 4");
        let mut sink = super::super::MeshBuilder::default();
        let opts = ReadOptions { vertex_memory: Some(1), ..Default::default() };
        let e =
            super::super::stream_mesh_bytes(bad.as_bytes(), MeshFormat::Ply, &mut sink, &opts).unwrap_err();
        assert!(e.to_string().contains("face 1 uses vertex 4"), "{e}");
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
