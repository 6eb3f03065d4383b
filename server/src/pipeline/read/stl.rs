//! STL, ASCII and binary, streamed through stl_io's triangle reader.
//!
//! stl_io picks ASCII whenever the first line starts with `solid `, which many
//! binary exporters write into their 80-byte header, and it does not see a
//! bare `solid` line at all. So the choice is made here, by the binary size
//! rule first, and stl_io is handed a stream whose first line says which
//! parser to use.

use std::io::{self, Read, Seek, SeekFrom};

use super::{IngestError, MeshFormat, ReadOptions, TICK_EVERY, TriangleSink};
use crate::pipeline::stream::RecordLayout;

const HEADER_LEN: usize = 80;
/// Header plus the little-endian u32 triangle count.
const BINARY_PREFIX: usize = HEADER_LEN + 4;
/// Normal, three vertices (12 × f32) and the u16 attribute count.
const RECORD_LEN: u64 = 50;
/// How far an ASCII file is scanned for NUL bytes, which no ASCII STL holds.
const TEXT_PROBE_LEN: usize = 1024;
/// STL coordinates are f32: streams keep them exactly at half the bytes.
const LAYOUT: RecordLayout = RecordLayout { f64_positions: false, color: false };

fn parse_err(message: impl Into<String>) -> IngestError {
    IngestError::Parse { format: MeshFormat::Stl, message: message.into() }
}

fn io_err(e: io::Error) -> IngestError {
    parse_err(format!("read failed: {e}"))
}

/// Streams an STL's triangles into `sink`: binary record by record, ASCII
/// from memory (so an ASCII file must fit the memory budget). `len` is the
/// whole input's size.
pub(super) fn stream<R: Read + Seek>(
    mut input: R,
    len: u64,
    sink: &mut dyn TriangleSink,
    opts: &ReadOptions,
) -> Result<(), IngestError> {
    let mut head = Vec::with_capacity(TEXT_PROBE_LEN);
    input.by_ref().take(TEXT_PROBE_LEN as u64).read_to_end(&mut head).map_err(io_err)?;
    if let Some(count) = binary_count(&head).filter(|&n| binary_len(n) == len) {
        input.seek(SeekFrom::Start(BINARY_PREFIX as u64)).map_err(io_err)?;
        return read_binary(input, count, sink);
    }
    if looks_ascii(&head) {
        if len.saturating_mul(2) > opts.memory_budget {
            return Err(IngestError::TooLarge(format!(
                "ASCII STL is parsed in memory and this file has {len} bytes, more than half the memory budget \
                 of {} bytes: raise --memory-budget or convert it to binary STL",
                opts.memory_budget
            )));
        }
        let mut bytes = head;
        input.read_to_end(&mut bytes).map_err(io_err)?;
        sink.begin(LAYOUT)?;
        return read_ascii(&bytes, sink).map_err(|e| match (e, binary_count(&bytes)) {
            // A binary file whose header starts with "solid" but whose count is wrong
            // lands here too: say both, so neither reading hides the other.
            (IngestError::Parse { message, .. }, Some(n)) => {
                parse_err(format!("{message}; {}", size_mismatch(n, len)))
            }
            (e, _) => e,
        });
    }
    match binary_count(&head) {
        Some(n) => Err(parse_err(size_mismatch(n, len))),
        None => Err(parse_err(format!(
            "the file has {len} bytes: too short for a binary STL ({BINARY_PREFIX}-byte header) \
             and not an ASCII STL (which starts with \"solid\")"
        ))),
    }
}

/// The triangle count a binary header declares, if there is a header.
fn binary_count(bytes: &[u8]) -> Option<u32> {
    let count: [u8; 4] = bytes.get(HEADER_LEN..BINARY_PREFIX)?.try_into().ok()?;
    Some(u32::from_le_bytes(count))
}

/// The exact size of a binary STL with `count` triangles (u64: no overflow for any count).
fn binary_len(count: u32) -> u64 {
    BINARY_PREFIX as u64 + RECORD_LEN * u64::from(count)
}

