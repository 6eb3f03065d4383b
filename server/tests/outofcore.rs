//! The out-of-core build (chunked stream → spilled bins → parallel blocks):
//! byte-identical stores whatever the memory budget and thread count, the
//! same blocks as the in-memory voxelizer, area-weighted colours, and temp
//! files gone after success, error and cancellation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use voxstream::pipeline::pyramid::build_levels;
use voxstream::pipeline::read::{TriangleMesh, read_mesh};
use voxstream::pipeline::voxelize::{choose_frame, voxelize};
use voxstream::pipeline::write::packed_block;
use voxstream::pipeline::{BuildError, BuildOptions, build_scene, parse_byte_size};
use voxstream_format::encode_block;

fn koala() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")
}

/// The koala as binary little-endian PLY with float positions and uchar vertex
/// colours (a gradient), written into `dir`: streamed, unlike OBJ.
fn koala_ply(dir: &Path) -> PathBuf {
    let (mesh, _) = read_mesh(&koala()).unwrap();
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty uchar red\n\
         property float y\nproperty uchar green\nproperty uchar blue\nproperty float z\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.positions.len(),
        mesh.triangles.len()
    )
    .into_bytes();
    for (i, p) in mesh.positions.iter().enumerate() {
        out.extend_from_slice(&(p[0] as f32).to_le_bytes());
        out.push((i % 256) as u8);
        out.extend_from_slice(&(p[1] as f32).to_le_bytes());
        out.extend_from_slice(&[(i / 256 % 256) as u8, 200]);
        out.extend_from_slice(&(p[2] as f32).to_le_bytes());
    }
    for t in &mesh.triangles {
        out.push(3);
        for i in t {
            out.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    let path = dir.join("koala-colour.ply");
    std::fs::write(&path, out).unwrap();
    path
}

/// Every file under `dir`, by relative path.
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

fn leftovers(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with('.'))
                .collect()
        })
        .unwrap_or_default()
}

fn build_with(input: &Path, threads: usize, budget: u64, tmp: Option<&Path>) -> BTreeMap<String, Vec<u8>> {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let opts = BuildOptions {
        resolution: 128,
        memory_budget: budget,
        temp_dir: tmp.map(Path::to_path_buf),
        ..Default::default()
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    let report = pool.install(|| build_scene(input, &store, &opts)).unwrap();
    assert!(report.voxels > 10_000, "{report:?}");
    assert_eq!(leftovers(&store), Vec::<String>::new(), "temp files left in the store");
    if let Some(t) = tmp {
        assert_eq!(leftovers(t), Vec::<String>::new(), "temp files left in --tmp");
    }
    files(&report.scene_dir)
}

#[test]
fn stores_are_byte_identical_across_runs_budgets_and_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let input = koala_ply(tmp.path());
    let reference = build_with(&input, 1, 1 << 30, None);
    assert!(reference.len() > 5 && reference.contains_key("manifest.json"));
    // 4 MiB: the stream and the bins spill to disk, one brick in flight.
    for (threads, budget, t) in [(1, 1 << 30, None), (3, 4 << 20, Some(tmp.path())), (2, 64 << 20, None)] {
        let got = build_with(&input, threads, budget, t);
        assert_eq!(got.keys().collect::<Vec<_>>(), reference.keys().collect::<Vec<_>>());
        for (name, bytes) in &got {
            assert!(bytes == &reference[name], "{name} differs (threads {threads}, budget {budget})");
        }
    }
}

