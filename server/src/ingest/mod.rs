//! Ingest: mesh files → an indexed triangle mesh in f64 source coordinates.
//!
//! Invariant of the output: every index is < `positions.len()`. Triangles may
//! still be degenerate or non-finite; the voxelizer skips and counts those.

mod gltf;
mod obj;
mod ply;
mod stl;

use std::fmt;
use std::path::Path;

/// An indexed triangle mesh in the source file's own coordinates and units.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct TriangleMesh {
    pub positions: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

impl TriangleMesh {
    pub fn triangle(&self, t: usize) -> [[f64; 3]; 3] {
        self.triangles[t].map(|i| self.positions[i as usize])
    }

    /// Appends a polygon as a fan, rejecting indices outside the vertex list.
    fn push_polygon(&mut self, poly: &[u32], vertex_count: usize, face: usize) -> Result<(), IngestError> {
        if let Some(&bad) = poly.iter().find(|&&i| i as usize >= vertex_count) {
            return Err(IngestError::Invalid(format!(
                "face {face} uses vertex {bad}, but the file has only {vertex_count} vertices"
            )));
        }
        for k in 1..poly.len().saturating_sub(1) {
            self.triangles.push([poly[0], poly[k], poly[k + 1]]);
        }
        Ok(())
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

/// Reads a mesh file. OBJ never follows `mtllib`: materials are not needed.
pub fn read_mesh(path: &Path) -> Result<(TriangleMesh, MeshFormat), IngestError> {
    let io = |source| IngestError::Io { path: path.display().to_string(), source };
    let bytes = std::fs::read(path).map_err(io)?;
    let format = MeshFormat::detect(path, &bytes[..bytes.len().min(8)])?;
    let mesh = read_mesh_bytes(&bytes, format)?;
    Ok((mesh, format))
}

pub fn read_mesh_bytes(bytes: &[u8], format: MeshFormat) -> Result<TriangleMesh, IngestError> {
    let mesh = match format {
        MeshFormat::Obj => obj::read(bytes)?,
        MeshFormat::Ply => ply::read(bytes)?,
        MeshFormat::Stl => stl::read(bytes)?,
        // The glTF reader tells JSON from GLB by the magic itself.
        MeshFormat::Gltf | MeshFormat::Glb => gltf::read(bytes)?,
    };
    if mesh.triangles.is_empty() {
        return Err(IngestError::Invalid("the file holds no triangles".into()));
    }
    Ok(mesh)
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
