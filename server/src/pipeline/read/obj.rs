use super::{IngestError, MeshFormat, TriangleMesh, srgb_to_linear};

pub(super) fn read(bytes: &[u8]) -> Result<TriangleMesh, IngestError> {
    check_relative_indices(bytes)?;
    let options = tobj::LoadOptions {
        triangulate: false, // fan-triangulated by push_polygon, with index checks
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // The material loader never touches the filesystem: an upload must not be
    // able to make us open paths it names.
    let (models, _materials) = tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(|e| IngestError::Parse { format: MeshFormat::Obj, message: e.to_string() })?;

    let mut mesh = TriangleMesh::default();
    // Colours only when every vertex of every model has one (`v x y z r g b`).
    let colored = models.iter().all(|m| m.mesh.vertex_color.len() == m.mesh.positions.len())
        && models.iter().any(|m| !m.mesh.positions.is_empty());
    for model in &models {
        let m = &model.mesh;
        let base = mesh.positions.len() as u32;
        let count = m.positions.len() / 3;
        mesh.positions.extend(m.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        if colored {
            mesh.colors.extend(
                m.vertex_color.chunks_exact(3).map(|c| [0, 1, 2].map(|a| srgb_to_linear(c[a] as f32))),
            );
        }
        let mut start = 0usize;
        // tobj leaves face_arities empty when every face is a triangle.
        let all_triangles;
        let arities: &[u32] = if m.face_arities.is_empty() {
            all_triangles = vec![3; m.indices.len() / 3];
            &all_triangles
        } else {
            &m.face_arities
        };
        for (face, &arity) in arities.iter().enumerate() {
            let end = start + arity as usize;
            let Some(poly) = m.indices.get(start..end) else {
                return Err(IngestError::Invalid(format!("face {face} of {:?} is truncated", model.name)));
            };
            let poly: Vec<u32> = poly.iter().map(|&i| i + base).collect();
            mesh.push_polygon(&poly, base as usize + count, face)?;
            start = end;
        }
    }
    Ok(mesh)
}

/// tobj 4.0.5 overflows (a panic with overflow checks on) when a negative
/// (relative) index reaches before the first texcoord or normal, so those are
/// refused here first. Only `f` lines are looked at; everything else is tobj's.
fn check_relative_indices(bytes: &[u8]) -> Result<(), IngestError> {
    let mut seen = [0u64; 3]; // v, vt, vn so far
    for (line_no, line) in bytes.split(|&b| b == b'\n').enumerate() {
        let line = line.trim_ascii();
        let mut words = line.split(|b| b.is_ascii_whitespace()).filter(|w| !w.is_empty());
        match words.next() {
            Some(b"v") => seen[0] += 1,
            Some(b"vt") => seen[1] += 1,
            Some(b"vn") => seen[2] += 1,
            Some(b"f") => {
                for corner in words {
                    for (kind, part) in corner.split(|&b| b == b'/').enumerate().take(3) {
                        let Some(reach) = part.strip_prefix(b"-") else { continue };
                        let reach = std::str::from_utf8(reach).ok().and_then(|r| r.parse::<u64>().ok());
                        if reach.is_none_or(|r| r > seen[kind]) {
                            let what = ["vertex", "texture coordinate", "normal"][kind];
                            return Err(IngestError::Parse {
                                format: MeshFormat::Obj,
                                message: format!(
                                    "line {}: face refers to {what} {} but only {} precede it",
                                    line_no + 1,
                                    String::from_utf8_lossy(part),
                                    seen[kind]
                                ),
                            });
                        }
                    }
                }
            }
            _ => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quads_become_two_triangles() {
        let m = read(b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n").unwrap();
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn relative_indices_before_the_start_are_errors() {
        let ok = read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n").unwrap();
        assert_eq!(ok.triangles.len(), 1);
        let e = read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//-1 2//-2 3//-1\n").unwrap_err();
        assert!(e.to_string().contains("normal -2"), "{e}");
        assert!(read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/-3 2/1 3/1\n").is_err());
        assert!(read(b"v 0 0 0\nf -4 -1 -1\n").is_err());
    }

    #[test]
    fn mtllib_is_never_opened() {
        let m = read(b"mtllib /etc/passwd\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        assert_eq!(m.triangles.len(), 1);
    }

    #[test]
    fn bad_input_is_an_error() {
        assert!(read(b"v 0 0 0\nf 1 2 3\n").is_err());
        assert!(read(b"v zero 0 0\n").is_err());
    }

    #[test]
    fn vertex_colours_are_linearised() {
        let m = read(b"v 0 0 0 1 0 0.5\nv 1 0 0 1 0 0.5\nv 0 1 0 0 0 0\nf 1 2 3\n").unwrap();
        assert_eq!(m.colors.len(), 3);
        assert_eq!(m.colors[0][0], 1.0);
        assert!((m.colors[0][2] - 0.214).abs() < 1e-3, "{:?}", m.colors[0]);
        let c = m.triangle_color(0).unwrap();
        assert!((c[0] - 2.0 / 3.0).abs() < 1e-6);
        assert!(read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap().triangle_color(0).is_none());
    }
}