#[test]
fn build_matches_the_in_memory_voxelizer() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let input = koala_ply(dir.path());
    let opts = BuildOptions { resolution: 128, memory_budget: 4 << 20, ..Default::default() };
    let report = build_scene(&input, &store, &opts).unwrap();
    let (mesh, _) = read_mesh(&input).unwrap();
    assert_eq!(mesh.colors.len(), mesh.positions.len());
    let frame = choose_frame(&mesh, 128).unwrap();
    let (level0, stats) = voxelize(&mesh, &frame).unwrap();
    assert_eq!(
        (report.triangles, report.skipped_triangles),
        (stats.triangles + stats.skipped, stats.skipped)
    );
    let levels = build_levels(level0, 128);
    for level in &levels {
        for b in level {
            let on_disk = std::fs::read(report.scene_dir.join(format!("blocks/{}.vxb", b.key))).unwrap();
            assert!(on_disk == encode_block(&packed_block(b)), "block {} differs", b.key);
        }
    }
    assert_eq!(report.blocks as usize, levels.iter().map(Vec::len).sum::<usize>());
}

#[test]
fn temp_files_are_removed_after_errors_and_cancellation() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let tmp = dir.path().join("tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    let opts = |cancel: Option<Arc<AtomicBool>>| BuildOptions {
        resolution: 64,
        cancel,
        temp_dir: Some(tmp.clone()),
        ..Default::default()
    };
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n").unwrap();
    assert!(matches!(build_scene(&bad, &store, &opts(None)), Err(BuildError::Ingest(_))));
    let cancelled = build_scene(&koala(), &store, &opts(Some(Arc::new(AtomicBool::new(true)))));
    assert!(matches!(cancelled, Err(BuildError::Cancelled)), "{cancelled:?}");
    assert_eq!(leftovers(&tmp), Vec::<String>::new());
    assert_eq!(leftovers(&store), Vec::<String>::new());
    assert!(!store.join("koala").exists());
}

#[test]
fn colours_are_area_weighted_per_voxel() {
    // Two triangles in one voxel column: red with area 1, blue with area 3 (voxel units).
    let mesh = TriangleMesh {
        positions: vec![
            [0.1, 0.1, 0.5],
            [0.1 + 2f64.sqrt(), 0.1, 0.5],
            [0.1, 0.1 + 2f64.sqrt(), 0.5],
            [0.1, 0.1, 0.6],
            [0.1 + 6f64.sqrt(), 0.1, 0.6],
            [0.1, 0.1 + 6f64.sqrt(), 0.6],
        ],
        triangles: vec![[0, 1, 2], [3, 4, 5]],
        colors: vec![
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
        ],
    };
    let frame =
        voxstream_format::GridFrame { origin: [0.0; 3], voxel_size: 1.0, resolution: 64, units: None };
    let (blocks, _) = voxelize(&mesh, &frame).unwrap();
    let v = blocks[0].voxels.iter().find(|v| v.morton == 0).expect("voxel (0,0,0) is set");
    // Both triangles touch voxel (0,0,0), each weighted by its whole area: red 1, blue 3.
    let mean = v.color_sum.map(|c| c / v.color_weight);
    assert!((mean[0] - 0.25).abs() < 1e-4 && mean[1] == 0.0 && (mean[2] - 0.75).abs() < 1e-4, "{mean:?}");
    assert!((v.color_weight - 4.0).abs() < 1e-4, "{}", v.color_weight);
    // Without colours every weight is zero.
    let plain = TriangleMesh { colors: Vec::new(), ..mesh };
    let (blocks, _) = voxelize(&plain, &frame).unwrap();
    assert!(blocks.iter().flat_map(|b| &b.voxels).all(|v| v.color_weight == 0.0 && v.color_sum == [0.0; 3]));
}

#[test]
fn memory_budget_sizes_parse() {
    assert_eq!(parse_byte_size("1GiB").unwrap(), 1 << 30);
    assert_eq!(parse_byte_size("512M").unwrap(), 512 << 20);
    assert_eq!(parse_byte_size("64k").unwrap(), 64 << 10);
    assert_eq!(parse_byte_size("1048576").unwrap(), 1 << 20);
    assert_eq!(parse_byte_size("1.5G").unwrap(), 3 << 29);
    for bad in ["", "GiB", "12 parsecs", "-1G", "0"] {
        assert!(parse_byte_size(bad).is_err(), "{bad}");
    }
}