fn size_mismatch(count: u32, len: u64) -> String {
    format!(
        "the binary STL header declares {count} triangles, which take {} bytes, but the file has {len} bytes",
        binary_len(count)
    )
}

fn looks_ascii(bytes: &[u8]) -> bool {
    let probe = &bytes[..bytes.len().min(TEXT_PROBE_LEN)];
    bytes.trim_ascii_start().starts_with(b"solid") && !probe.contains(&0)
}

/// `input` is positioned at the first record; the count was checked against the file size.
fn read_binary<R: Read + Seek>(input: R, count: u32, sink: &mut dyn TriangleSink) -> Result<(), IngestError> {
    // A header whose first line is empty can never pass stl_io's ASCII probe.
    let mut head = [0u8; BINARY_PREFIX];
    head[0] = b'\n';
    head[HEADER_LEN..].copy_from_slice(&count.to_le_bytes());
    let mut stream = Spliced::new(&head, input, BINARY_PREFIX as u64, RECORD_LEN * u64::from(count));
    let triangles = stl_io::create_stl_reader(&mut stream).map_err(|e| parse_err(e.to_string()))?;
    sink.begin(LAYOUT)?;
    let mut read = 0usize;
    for (i, t) in triangles.enumerate() {
        let t = t.map_err(|e| parse_err(format!("triangle {i}: {e}")))?;
        push_triangle(sink, t)?;
        read += 1;
        if i % TICK_EVERY == TICK_EVERY - 1 {
            sink.tick()?;
        }
    }
    if read != count as usize {
        return Err(parse_err(format!("read {read} of {count} triangles")));
    }
    Ok(())
}

/// Reads every `solid … endsolid` block: stl_io stops at the first `endsolid`,
/// and some exporters write one solid per part.
fn read_ascii(bytes: &[u8], sink: &mut dyn TriangleSink) -> Result<(), IngestError> {
    for (s, solid) in ascii_solids(bytes).into_iter().enumerate() {
        let (first, body) = split_first_line(solid);
        let name = String::from_utf8_lossy(first.trim_ascii()["solid".len()..].trim_ascii()).into_owned();
        let at = |msg: String| parse_err(format!("solid {s} ({name:?}): {msg}"));
        check_after_endsolid(body).map_err(at)?;
        // stl_io wants "solid " with a space; a bare "solid" line is just as valid.
        let body_len = body.len() as u64;
        let mut stream = Spliced::new(b"solid \n", io::Cursor::new(body), 0, body_len);
        let triangles = stl_io::create_stl_reader(&mut stream).map_err(|e| at(e.to_string()))?;
        for (i, t) in triangles.enumerate() {
            let t = t.map_err(|e| at(format!("facet {i}: {e}")))?;
            push_triangle(sink, t)?;
            if i % TICK_EVERY == TICK_EVERY - 1 {
                sink.tick()?;
            }
        }
    }
    Ok(())
}

/// Splits the text at each line that starts with `solid`; text before the first one is an error.
fn ascii_solids(bytes: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut offset = 0;
    for line in bytes.split_inclusive(|&b| b == b'\n') {
        if line.trim_ascii_start().starts_with(b"solid") {
            starts.push(offset);
        }
        offset += line.len();
    }
    // looks_ascii guarantees the file starts with a solid line (after whitespace).
    starts
        .iter()
        .enumerate()
        .map(|(k, &a)| &bytes[a..starts.get(k + 1).copied().unwrap_or(bytes.len())])
        .collect()
}

fn split_first_line(text: &[u8]) -> (&[u8], &[u8]) {
    match text.iter().position(|&b| b == b'\n') {
        Some(i) => (&text[..i], &text[i + 1..]),
        None => (text, &[]),
    }
}

