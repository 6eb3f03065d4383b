//! Mesh readers on real files: the shared test meshes read with the counts
//! MANIFEST.md gives, and the binary PLY converted to STL and GLB here (never
//! checked in) reading back to the same triangles. Also `build_scene` end to
//! end on an STL and a GLB, the path `voxstream build` takes.

use std::path::{Path, PathBuf};

use serde_json::json;
use voxstream::pipeline::read::{
    IngestError, MeshFormat, ReadOptions, RecordLayout, TriangleMesh, TriangleSink, read_mesh,
    read_mesh_bytes, stream_mesh, stream_mesh_bytes,
};
use voxstream::pipeline::{BuildOptions, Resolution, build_scene};

/// The shared meshes live beside the repository (never in it); tests that need
/// one skip, saying so, where it is absent.
fn shared(name: &str) -> Option<PathBuf> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data").join(name);
    if !path.is_file() {
        eprintln!("skipped: {} not found (the shared test meshes live in ../shared/data)", path.display());
        return None;
    }
    Some(path)
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

fn rocker_arm() -> Option<TriangleMesh> {
    let (mesh, format) = read_mesh(&shared("rocker-arm.ply")?).unwrap();
    assert_eq!(format, MeshFormat::Ply);
    assert_eq!(mesh.triangles.len(), 20_088);
    Some(mesh)
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
        let Some(path) = shared(name) else { continue };
        let (mesh, got) = read_mesh(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got, format, "{name}");
        assert_eq!(mesh.triangles.len(), triangles, "{name}");
        let (lo, hi) = triangle_bounds(&mesh);
        assert!((0..3).all(|c| lo[c].is_finite() && lo[c] < hi[c]), "{name}: bounds {lo:?}..{hi:?}");
    }
}

#[test]
fn rocker_arm_as_binary_stl_reads_back_the_same_triangles() {
    let Some(ply) = rocker_arm() else { return };
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
    let Some(ply) = rocker_arm() else { return };
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
    let Some(ply) = rocker_arm() else { return };
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
        let opts = BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() };
        let report = build_scene(input, &store, &opts).unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!((report.triangles, report.skipped_triangles), (triangles, skipped), "{format}");
        assert!(report.voxels > 0 && report.blocks > 0, "{format}: {report:?}");
        let manifest: serde_json::Value =
            serde_json::from_slice(&std::fs::read(report.scene_dir.join("manifest.json")).unwrap()).unwrap();
        assert_eq!(manifest["source"]["format"], format);
    }
}

/// Counts what a streaming read delivers, holding nothing.
#[derive(Default)]
struct Counter {
    layout: Option<RecordLayout>,
    triangles: u64,
    non_finite: u64,
    colors: Vec<[f32; 3]>,
}

impl TriangleSink for Counter {
    fn begin(&mut self, layout: RecordLayout) -> Result<(), IngestError> {
        assert!(self.layout.is_none(), "begin called twice");
        self.layout = Some(layout);
        Ok(())
    }
    fn triangle(&mut self, tri: [[f64; 3]; 3], color: [f32; 3]) -> Result<(), IngestError> {
        assert!(self.layout.is_some(), "triangle before begin");
        self.triangles += 1;
        if !tri.as_flattened().iter().all(|c| c.is_finite()) {
            self.non_finite += 1;
        }
        if self.colors.len() < 16 {
            self.colors.push(color);
        }
        Ok(())
    }
}

#[test]
fn every_shared_format_streams_with_the_manifest_counts() {
    let cases = [
        ("dragon_vrip.ply", MeshFormat::Ply, 871_414, false),
        ("matterport_cedar_creek.ply", MeshFormat::Ply, 1_091_591, false),
        ("dragon_vrip_res2.ply", MeshFormat::Ply, 202_520, false),
        ("sponza.obj", MeshFormat::Obj, 66_454, true),
        ("CornellBox-Original.obj", MeshFormat::Obj, 36, true),
        ("conference.obj", MeshFormat::Obj, 331_179, true),
    ];
    for (name, format, triangles, f64_positions) in cases {
        let Some(path) = shared(name) else { continue };
        let mut sink = Counter::default();
        let got =
            stream_mesh(&path, &mut sink, &ReadOptions::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got, format, "{name}");
        assert_eq!(sink.triangles, triangles, "{name}");
        assert_eq!(sink.non_finite, 0, "{name}");
        assert_eq!(sink.layout, Some(RecordLayout { f64_positions, color: false }), "{name}");
    }
}

