use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{PropertyAccess, PropertyAccessResult};

use super::{IngestError, MeshFormat, TriangleMesh};

#[derive(Default)]
struct Vertex([f64; 3]);

impl Vertex {
    fn set(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        let i = match name {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            _ => return PropertyAccessResult::Ignored,
        };
        self.0[i] = v;
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for Vertex {
    fn new() -> Self {
        Self::default()
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_int(&mut self, name: &str, v: i32) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_short(&mut self, name: &str, v: i16) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        self.set(name, v as f64)
    }
}

/// A face's vertex list; negative indices become `u32::MAX` so the range check rejects them.
#[derive(Default)]
struct Face(Vec<u32>);

impl Face {
    fn set<T: TryInto<u32> + Copy>(&mut self, name: &str, v: &[T]) -> PropertyAccessResult {
        if name != "vertex_indices" && name != "vertex_index" {
            return PropertyAccessResult::Ignored;
        }
        self.0 = v.iter().map(|&i| i.try_into().unwrap_or(u32::MAX)).collect();
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for Face {
    fn new() -> Self {
        Self::default()
    }
    fn set_list_int(&mut self, name: &str, v: Vec<i32>) -> PropertyAccessResult {
        self.set(name, &v)
    }
    fn set_list_uint(&mut self, name: &str, v: Vec<u32>) -> PropertyAccessResult {
        self.set(name, &v)
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

pub(super) fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
    let mut reader = Reader::new(std::io::Cursor::new(bytes));
    let header = Parser::<Skipped>::new().read_header(&mut reader).map_err(parse_err)?;
    if !header.elements.contains_key("vertex") {
        return Err(IngestError::Invalid("the PLY header declares no vertex element".into()));
    }
    let mut mesh = TriangleMesh::default();
    let mut faces = Vec::new();
    // Elements must be read in header order.
    for (name, def) in &header.elements {
        match name.as_str() {
            "vertex" => {
                let v = Parser::<Vertex>::new().read_payload_for_element(&mut reader, def, &header);
                mesh.positions = v.map_err(parse_err)?.into_iter().map(|v| v.0).collect();
            }
            "face" => {
                faces = Parser::<Face>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(parse_err)?;
            }
            _ => {
                Parser::<Skipped>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(parse_err)?;
            }
        }
    }
    let n = mesh.positions.len();
    for (i, f) in faces.iter().enumerate() {
        mesh.push_polygon(&f.0, n, i)?;
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    const ASCII: &[u8] =
        b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";

    #[test]
    fn ascii_polygon_is_fanned() {
        let m = read(ASCII).unwrap();
        assert_eq!(m.positions[2], [1.0, 1.0, 0.0]);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
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
    fn reads_shared_dragon_header_order() {
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
        assert_eq!(m.positions[1], [1e7, 0.0, 0.0]);
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
    }
}