/// stl_io stops reading at `endsolid`; anything after it in the same solid would be dropped silently.
fn check_after_endsolid(body: &[u8]) -> Result<(), String> {
    let mut lines = body.split(|&b| b == b'\n');
    if lines.by_ref().any(|l| l.trim_ascii_start().starts_with(b"endsolid")) {
        if let Some(extra) = lines.find(|l| !l.trim_ascii().is_empty()) {
            return Err(format!("text after endsolid: {:?}", String::from_utf8_lossy(extra.trim_ascii())));
        }
    }
    Ok(())
}

/// Passes one triangle on; positions pass through as they are, NaN included.
fn push_triangle(sink: &mut dyn TriangleSink, t: stl_io::Triangle) -> Result<(), IngestError> {
    sink.triangle(t.vertices.map(|v| v.0.map(f64::from)), [0.0; 3])
}

/// `head` followed by `tail_len` bytes of `tail` from `tail_start`, as one
/// seekable stream, without copying the tail.
struct Spliced<'a, R> {
    head: &'a [u8],
    tail: R,
    tail_start: u64,
    tail_len: u64,
    /// Where `tail` is positioned, relative to `tail_start`, when known.
    tail_pos: Option<u64>,
    pos: u64,
}

impl<'a, R: Read + Seek> Spliced<'a, R> {
    fn new(head: &'a [u8], tail: R, tail_start: u64, tail_len: u64) -> Self {
        Self { head, tail, tail_start, tail_len, tail_pos: None, pos: 0 }
    }

    fn len(&self) -> u64 {
        self.head.len() as u64 + self.tail_len
    }
}

impl<R: Read + Seek> Read for Spliced<'_, R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let pos = self.pos.min(self.len());
        let n = match pos.checked_sub(self.head.len() as u64) {
            None => {
                let rest = &self.head[pos as usize..];
                let n = rest.len().min(buf.len());
                buf[..n].copy_from_slice(&rest[..n]);
                n
            }
            Some(t) => {
                if self.tail_pos != Some(t) {
                    self.tail.seek(SeekFrom::Start(self.tail_start + t))?;
                }
                let want = ((self.tail_len - t) as usize).min(buf.len());
                let n = self.tail.read(&mut buf[..want])?;
                self.tail_pos = Some(t + n as u64);
                n
            }
        };
        self.pos += n as u64;
        Ok(n)
    }
}

impl<R: Read + Seek> Seek for Spliced<'_, R> {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        let pos = match to {
            SeekFrom::Start(p) => Some(p),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
            SeekFrom::End(d) => self.len().checked_add_signed(d),
        };
        self.pos = pos.ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "seek before the start"))?;
        Ok(self.pos)
    }
}

#[cfg(test)]
mod tests {
    use super::super::{TriangleMesh, read_mesh_bytes};
    use super::*;

    fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
        read_mesh_bytes(bytes, MeshFormat::Stl)
    }

    fn binary_stl(header: &[u8], triangles: &[[[f32; 3]; 3]]) -> Vec<u8> {
        let mut b = vec![0u8; HEADER_LEN];
        b[..header.len()].copy_from_slice(header);
        b.extend_from_slice(&(triangles.len() as u32).to_le_bytes());
        for t in triangles {
            b.extend_from_slice(&[0u8; 12]); // normal: unused
            for c in t.as_flattened() {
                b.extend_from_slice(&c.to_le_bytes());
            }
            b.extend_from_slice(&[0u8; 2]);
        }
        b
    }

    const TRIS: [[[f32; 3]; 3]; 2] = [
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 2.5]],
    ];

    const ASCII: &str = "solid cube\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n\
   vertex 0 1 0\n  endloop\n endfacet\n facet normal 0 0 1\n  outer loop\n   vertex 1 0 0\n   vertex 1 1 0\n\
   vertex 0 1 2.5\n  endloop\n endfacet\nendsolid cube\n";

    fn expected() -> Vec<[f64; 3]> {
        TRIS.as_flattened().iter().map(|v| v.map(f64::from)).collect()
    }

    #[test]
    fn ascii_is_read_unwelded() {
        let m = read(ASCII.as_bytes()).unwrap();
        assert_eq!(m.positions, expected());
        assert_eq!(m.triangles, vec![[0, 1, 2], [3, 4, 5]]);
    }

    #[test]
    fn ascii_bare_solid_line_crlf_and_several_solids() {
        let two = ASCII.replace("solid cube\n", "solid\n").replace('\n', "\r\n") + ASCII;
        let m = read(two.as_bytes()).unwrap();
        assert_eq!(m.triangles.len(), 4);
        assert_eq!(m.positions[6..], expected()[..]);
    }

    #[test]
    fn ascii_text_after_endsolid_is_an_error() {
        let extra = format!("{ASCII}facet normal 0 0 1\n");
        let e = read(extra.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("after endsolid"), "{e}");
    }

    #[test]
    fn binary_is_read() {
        let m = read(&binary_stl(b"exported by test", &TRIS)).unwrap();
        assert_eq!(m.positions, expected());
        assert_eq!(m.triangles, vec![[0, 1, 2], [3, 4, 5]]);
    }

    #[test]
    fn binary_with_solid_header_is_binary() {
        for header in [&b"solid "[..], b"solid part_1 exported by CAD\n", b"solid"] {
            let m = read(&binary_stl(header, &TRIS)).unwrap();
            assert_eq!(m.positions, expected(), "{header:?}");
        }
    }

    #[test]
    fn count_larger_than_file_names_both_numbers() {
        let mut b = binary_stl(b"", &TRIS);
        b[HEADER_LEN..BINARY_PREFIX].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = read(&b).unwrap_err().to_string();
        assert!(e.contains(&u32::MAX.to_string()) && e.contains(&b.len().to_string()), "{e}");
        // Same with a "solid" header: still an error naming the size, not an ASCII puzzle.
        b[..6].copy_from_slice(b"solid ");
        let e = read(&b).unwrap_err().to_string();
        assert!(e.contains(&u32::MAX.to_string()), "{e}");
    }

    #[test]
    fn truncated_binary_is_an_error() {
        let b = binary_stl(b"", &TRIS);
        for len in [BINARY_PREFIX + 10, b.len() - 1] {
            let e = read(&b[..len]).unwrap_err().to_string();
            assert!(e.contains("declares 2 triangles"), "{len}: {e}");
        }
    }

    #[test]
    fn empty_and_garbage_are_errors() {
        for bytes in [&b""[..], b"garbage", &[0xffu8; 83], b"solid x\n facet normal 0 0 1\n bogus\n"] {
            let e = read(bytes).unwrap_err();
            assert!(matches!(e, IngestError::Parse { format: MeshFormat::Stl, .. }), "{e}");
        }
    }

    #[test]
    fn nan_passes_through_binary_and_is_an_error_in_ascii() {
        let nan = [[f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let m = read(&binary_stl(b"", &[nan])).unwrap();
        assert!(m.positions[0][0].is_nan());
        assert_eq!(m.positions[1], [1.0, 0.0, 0.0]);
        // stl_io rejects non-finite ASCII numbers itself: an error, not a panic.
        let e = read(ASCII.replacen("vertex 0 0 0", "vertex nan 0 0", 1).as_bytes()).unwrap_err();
        assert!(e.to_string().contains("NaN"), "{e}");
    }

    #[test]
    fn spliced_stream_reads_and_seeks() {
        let mut s = Spliced::new(b"ab", io::Cursor::new(b"xxcdeyy"), 2, 3);
        let mut all = String::new();
        s.read_to_string(&mut all).unwrap();
        assert_eq!(all, "abcde");
        assert_eq!(s.seek(SeekFrom::End(-2)).unwrap(), 3);
        assert!(s.seek(SeekFrom::Current(-4)).is_err());
        s.seek(SeekFrom::Start(1)).unwrap();
        let mut two = [0u8; 2];
        s.read_exact(&mut two).unwrap();
        assert_eq!(&two, b"bc");
    }
}
