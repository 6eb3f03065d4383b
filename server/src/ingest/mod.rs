//! Ingest: mesh files → an indexed triangle mesh in f64 source coordinates.
//!
//! Invariant of the output: every index is < `positions.len()`. Triangles may
//! still be degenerate or non-finite; the voxelizer skips and counts those.

mod obj;
mod ply;

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
}

impl fmt::Display for MeshFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MeshFormat::Obj => "obj",
            MeshFormat::Ply => "ply",
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("unsupported mesh format {0:?}: expected .obj or .ply")]
    UnsupportedFormat(String),
    #[error("not a valid {format} file: {message}")]
    Parse { format: MeshFormat, message: String },
    #[error("invalid mesh: {0}")]
    Invalid(String),
}

impl MeshFormat {
    /// Picks the parser from the file's magic bytes, falling back to its extension.
    pub fn detect(path: &Path, head: &[u8]) -> Result<Self, IngestError> {
        if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
            return Ok(MeshFormat::Ply);
        }
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        match ext.as_str() {
            "obj" => Ok(MeshFormat::Obj),
            "ply" => Ok(MeshFormat::Ply),
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
    };
    if mesh.triangles.is_empty() {
        return Err(IngestError::Invalid("the file holds no triangles".into()));
    }
    Ok(mesh)
}
