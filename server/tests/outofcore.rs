//! The out-of-core build (chunked stream → spilled bins → parallel blocks →
//! streaming pyramid → writer): byte-identical stores whatever the memory
//! budget and thread count, the same files as the in-memory reference
//! (voxelize + `build_levels` + `write_scene`) for every topology, with
//! colours, area-weighted colours, the budget rule, and temp files gone
//! after success, error and cancellation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use voxstream::pipeline::progress::ProgressSink;
use voxstream::pipeline::pyramid::build_levels;
use voxstream::pipeline::read::{TriangleMesh, read_mesh};
use voxstream::pipeline::stream::Bounds;
use voxstream::pipeline::voxelize::{
    EdgeHistogram, MAX_RESOLUTION, Topology, choose_frame, choose_resolution, voxelize, voxelize_reporting,
};
use voxstream::pipeline::write::{SceneContent, write_scene};
use voxstream::pipeline::{BuildError, BuildOptions, MemoryPlan, Resolution, build_scene, parse_byte_size};
use voxstream_format::SourceInfo;

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
        resolution: Resolution::Explicit(128),
        memory_budget: budget,
        temp_dir: tmp.map(Path::to_path_buf),
        // With the (opt-in) AO field, so its column is compared too.
        ao_field: Some(Default::default()),
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
    // The manifest and packs (holding blocks and pages): every one compared below.
    assert!(reference.len() >= 2 && reference.contains_key("manifest.json"), "{:?}", reference.keys());
    assert!(reference.keys().any(|n| n.starts_with("packs/")));
    assert!(!reference.keys().any(|n| n.starts_with("pages/")), "pages live in packs");
    // The AO field is on, so its column is part of what is compared.
    assert!(String::from_utf8_lossy(&reference["manifest.json"]).contains("\"ao_field\""));
    // The smallest budget: the stream and the bins spill to disk, the bin
    // buffers flush often, one brick in flight, small batches.
    // The AO field (on, 128³ cells) needs its peak beside the smallest plan.
    let least = MemoryPlan::minimum_budget(128) + voxstream::pipeline::aofield::peak_bytes(128);
    for (threads, budget, t) in
        [(1, 1 << 30, None), (3, least, Some(tmp.path())), (2, least + (64 << 20), None)]
    {
        let got = build_with(&input, threads, budget, t);
        assert_eq!(got.keys().collect::<Vec<_>>(), reference.keys().collect::<Vec<_>>());
        for (name, bytes) in &got {
            assert!(bytes == &reference[name], "{name} differs (threads {threads}, budget {budget})");
        }
    }
}

#[test]
fn a_paged_ply_vertex_table_builds_the_same_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let input = koala_ply(tmp.path());
    let build = |vertex_memory: Option<u64>| {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("store");
        let opts = BuildOptions {
            resolution: Resolution::Explicit(128),
            ply_vertex_memory: vertex_memory,
            ..Default::default()
        };
        let report = build_scene(&input, &store, &opts).unwrap();
        assert_eq!(leftovers(&store), Vec::<String>::new(), "temp files left in the store");
        files(&report.scene_dir)
    };
    let reference = build(None);
    assert!(
        reference.contains_key("manifest.json") && reference.keys().any(|k| k.contains("packs")),
        "{:?}",
        reference.keys()
    );
    // One page of cache (faces across pages are read one by one) and 4 of its 13 pages (evictions).
    for vertex_memory in [1, 480 << 10] {
        let got = build(Some(vertex_memory));
        assert_eq!(got.keys().collect::<Vec<_>>(), reference.keys().collect::<Vec<_>>());
        for (name, bytes) in &got {
            assert!(
                bytes == &reference[name],
                "{name} differs with the vertex table paged at {vertex_memory}"
            );
        }
    }
    // Negative control: a paged build of a slightly different mesh differs.
    let mut bytes = std::fs::read(&input).unwrap();
    let header = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    bytes[header + 3] ^= 0x40; // the exponent of vertex 0's x
    std::fs::write(&input, &bytes).unwrap();
    let other = build(Some(1));
    assert!(other.iter().any(|(name, b)| reference.get(name) != Some(b)));
}

