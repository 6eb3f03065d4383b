//! STL, ASCII and binary, streamed through stl_io's triangle reader.
//!
//! stl_io picks ASCII whenever the first line starts with `solid `, which many
//! binary exporters write into their 80-byte header, and it does not see a
//! bare `solid` line at all. So the choice is made here, by the binary size
//! rule first, and stl_io is handed a stream whose first line says which
//! parser to use.

use std::io::{self, Read, Seek, SeekFrom};

use super::{IngestError, MeshFormat, TriangleMesh};

const HEADER_LEN: usize = 80;
/// Header plus the little-endian u32 triangle count.
const BINARY_PREFIX: usize = HEADER_LEN + 4;
/// Normal, three vertices (12 × f32) and the u16 attribute count.
const RECORD_LEN: u64 = 50;
/// How far an ASCII file is scanned for NUL bytes, which no ASCII STL holds.
const TEXT_PROBE_LEN: usize = 1024;

fn parse_err(message: impl Into<String>) -> IngestError {
    IngestError::Parse { format: MeshFormat::Stl, message: message.into() }
}

pub(super) fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
    if let Some(count) = binary_count(bytes).filter(|&n| binary_len(n) == bytes.len() as u64) {
        return read_binary(bytes, count);
    }
    if looks_ascii(bytes) {
        return read_ascii(bytes).map_err(|e| match binary_count(bytes) {
            // A binary file whose header starts with "solid" but whose count is wrong
            // lands here too: say both, so neither reading hides the other.
            Some(n) => parse_err(format!("{e}; {}", size_mismatch(n, bytes.len()))),
            None => e,
        });
    }
    match binary_count(bytes) {
        Some(n) => Err(parse_err(size_mismatch(n, bytes.len()))),
        None => Err(parse_err(format!(
            "the file has {} bytes: too short for a binary STL ({BINARY_PREFIX}-byte header) \
             and not an ASCII STL (which starts with \"solid\")",
            bytes.len()
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

fn size_mismatch(count: u32, len: usize) -> String {
    format!(
        "the binary STL header declares {count} triangles, which take {} bytes, but the file has {len} bytes",
        binary_len(count)
    )
}

fn looks_ascii(bytes: &[u8]) -> bool {
    let probe = &bytes[..bytes.len().min(TEXT_PROBE_LEN)];
    bytes.trim_ascii_start().starts_with(b"solid") && !probe.contains(&0)
}

fn read_binary(bytes: &[u8], count: u32) -> Result<TriangleMesh, IngestError> {
    check_vertex_count(u64::from(count) * 3)?;
    // A header whose first line is empty can never pass stl_io's ASCII probe.
    let mut head = [0u8; BINARY_PREFIX];
    head[0] = b'\n';
    head[HEADER_LEN..].copy_from_slice(&count.to_le_bytes());
    let mut stream = Spliced::new(&head, &bytes[BINARY_PREFIX..]);
    let triangles = stl_io::create_stl_reader(&mut stream).map_err(|e| parse_err(e.to_string()))?;

    let mut mesh = TriangleMesh::default();
    // The count was checked against the file size above, so reserving by it is
    // bounded by the bytes already in memory.
    mesh.positions.reserve(count as usize * 3);
    mesh.triangles.reserve(count as usize);
    for (i, t) in triangles.enumerate() {
        let t = t.map_err(|e| parse_err(format!("triangle {i}: {e}")))?;
        push_triangle(&mut mesh, t)?;
    }
    if mesh.triangles.len() != count as usize {
        return Err(parse_err(format!("read {} of {count} triangles", mesh.triangles.len())));
    }
    Ok(mesh)
}

/// Reads every `solid … endsolid` block: stl_io stops at the first `endsolid`,
/// and some exporters write one solid per part.
fn read_ascii(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
    let mut mesh = TriangleMesh::default();
    for (s, solid) in ascii_solids(bytes).into_iter().enumerate() {
        let (first, body) = split_first_line(solid);
        let name = String::from_utf8_lossy(first.trim_ascii()["solid".len()..].trim_ascii()).into_owned();
        let at = |msg: String| parse_err(format!("solid {s} ({name:?}): {msg}"));
        check_after_endsolid(body).map_err(at)?;
        // stl_io wants "solid " with a space; a bare "solid" line is just as valid.
        let mut stream = Spliced::new(b"solid \n", body);
        let triangles = stl_io::create_stl_reader(&mut stream).map_err(|e| at(e.to_string()))?;
        for (i, t) in triangles.enumerate() {
            let t = t.map_err(|e| at(format!("facet {i}: {e}")))?;
            push_triangle(&mut mesh, t)?;
        }
    }
    Ok(mesh)
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

fn check_vertex_count(vertices: u64) -> Result<(), IngestError> {
    if vertices > u64::from(u32::MAX) + 1 {
        return Err(IngestError::Invalid(format!(
            "{vertices} vertices do not fit 32-bit indices ({} at most)",
            u64::from(u32::MAX) + 1
        )));
    }
    Ok(())
}

/// Appends one unwelded triangle; positions pass through as they are, NaN included.
fn push_triangle(mesh: &mut TriangleMesh, t: stl_io::Triangle) -> Result<(), IngestError> {
    let base = mesh.positions.len();
    check_vertex_count(base as u64 + 3)?;
    mesh.positions.extend(t.vertices.map(|v| v.0.map(f64::from)));
    let base = base as u32;
    mesh.triangles.push([base, base + 1, base + 2]);
    Ok(())
}

/// `head` followed by `tail` as one seekable stream, without copying `tail`.
struct Spliced<'a> {
    head: &'a [u8],
    tail: &'a [u8],
    pos: u64,
}

impl<'a> Spliced<'a> {
    fn new(head: &'a [u8], tail: &'a [u8]) -> Self {
        Self { head, tail, pos: 0 }
    }

    fn len(&self) -> u64 {
        (self.head.len() + self.tail.len()) as u64
    }
}

impl Read for Spliced<'_> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let pos = self.pos.min(self.len()) as usize;
        let rest = match pos.checked_sub(self.head.len()) {
            None => &self.head[pos..],
            Some(t) => &self.tail[t..],
        };
        let n = rest.len().min(buf.len());
        buf[..n].copy_from_slice(&rest[..n]);
        self.pos += n as u64;
        Ok(n)
    }
}

impl Seek for Spliced<'_> {
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
    use super::*;

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
        let mut s = Spliced::new(b"ab", b"cde");
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
