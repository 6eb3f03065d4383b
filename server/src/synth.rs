//! Synthetic scans for benchmarks: a displaced, finely tessellated sphere,
//! streamed to a binary little-endian PLY so that a billion-triangle file
//! costs a few kilobytes of memory to write.
//!
//! Layout: `rows + 1` latitude rings of `2·rows` vertices (poles repeated per
//! column, so every quad has 4 distinct indices), then `2·rows·(2·rows)` =
//! `4·rows²` triangles. The pole vertices of a column differ only in height,
//! so the triangles at the poles are slivers, as in real scans.

use std::f64::consts::PI;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// What [`write_sphere_ply`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SynthReport {
    pub vertices: u64,
    pub triangles: u64,
    pub bytes: u64,
}

/// Rings so that `4·rows²` is at least `triangles`.
pub fn rows_for(triangles: u64) -> u32 {
    let rows = ((triangles.max(8) as f64 / 4.0).sqrt().ceil()) as u64;
    rows.clamp(2, u32::MAX as u64 / 4) as u32
}

/// Radius at a direction: a few octaves of smooth bumps, so the surface has
/// detail at every LOD level yet is closed and star-shaped.
fn radius(theta: f64, phi: f64) -> f64 {
    1.0 + 0.06 * (5.0 * theta).sin() * (7.0 * phi).cos()
        + 0.02 * (23.0 * theta + 1.0).sin() * (19.0 * phi).sin()
        + 0.006 * (97.0 * theta).cos() * (89.0 * phi + 2.0).sin()
}

pub fn write_sphere_ply(path: &Path, triangles: u64) -> io::Result<SynthReport> {
    let rows = rows_for(triangles) as u64;
    let cols = 2 * rows;
    let vertices = (rows + 1) * cols;
    let tris = 2 * rows * cols;
    if vertices > u32::MAX as u64 {
        return Err(io::Error::new(io::ErrorKind::InvalidInput, "too many vertices for u32 indices"));
    }
    // Written to a temp name and renamed, so a killed run never leaves a plausible half file.
    let tmp = path.with_extension("ply.partial");
    let mut out = BufWriter::with_capacity(1 << 20, std::fs::File::create(&tmp)?);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment voxstream synth: displaced sphere, {rows} rings\n\
         element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n\
         element face {tris}\nproperty list uchar uint vertex_indices\nend_header\n"
    );
    out.write_all(header.as_bytes())?;
    for r in 0..=rows {
        let theta = PI * r as f64 / rows as f64;
        for c in 0..cols {
            let phi = 2.0 * PI * c as f64 / cols as f64;
            let rad = radius(theta, phi);
            let p = [rad * theta.sin() * phi.cos(), rad * theta.cos(), rad * theta.sin() * phi.sin()];
            for v in p {
                out.write_all(&(v as f32).to_le_bytes())?;
            }
        }
    }
    let index = |r: u64, c: u64| (r * cols + c % cols) as u32;
    for r in 0..rows {
        for c in 0..cols {
            let (a, b, d, e) = (index(r, c), index(r, c + 1), index(r + 1, c), index(r + 1, c + 1));
            for t in [[a, d, b], [b, d, e]] {
                out.write_all(&[3])?;
                for i in t {
                    out.write_all(&i.to_le_bytes())?;
                }
            }
        }
    }
    out.flush()?;
    let file = out.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()?;
    let bytes = file.metadata()?.len();
    std::fs::rename(&tmp, path)?;
    Ok(SynthReport { vertices, triangles: tris, bytes })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::read::read_mesh;

    #[test]
    fn writes_a_readable_closed_sphere() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.ply");
        let report = write_sphere_ply(&path, 5000).unwrap();
        assert!(report.triangles >= 5000);
        assert_eq!(report.bytes, std::fs::metadata(&path).unwrap().len());
        let (mesh, _) = read_mesh(&path).unwrap();
        assert_eq!(mesh.triangles.len() as u64, report.triangles);
        let r = |p: [f64; 3]| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        assert!(mesh.positions.iter().all(|&p| (0.9..1.1).contains(&r(p))));
        assert!(!dir.path().join("s.ply.partial").exists());
    }

    #[test]
    fn row_count_reaches_the_request() {
        for n in [1, 8, 1000, 50_000_000, 1_000_000_000] {
            let rows = rows_for(n) as u64;
            assert!(4 * rows * rows >= n && 4 * (rows - 1) * (rows - 1) < n.max(16), "{n}");
        }
    }
}