/// The in-memory reference: every block voxelized at once, `build_levels`, `write_scene`.
fn reference_scene(input: &Path, resolution: u32, topology: Topology, store: &Path, id: &str) -> PathBuf {
    let (mesh, format) = read_mesh(input).unwrap();
    let frame = choose_frame(&mesh, resolution).unwrap();
    // The choice the build records: the same median, from the same valid triangles.
    let (mut edges, mut bounds) = (EdgeHistogram::default(), Bounds::EMPTY);
    for t in 0..mesh.triangles.len() {
        let tri = mesh.triangle(t);
        if voxstream::pipeline::voxelize::valid_triangle(&tri) {
            edges.add_triangle(&tri);
            bounds.add_triangle(&tri);
        }
    }
    let (same_frame, resolution_choice) =
        choose_resolution(&bounds, Resolution::Explicit(resolution), edges.median(), MAX_RESOLUTION, 0)
            .unwrap();
    assert_eq!(same_frame, frame);
    let (level0, stats) = voxelize_reporting(&mesh, &frame, topology, &ProgressSink::new(&|_| {})).unwrap();
    let levels = build_levels(level0, resolution);
    let content = SceneContent {
        name: id.to_string(),
        source: SourceInfo {
            file: input.file_name().unwrap().to_str().unwrap().to_string(),
            format: format.to_string(),
            triangles: stats.triangles + stats.skipped,
            skipped_triangles: stats.skipped,
        },
        grid: frame,
        resolution_choice,
        levels: &levels,
    };
    write_scene(store, id, &content).unwrap();
    store.join(id)
}

/// A sphere of radius 1 tessellated into `n` × 2n quads (two triangles each), as ASCII PLY.
fn sphere_ply(dir: &Path, n: usize) -> PathBuf {
    let (rows, cols) = (n, 2 * n);
    let mut verts = Vec::new();
    for i in 0..=rows {
        let theta = std::f64::consts::PI * i as f64 / rows as f64;
        for j in 0..cols {
            let phi = std::f64::consts::TAU * j as f64 / cols as f64;
            verts.push([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()]);
        }
    }
    let mut faces = Vec::new();
    for i in 0..rows {
        for j in 0..cols {
            let (a, b) = (i * cols + j, i * cols + (j + 1) % cols);
            let (c, d) = (a + cols, b + cols);
            faces.push([a, b, d]);
            faces.push([a, d, c]);
        }
    }
    let mut out = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    for v in &verts {
        out += &format!("{} {} {}\n", v[0], v[1], v[2]);
    }
    for f in &faces {
        out += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
    }
    let path = dir.join(format!("sphere-{n}.ply"));
    std::fs::write(&path, out).unwrap();
    path
}

/// Every pack is exactly the concatenation of the blocks that name it (no gap,
/// no overlap, nothing after the last), each block's range is the block its
/// hash names, and no pack file is left that no page names.
fn check_packs(store: &Path, id: &str) {
    let scene = voxstream::store::open_scene(store, id).unwrap();
    let mut ranges: BTreeMap<String, Vec<(u64, u64)>> = BTreeMap::new();
    for e in scene.blocks() {
        let r = scene
            .index
            .read()
            .pack_range(&e.key)
            .unwrap_or_else(|| panic!("{id}: block {} is not packed", e.key));
        ranges.entry(r.pack.hash.clone()).or_default().push((r.offset, r.end()));
        let bytes = scene.read_block(&e).unwrap();
        assert_eq!(voxstream_format::decode_block(&bytes).unwrap().key, e.key);
    }
    for (page, range) in scene.index.read().loaded_pages() {
        let r = range.unwrap_or_else(|| panic!("{id}: page {} is not packed", page.root));
        ranges.entry(r.pack.hash.clone()).or_default().push((r.offset, r.end()));
    }
    let on_disk: Vec<String> = std::fs::read_dir(scene.dir().join("packs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    let mut named: Vec<String> = ranges.keys().map(|h| format!("{h}.vxp")).collect();
    let mut on_disk_sorted = on_disk.clone();
    on_disk_sorted.sort();
    named.sort();
    assert_eq!(on_disk_sorted, named, "{id}: packs on disk and packs named");
    for (hash, mut r) in ranges {
        r.sort();
        let bytes = std::fs::read(scene.dir().join(format!("packs/{hash}.vxp"))).unwrap();
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), hash, "{id}: a pack is named by its hash");
        assert_eq!(r[0].0, 0, "{id}");
        assert!(r.windows(2).all(|w| w[0].1 == w[1].0), "{id}: ranges tile the pack");
        assert_eq!(r.last().unwrap().1, bytes.len() as u64, "{id}: nothing after the last block or page");
    }
}

