//! Mesh readers on real files: the shared test meshes read with the counts
//! MANIFEST.md gives, and the binary PLY converted to STL and GLB here (never
//! checked in) reading back to the same triangles. Also `build_scene` end to
//! end on an STL and a GLB, the path `voxstream build` takes.

use std::path::{Path, PathBuf};

use serde_json::json;
use voxstream::build::{BuildOptions, build_scene};
use voxstream::ingest::{MeshFormat, TriangleMesh, read_mesh, read_mesh_bytes};

/// The shared meshes live beside the repository; CI always has them, so a missing folder fails loudly.
fn shared(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    assert!(
        dir.is_dir(),
        "test meshes not found at {}: these tests need ../shared/data beside the repository",
        dir.display()
    );
    dir.join(name)
}

/// Binary STL, with a header that starts with "solid" as many exporters write it.
fn write_binary_stl(mesh: &TriangleMesh) -> Vec<u8> {
    let mut out = vec![0u8; 80];
    out[..22].copy_from_slice(b"solid written by tests");
    out.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
    for t in 0..mesh.triangles.len() {
        out.extend_from_slice(&[0u8; 12]); // normal: readers ignore it
        for v in mesh.triangle(t) {
            for c in v {
                out.extend_from_slice(&(c as f32).to_le_bytes());
            }
        }
        out.extend_from_slice(&[0u8; 2]);
    }
    out
}

/// GLB with one node (translated by `offset`) holding the mesh: f32 VEC3 positions, u32 indices.
fn write_glb(mesh: &TriangleMesh, offset: [f64; 3]) -> Vec<u8> {
    let mut bin: Vec<u8> = mesh.positions.iter().flatten().flat_map(|&c| (c as f32).to_le_bytes()).collect();
    let pos_len = bin.len();
    bin.extend(mesh.triangles.iter().flatten().flat_map(|i| i.to_le_bytes()));
    let (min, max) = bounds(&mesh.positions);
    let doc = json!({
        "asset": {"version": "2.0", "generator": "voxstream readers test"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": offset}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": mesh.positions.len(), "type": "VEC3",
             "min": min, "max": max},
            {"bufferView": 1, "componentType": 5125, "count": mesh.triangles.len() * 3, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": pos_len},
            {"buffer": 0, "byteOffset": pos_len, "byteLength": bin.len() - pos_len},
        ],
        "buffers": [{"byteLength": bin.len()}],
    });
    let mut json = serde_json::to_vec(&doc).unwrap();
    json.resize(json.len().next_multiple_of(4), b' ');
    bin.resize(bin.len().next_multiple_of(4), 0);
    let mut out = b"glTF".to_vec();
    let total = 12 + 8 + json.len() + 8 + bin.len();
    for word in [2, total as u32, json.len() as u32, 0x4E4F_534A] {
        out.extend_from_slice(&u32::to_le_bytes(word));
    }
    out.extend_from_slice(&json);
    for word in [bin.len() as u32, 0x004E_4942] {
        out.extend_from_slice(&u32::to_le_bytes(word));
    }
    out.extend_from_slice(&bin);
    out
}

fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for c in 0..3 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    (lo, hi)
}

/// Bounds of the vertices triangles use (a file may hold unused vertices).
fn triangle_bounds(mesh: &TriangleMesh) -> ([f64; 3], [f64; 3]) {
    let used: Vec<[f64; 3]> = (0..mesh.triangles.len()).flat_map(|t| mesh.triangle(t)).collect();
    bounds(&used)
}

fn rocker_arm() -> TriangleMesh {
    let (mesh, format) = read_mesh(&shared("rocker-arm.ply")).unwrap();
    assert_eq!(format, MeshFormat::Ply);
    assert_eq!(mesh.triangles.len(), 20_088);
    mesh
}