/// Rewrites a binary little-endian PLY of float x y z vertices and uchar/int face lists as big-endian.
fn to_big_endian(le: &[u8]) -> Vec<u8> {
    let end = le.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = std::str::from_utf8(&le[..end]).unwrap();
    assert!(
        header.contains("property float x\nproperty float y\nproperty float z\nelement face"),
        "{header}"
    );
    let count = |el: &str| -> usize {
        let line = header.lines().find(|l| l.starts_with(&format!("element {el} "))).unwrap();
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let mut out = header.replace("binary_little_endian", "binary_big_endian").into_bytes();
    let mut at = end;
    let word = |out: &mut Vec<u8>, at: &mut usize| {
        out.extend(le[*at..*at + 4].iter().rev());
        *at += 4;
    };
    for _ in 0..count("vertex") * 3 {
        word(&mut out, &mut at);
    }
    for _ in 0..count("face") {
        let n = le[at];
        out.push(n);
        at += 1;
        for _ in 0..n {
            word(&mut out, &mut at);
        }
    }
    assert_eq!(at, le.len());
    out
}

#[test]
fn big_endian_ply_reads_the_same_triangles() {
    let Some(path) = shared("rocker-arm.ply") else { return };
    let le = std::fs::read(path).unwrap();
    let be = to_big_endian(&le);
    let (a, b) =
        (read_mesh_bytes(&le, MeshFormat::Ply).unwrap(), read_mesh_bytes(&be, MeshFormat::Ply).unwrap());
    assert_eq!(a.triangles.len(), 20_088);
    assert_eq!(a, b);
}

/// Colours, normals and positions interleaved in an odd order, an alpha, and a
/// texture-coordinate list on the faces; float colours in the second file.
#[test]
fn ply_colours_and_normals_in_any_property_order() {
    let header = |color: &str| {
        format!(
            "ply\nformat ascii 1.0\ncomment odd order\nelement vertex 4\nproperty {color} red\nproperty float nx\n\
             property double z\nproperty {color} green\nproperty float x\nproperty float ny\nproperty {color} blue\n\
             property float y\nproperty float nz\nproperty {color} alpha\nelement face 1\n\
             property list uchar float texcoord\nproperty list uchar uint vertex_indices\nend_header\n"
        )
    };
    let body = |c: [&str; 4]| {
        format!(
            "{r} 0 0.5 {g} 0 0 {b} 0 1 {a}\n{r} 0 0.5 {g} 1 0 {b} 0 1 {a}\n{r} 0 0.5 {g} 1 0 {b} 1 1 {a}\n\
             {r} 0 0.5 {g} 0 0 {b} 1 1 {a}\n2 0.5 0.5 4 0 1 2 3\n",
            r = c[0],
            g = c[1],
            b = c[2],
            a = c[3]
        )
    };
    let uchar = header("uchar") + &body(["255", "0", "128", "255"]);
    let float = header("float") + &body(["1.0", "0.0", "0.5", "1.0"]);
    for text in [uchar, float] {
        let m = read_mesh_bytes(text.as_bytes(), MeshFormat::Ply).unwrap_or_else(|e| panic!("{e}\n{text}"));
        assert_eq!(m.triangles.len(), 2, "quad fanned");
        assert_eq!(m.triangle(0), [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [1.0, 1.0, 0.5]]);
        let c = m.triangle_color(0).unwrap();
        assert_eq!(c[0], 1.0);
        assert_eq!(c[1], 0.0);
        // sRGB 128/255 (or 0.5) is about 0.21 in linear light.
        assert!((0.2..0.22).contains(&c[2]), "{c:?}");
        let mut sink = Counter::default();
        stream_mesh_bytes(text.as_bytes(), MeshFormat::Ply, &mut sink, &ReadOptions::default()).unwrap();
        assert_eq!(sink.layout, Some(RecordLayout { f64_positions: true, color: true }), "double z");
        assert_eq!(sink.colors[0], c);
    }
}

#[test]
fn ngons_are_fanned_in_ascii_and_binary() {
    let ascii = b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n\
element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n2 1 0\n1 2 0\n0 1 0\n5 0 1 2 3 4\n2 0 1\n";
    let m = read_mesh_bytes(ascii, MeshFormat::Ply).unwrap();
    // The pentagon gives 3 triangles; a 2-gon none.
    assert_eq!(m.triangles.len(), 3);
    assert_eq!(m.triangle(2), [[0.0, 0.0, 0.0], [1.0, 2.0, 0.0], [0.0, 1.0, 0.0]]);
    let mut bin =
        b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n\
property float z\nelement face 1\nproperty list uchar ushort vertex_indices\nend_header\n"
            .to_vec();
    for p in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 1.0, 0.0]] {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    bin.push(5);
    for i in 0u16..5 {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    assert_eq!(read_mesh_bytes(&bin, MeshFormat::Ply).unwrap(), m);
}

#[test]
fn truncated_files_are_errors_in_every_format() {
    let Some(ply) = shared("rocker-arm.ply").map(|p| std::fs::read(p).unwrap()) else { return };
    let mesh = read_mesh_bytes(&ply, MeshFormat::Ply).unwrap();
    let stl = write_binary_stl(&mesh);
    let glb = write_glb(&mesh, [0.0; 3]);
    for (bytes, format) in [(&ply, MeshFormat::Ply), (&stl, MeshFormat::Stl), (&glb, MeshFormat::Glb)] {
        for cut in [0, 10, 100, bytes.len() / 3, bytes.len() - 7, bytes.len() - 1] {
            let e = read_mesh_bytes(&bytes[..cut], format).expect_err(&format!("{format} cut at {cut}"));
            assert!(!e.to_string().is_empty());
        }
    }
    let e = read_mesh_bytes(&ply[..ply.len() - 7], MeshFormat::Ply).unwrap_err().to_string();
    assert!(e.contains("face"), "names the element: {e}");
}

#[test]
fn wrong_headers_are_errors() {
    let v = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n";
    let cases = [
        format!("ply\nformat binary_middle_endian 1.0\n{v}end_header\n"),
        format!("ply\nformat ascii 1.0\n{v}"),
        "ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nend_header\n".to_string(),
        format!("ply\nformat ascii 1.0\n{}end_header\n0 0 0\n", v.replace("float y", "quaternion y")),
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n0 0\n"
            .to_string(),
        "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
            .to_string(),
        format!("ply\nformat ascii 1.0\n{v}property list uchar float x2\nend_header\n0 0 0 1 zero\n"),
        "solid x\n".to_string(),
    ];
    for text in &cases {
        let e = read_mesh_bytes(text.as_bytes(), MeshFormat::Ply).expect_err(text);
        assert!(!e.to_string().is_empty());
    }
}

#[test]
fn counts_larger_than_the_file_fail_fast_without_allocating() {
    let start = std::time::Instant::now();
    for (el, count) in [("vertex", "4000000000"), ("vertex", "18446744073709551615"), ("face", "4000000000")]
    {
        for format in ["ascii", "binary_little_endian", "binary_big_endian"] {
            let text = format!(
                "ply\nformat {format} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
                 element face {}\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n",
                if el == "vertex" { count } else { "1" },
                if el == "face" { count } else { "1" },
            );
            let e = read_mesh_bytes(text.as_bytes(), MeshFormat::Ply).unwrap_err().to_string();
            assert!(e.contains(count) && e.contains("but the file has only"), "{format} {el}: {e}");
        }
    }
    // No per-element work happened: the check comes before reading.
    assert!(start.elapsed().as_secs() < 5);
}

#[test]
fn non_finite_coordinates_are_counted_and_skipped_by_the_build() {
    let mut ply =
        b"ply\nformat binary_big_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n\
property float z\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
            .to_vec();
    for p in [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [f32::NAN, 0.0, 0.0],
        [0.0, f32::INFINITY, 1.0],
    ] {
        for c in p {
            ply.extend_from_slice(&c.to_be_bytes());
        }
    }
    for face in [[0i32, 1, 2], [0, 3, 2], [4, 1, 2]] {
        ply.push(3);
        for i in face {
            ply.extend_from_slice(&i.to_be_bytes());
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan.ply");
    std::fs::write(&path, &ply).unwrap();
    let report = build_scene(
        &path,
        &dir.path().join("store"),
        &BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() },
    )
    .unwrap();
    assert_eq!((report.triangles, report.skipped_triangles), (3, 2));
    // ASCII "nan" is not a PLY number: an error naming the line, not a panic.
    let ascii =
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
end_header\n0 0 0\nnan 0 0\n0 1 0\n";
    assert!(read_mesh_bytes(ascii, MeshFormat::Ply).is_err());
}

#[test]
fn memory_budget_refuses_what_cannot_fit() {
    let Some(path) = shared("rocker-arm.ply") else { return };
    // A PLY's vertex table that does not fit is paged from disk, not refused.
    let small = ReadOptions { memory_budget: 64 << 10, ..Default::default() };
    let mut paged = Counter::default();
    stream_mesh(&path, &mut paged, &small).unwrap();
    let koala = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj");
    let e = stream_mesh(&koala, &mut Counter::default(), &small).unwrap_err();
    assert!(matches!(e, IngestError::TooLarge(_)), "{e}");
    // Within the budget both stream, and bytes_read reaches the file size.
    let opts = ReadOptions::default();
    let mut held = Counter::default();
    stream_mesh(&path, &mut held, &opts).unwrap();
    assert_eq!((paged.triangles, &paged.colors), (held.triangles, &held.colors));
    assert_eq!(
        opts.bytes_read.load(std::sync::atomic::Ordering::Relaxed),
        std::fs::metadata(&path).unwrap().len()
    );
}

/// Every triangle and colour a streaming read delivers, as bits.
#[derive(Default)]
struct Recorder {
    layout: Option<RecordLayout>,
    bits: Vec<u64>,
}

impl TriangleSink for Recorder {
    fn begin(&mut self, layout: RecordLayout) -> Result<(), IngestError> {
        self.layout = Some(layout);
        Ok(())
    }
    fn triangle(&mut self, tri: [[f64; 3]; 3], color: [f32; 3]) -> Result<(), IngestError> {
        self.bits.extend(tri.as_flattened().iter().map(|c| c.to_bits()));
        self.bits.extend(color.iter().map(|c| u64::from(c.to_bits())));
        Ok(())
    }
}

/// The koala as binary big-endian PLY with double positions, ushort colours
/// and a list in the vertex element (variable-size records), faces as
/// quads and triangles.
fn koala_ply_with_lists(dir: &Path) -> PathBuf {
    let (mesh, _) = read_mesh(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")).unwrap();
    let mut out = format!(
        "ply\nformat binary_big_endian 1.0\nelement vertex {}\nproperty double x\nproperty ushort red\n\
         property list uchar int tags\nproperty double y\nproperty ushort green\nproperty ushort blue\n\
         property double z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.positions.len(),
        mesh.triangles.len()
    )
    .into_bytes();
    for (i, p) in mesh.positions.iter().enumerate() {
        out.extend_from_slice(&p[0].to_be_bytes());
        out.extend_from_slice(&((i * 37 % 65536) as u16).to_be_bytes());
        out.push((i % 3) as u8);
        for k in 0..i % 3 {
            out.extend_from_slice(&(k as i32).to_be_bytes());
        }
        out.extend_from_slice(&p[1].to_be_bytes());
        out.extend_from_slice(&((i * 11 % 65536) as u16).to_be_bytes());
        out.extend_from_slice(&40000u16.to_be_bytes());
        out.extend_from_slice(&p[2].to_be_bytes());
    }
    for t in &mesh.triangles {
        out.push(3);
        for i in t {
            out.extend_from_slice(&i.to_be_bytes());
        }
    }
    let path = dir.join("koala-lists.ply");
    std::fs::write(&path, out).unwrap();
    path
}

#[test]
fn a_paged_vertex_table_gives_the_same_triangles() {
    let dir = tempfile::tempdir().unwrap();
    let mut inputs = vec![koala_ply_with_lists(dir.path())];
    // ASCII, 437k vertices: hundreds of pages.
    inputs.extend(shared("dragon_vrip.ply"));
    let read = |path: &Path, vertex_memory: Option<u64>, temp_dir: Option<PathBuf>| {
        let mut sink = Recorder::default();
        let opts = ReadOptions { vertex_memory, temp_dir, ..Default::default() };
        stream_mesh(path, &mut sink, &opts).map(|_| sink)
    };
    for path in &inputs {
        let held = read(path, None, None).unwrap();
        assert!(held.bits.len() > 100_000, "{}", path.display());
        // One page of cache (faces across pages take the one-by-one path),
        // 4 pages of the koala's 13 and 9 of the dragon's 107 (evictions), and all.
        for vertex_memory in [1, 864 << 10, 16 << 20] {
            let paged = read(path, Some(vertex_memory), Some(dir.path().to_path_buf())).unwrap();
            assert_eq!(paged.layout, held.layout);
            assert!(paged.bits == held.bits, "{} differs paged at {vertex_memory}", path.display());
        }
        // Negative control: the knob does take the paged path (it needs its
        // temporary directory), and the default does not.
        let missing = dir.path().join("missing");
        let e = read(path, Some(1), Some(missing.clone())).err().expect("the paged path needs its directory");
        assert!(e.to_string().contains("temporary file of the PLY's vertices"), "{e}");
        assert!(read(path, None, Some(missing)).is_ok());
    }
    // Negative control: a vertex moved by one ulp is seen by the comparison.
    let bytes = std::fs::read(&inputs[0]).unwrap();
    let header = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let mut moved = bytes.clone();
    moved[header + 7] ^= 1;
    let moved_path = dir.path().join("moved.ply");
    std::fs::write(&moved_path, &moved).unwrap();
    let held = read(&inputs[0], None, None).unwrap();
    let paged = read(&moved_path, Some(1), Some(dir.path().to_path_buf())).unwrap();
    assert!(paged.bits != held.bits);
    // A truncated file and an index past the vertices are errors naming the problem, paged too.
    let cut = dir.path().join("cut.ply");
    for len in [header + 1000, bytes.len() - 3] {
        std::fs::write(&cut, &bytes[..len]).unwrap();
        let e = read(&cut, Some(1), Some(dir.path().to_path_buf())).err().expect("truncated");
        assert!(e.to_string().contains("not a valid ply file"), "{len}: {e}");
    }
    let mut bad = bytes.clone();
    let n = bad.len();
    bad[n - 4..].copy_from_slice(&u32::MAX.to_be_bytes());
    std::fs::write(&cut, &bad).unwrap();
    let e = read(&cut, Some(1), Some(dir.path().to_path_buf())).err().expect("bad index");
    assert!(e.to_string().contains(&format!("uses vertex {}", u32::MAX)), "{e}");
    // The unnamed spill files leave nothing behind.
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left.len(), 3, "{left:?}");
}

#[test]
fn mutated_files_never_panic() {
    use rand::{Rng, SeedableRng, rngs::StdRng};
    let ascii = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 2\nproperty list uchar int vertex_indices\n\
end_header\n0 0 0 1 2 3\n1 0 0 4 5 6\n1 1 0 7 8 9\n0 1 0 1 1 1\n3 0 1 2\n4 0 1 2 3\n";
    let mesh = read_mesh_bytes(ascii, MeshFormat::Ply).unwrap();
    let binary = |big: bool| {
        let mut b = format!(
            "ply\nformat binary_{}_endian 1.0\nelement vertex 4\nproperty float x\nproperty uchar red\n\
             property float y\nproperty uchar green\nproperty uchar blue\nproperty float z\nelement face 2\n\
             property list uchar int vertex_indices\nproperty uchar flags\nend_header\n",
            if big { "big" } else { "little" }
        )
        .into_bytes();
        let f = |b: &mut Vec<u8>, v: f32| {
            b.extend_from_slice(&if big { v.to_be_bytes() } else { v.to_le_bytes() })
        };
        for (k, p) in [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]].iter().enumerate()
        {
            f(&mut b, p[0]);
            b.push(k as u8 * 60);
            f(&mut b, p[1]);
            b.extend_from_slice(&[9, 200]);
            f(&mut b, p[2]);
        }
        for face in [&[0i32, 1, 2][..], &[0, 1, 2, 3]] {
            b.push(face.len() as u8);
            for i in face {
                b.extend_from_slice(&if big { i.to_be_bytes() } else { i.to_le_bytes() });
            }
            b.push(7);
        }
        b
    };
    let (le, be) = (binary(false), binary(true));
    let (a, b) =
        (read_mesh_bytes(&le, MeshFormat::Ply).unwrap(), read_mesh_bytes(&be, MeshFormat::Ply).unwrap());
    assert_eq!(a.triangles.len(), 3);
    assert_eq!(a, b);
    let seeds: Vec<(Vec<u8>, MeshFormat)> = vec![
        (ascii.to_vec(), MeshFormat::Ply),
        (le, MeshFormat::Ply),
        (be, MeshFormat::Ply),
        (write_binary_stl(&mesh), MeshFormat::Stl),
        (write_glb(&mesh, [0.0; 3]), MeshFormat::Glb),
        (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(), MeshFormat::Obj),
    ];
    let mut rng = StdRng::seed_from_u64(7);
    for (seed, format) in &seeds {
        for _ in 0..1500 {
            let mut b = seed.clone();
            for _ in 0..rng.random_range(1..4) {
                let i = rng.random_range(0..b.len());
                match rng.random_range(0..3) {
                    0 => b[i] = rng.random(),
                    1 => b.truncate(i),
                    _ => b.insert(i, b"0123456789 \n-e."[rng.random_range(0..15)]),
                }
                if b.is_empty() {
                    break;
                }
            }
            let _ = read_mesh_bytes(&b, *format);
        }
    }
}