/// Fails if the streaming pyramid or the block writer differs from the
/// in-memory reference in any byte of any block or of the manifest: a sum in
/// another order, a wrong octant, an error bound, a dropped or extra block,
/// a level's totals.
#[test]
fn streaming_build_matches_the_in_memory_reference() {
    let dir = tempfile::tempdir().unwrap();
    let coloured = koala_ply(dir.path());
    let sphere = sphere_ply(dir.path(), 60);
    let cases = [
        (coloured.clone(), 128, Topology::Conservative),
        (coloured.clone(), 128, Topology::Separating26),
        (coloured, 256, Topology::Separating6),
        (koala(), 256, Topology::Conservative),
        (sphere.clone(), 512, Topology::Conservative),
        (sphere, 64, Topology::Separating26),
    ];
    for (k, (input, resolution, topology)) in cases.into_iter().enumerate() {
        let id = format!("case{k}");
        let reference = reference_scene(&input, resolution, topology, &dir.path().join("reference"), &id);
        // The smallest budget: every store spills, the writer flushes often, small batches.
        let opts = BuildOptions {
            resolution: Resolution::Explicit(resolution),
            topology,
            name: Some(id.clone()),
            memory_budget: MemoryPlan::minimum_budget(resolution),
            // The in-memory reference has no AO field; the field's determinism is
            // `stores_are_byte_identical_across_runs_budgets_and_threads` (field on).
            ao_field: None,
            ..Default::default()
        };
        let report = build_scene(&input, &dir.path().join("streamed"), &opts).unwrap();
        let (want, got) = (files(&reference), files(&report.scene_dir));
        assert!(want.len() >= 2 && want.contains_key("manifest.json"), "{id}: {:?}", want.keys());
        assert_eq!(got.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>(), "{id}");
        for (name, bytes) in &got {
            assert!(
                bytes == &want[name],
                "{id} ({}, {resolution}, {topology:?}): {name} differs",
                input.display()
            );
        }
        // Few objects: the manifest and a pack per PACK_MAX_ITEMS items (blocks and pages; the
        // last page layers close a few small packs at the end).
        let packs = want.keys().filter(|n| n.starts_with("packs/")).count();
        assert_eq!(want.len(), 1 + packs, "{id}: {:?}", want.keys());
        let blocks = report.blocks as usize;
        let scene = voxstream::store::open_scene(&dir.path().join("reference"), &id).unwrap();
        let full =
            (blocks + scene.index.read().pages_loaded()).div_ceil(voxstream::pipeline::write::PACK_MAX_ITEMS);
        assert!((full..=full + 3).contains(&packs), "{id}: {packs} packs for {blocks} blocks");
        if resolution >= 256 {
            assert!(4 * want.len() <= blocks, "{id}: {} files for {blocks} blocks", want.len());
        }
        check_packs(&dir.path().join("reference"), &id);
        if resolution > 64 {
            assert!(scene.index.read().pages_loaded() > 0, "{id}: pages (inside the packs) are compared too");
        }
    }
}

/// Fails if a budget below the smallest one is accepted, or if the message
/// does not name the smallest budget (which must itself be accepted).
#[test]
fn too_small_a_budget_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let least = MemoryPlan::minimum_budget(65536);
    // 65536 has 11 levels: a front of 11 full blocks is over 100 MiB.
    assert!(least > 100 << 20 && least < 256 << 20, "{least}");
    assert!(MemoryPlan::minimum_budget(4096) < 128 << 20, "the 4096 test below must be possible");
    assert!(MemoryPlan::minimum_budget(128) < MemoryPlan::minimum_budget(4096));
    // The input does not exist: the budget is checked before anything is read.
    let missing = dir.path().join("missing.ply");
    let opts = BuildOptions {
        resolution: Resolution::Explicit(65536),
        memory_budget: 16 << 20,
        ..Default::default()
    };
    let err = build_scene(&missing, dir.path(), &opts).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, BuildError::BudgetTooSmall { .. }), "{text}");
    let named = format!("at least {} MiB is needed", least.div_ceil(1 << 20));
    assert!(text.contains("too small for resolution 65536") && text.contains(&named), "{text}");
    assert!(MemoryPlan::new(least, 65536).is_ok() && MemoryPlan::new(least - 1, 65536).is_err());
}

#[test]
fn temp_files_are_removed_after_errors_and_cancellation() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let tmp = dir.path().join("tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    let opts = |cancel: Option<Arc<AtomicBool>>| BuildOptions {
        resolution: Resolution::Explicit(64),
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