#[test]
fn shared_meshes_have_the_manifest_triangle_counts() {
    let cases = [
        ("koala.obj", MeshFormat::Obj, 99_994),
        ("stanford-bunny.obj", MeshFormat::Obj, 69_451),
        ("dragon_vrip_res4.ply", MeshFormat::Ply, 11_102),
        ("rocker-arm.ply", MeshFormat::Ply, 20_088),
    ];
    for (name, format, triangles) in cases {
        let (mesh, got) = read_mesh(&shared(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got, format, "{name}");
        assert_eq!(mesh.triangles.len(), triangles, "{name}");
        let (lo, hi) = triangle_bounds(&mesh);
        assert!((0..3).all(|c| lo[c].is_finite() && lo[c] < hi[c]), "{name}: bounds {lo:?}..{hi:?}");
    }
}

#[test]
fn rocker_arm_as_binary_stl_reads_back_the_same_triangles() {
    let ply = rocker_arm();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rocker-arm.stl");
    std::fs::write(&path, write_binary_stl(&ply)).unwrap();
    let (stl, format) = read_mesh(&path).unwrap();
    assert_eq!(format, MeshFormat::Stl);
    assert_eq!(stl.triangles.len(), ply.triangles.len());
    assert_eq!(triangle_bounds(&stl), triangle_bounds(&ply));
    // The PLY holds float32 coordinates, so the round trip through f32 is exact.
    for t in 0..ply.triangles.len() {
        assert_eq!(stl.triangle(t), ply.triangle(t), "triangle {t}");
    }
}

#[test]
fn rocker_arm_as_glb_reads_back_the_same_triangles_moved_by_the_node() {
    let ply = rocker_arm();
    let offset = [100.0, -20.0, 0.5];
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rocker-arm.glb");
    std::fs::write(&path, write_glb(&ply, offset)).unwrap();
    let (glb, format) = read_mesh(&path).unwrap();
    assert_eq!(format, MeshFormat::Glb);
    assert_eq!(glb.triangles.len(), ply.triangles.len());
    let moved = |p: [f64; 3]| std::array::from_fn(|c| p[c] + offset[c]);
    let (lo, hi) = triangle_bounds(&ply);
    assert_eq!(triangle_bounds(&glb), (moved(lo), moved(hi)));
    for t in 0..ply.triangles.len() {
        assert_eq!(glb.triangle(t), ply.triangle(t).map(moved), "triangle {t}");
    }
    // The same bytes under a .bin name are still found by their magic.
    let renamed = dir.path().join("rocker-arm.bin");
    std::fs::rename(&path, &renamed).unwrap();
    assert_eq!(read_mesh(&renamed).unwrap().1, MeshFormat::Glb);
}

#[test]
fn hostile_headers_are_errors_without_huge_allocations() {
    let ply = rocker_arm();
    let mut stl = write_binary_stl(&ply);
    stl[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    let e = read_mesh_bytes(&stl, MeshFormat::Stl).unwrap_err().to_string();
    assert!(e.contains("4294967295") && e.contains(&stl.len().to_string()), "{e}");
    let glb = write_glb(&ply, [0.0; 3]);
    let e = read_mesh_bytes(&glb[..glb.len() / 2], MeshFormat::Glb).unwrap_err().to_string();
    assert!(e.starts_with("not a valid glb"), "{e}");
}

#[test]
fn build_scene_accepts_stl_and_glb() {
    let mut mesh = TriangleMesh {
        positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        ..Default::default()
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let glb = dir.path().join("tetra-glb.glb");
    std::fs::write(&glb, write_glb(&mesh, [0.0; 3])).unwrap();
    // A NaN triangle passes the reader and is skipped (and counted) by the voxelizer.
    mesh.positions.push([f64::NAN, 0.0, 0.0]);
    mesh.triangles.push([4, 1, 2]);
    let stl = dir.path().join("tetra-stl.stl");
    std::fs::write(&stl, write_binary_stl(&mesh)).unwrap();

    for (input, format, triangles, skipped) in [(&stl, "stl", 5, 1), (&glb, "glb", 4, 0)] {
        let opts = BuildOptions { resolution: 64, ..Default::default() };
        let report = build_scene(input, &store, &opts).unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!((report.triangles, report.skipped_triangles), (triangles, skipped), "{format}");
        assert!(report.voxels > 0 && report.blocks > 0, "{format}: {report:?}");
        let manifest: serde_json::Value =
            serde_json::from_slice(&std::fs::read(report.scene_dir.join("manifest.json")).unwrap()).unwrap();
        assert_eq!(manifest["source"]["format"], format);
    }
}
