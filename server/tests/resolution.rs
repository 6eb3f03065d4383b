//! Resolution matched to the scan: `auto` picks the power of two whose voxel
//! is closest to the median triangle edge, `--voxel-size` gives exactly that
//! voxel, and the build reports what it chose and why.

use std::path::{Path, PathBuf};

use voxstream::pipeline::stream::Bounds;
use voxstream::pipeline::voxelize::{EdgeHistogram, MAX_RESOLUTION, choose_resolution};
use voxstream::pipeline::{BuildOptions, Resolution, build_scene};

/// A strip of `n` squares of side 1/n along x (two triangles each): two of
/// every three edges are 1/n long, so the median edge is 1/n and the extent 1.
fn strip(n: usize) -> Vec<[[f64; 3]; 3]> {
    let h = 1.0 / n as f64;
    (0..n)
        .flat_map(|i| {
            let x = i as f64 * h;
            [
                [[x, 0.0, 0.0], [x + h, 0.0, 0.0], [x + h, h, 0.0]],
                [[x, 0.0, 0.0], [x + h, h, 0.0], [x, h, 0.0]],
            ]
        })
        .collect()
}

/// A unit sphere of `n` × 2n quads (two triangles each).
fn sphere(n: usize) -> Vec<[[f64; 3]; 3]> {
    let p = |i: usize, j: usize| {
        let (t, f) =
            (std::f64::consts::PI * i as f64 / n as f64, std::f64::consts::TAU * j as f64 / (2 * n) as f64);
        [t.sin() * f.cos(), t.sin() * f.sin(), t.cos()]
    };
    let mut out = Vec::new();
    for i in 0..n {
        for j in 0..2 * n {
            let (a, b, c, d) = (p(i, j), p(i, j + 1), p(i + 1, j), p(i + 1, j + 1));
            // Skip the zero-area triangles at the poles, as the reader's validity check would.
            if i != 0 {
                out.push([a, b, d]);
            }
            if i != n - 1 {
                out.push([a, d, c]);
            }
        }
    }
    out
}

fn auto_choice(tris: &[[[f64; 3]; 3]]) -> (u32, f64) {
    let mut hist = EdgeHistogram::default();
    let mut bounds = Bounds::EMPTY;
    for t in tris {
        hist.add_triangle(t);
        bounds.add_triangle(t);
    }
    let (frame, choice) =
        choose_resolution(&bounds, Resolution::Auto, hist.median(), MAX_RESOLUTION, 0).unwrap();
    assert_eq!(frame.resolution, choice.resolution);
    assert_eq!(choice.mode, "auto");
    assert!(choice.reason.contains("median triangle edge"), "{}", choice.reason);
    (choice.resolution, choice.median_edge.unwrap())
}

/// Fails if auto rounds the wrong way, misses the clamp to [64, 65536], or
/// the histogram's median is off by more than its bin.
#[test]
fn auto_picks_the_power_of_two_closest_to_the_median_edge_of_a_strip() {
    // log2(n) rounds to: 4.3 → 64 (clamped), 6.6 → 128, 7.2 → 128, 8.2 → 256,
    // 9.5 - 0.05 → 512, 11.3 → 2048, 17.6 → 65536 (clamped).
    for (n, want) in
        [(20, 64), (100, 128), (150, 128), (300, 256), (700, 512), (2500, 2048), (200_000, 65536)]
    {
        let (got, median) = auto_choice(&strip(n));
        assert_eq!(got, want, "{n} squares");
        let h = 1.0 / n as f64;
        assert!((median / h).log2().abs() < 1.0 / 32.0, "median {median} vs edge {h}");
    }
}

/// The same on spheres, against the exact median of every edge (sorted here,
/// not binned): fails if the histogram or the rounding is wrong.
#[test]
fn auto_matches_sphere_tessellations() {
    let mut seen = Vec::new();
    for n in [90, 180, 360, 720] {
        let tris = sphere(n);
        let mut edges: Vec<f64> = tris
            .iter()
            .flat_map(|t| {
                [(0, 1), (1, 2), (2, 0)]
                    .map(|(a, b)| (0..3).map(|k| (t[a][k] - t[b][k]).powi(2)).sum::<f64>().sqrt())
            })
            .collect();
        edges.sort_by(f64::total_cmp);
        let median = edges[(edges.len() - 1) / 2];
        let cube = 2.0 * (1.0 + 1e-6);
        let ideal = (cube / median).log2();
        // Far enough from a tie that the histogram's 1/64-octave bins cannot flip it.
        assert!((ideal - ideal.round()).abs() < 0.45, "n = {n}: log2 {ideal} is too close to a tie");
        let want = (1u32 << ideal.round() as u32).clamp(64, MAX_RESOLUTION);
        let (got, measured) = auto_choice(&tris);
        assert_eq!(got, want, "sphere n = {n}: exact median {median}, measured {measured}");
        seen.push(got);
    }
    seen.dedup();
    assert!(seen.len() >= 3, "the tessellations should span several powers of two: {seen:?}");
}

fn write_obj(dir: &Path, name: &str, tris: &[[[f64; 3]; 3]]) -> PathBuf {
    let mut s = String::new();
    for t in tris {
        for v in t {
            s += &format!("v {} {} {}\n", v[0], v[1], v[2]);
        }
    }
    for i in 0..tris.len() {
        s += &format!("f {} {} {}\n", 3 * i + 1, 3 * i + 2, 3 * i + 3);
    }
    let path = dir.join(name);
    std::fs::write(&path, s).unwrap();
    path
}

/// Fails if the build ignores auto, the voxel size, or does not report them.
#[test]
fn builds_use_and_report_the_choice() {
    let dir = tempfile::tempdir().unwrap();
    let input = write_obj(dir.path(), "strip.obj", &strip(300));
    let store = dir.path().join("store");
    // The default is auto.
    let report = build_scene(&input, &store, &BuildOptions::default()).unwrap();
    assert_eq!((report.resolution_choice.mode.as_str(), report.resolution_choice.resolution), ("auto", 256));
    let manifest = voxstream::store::open_scene(&store, "strip").unwrap().manifest;
    assert_eq!(manifest.grid.resolution, 256);

    // An exact voxel of 0.01 over an extent of 1: 101 voxels → 128, the cube grows to 1.28.
    let opts = BuildOptions { resolution: Resolution::VoxelSize(0.01), ..Default::default() };
    let report = build_scene(&input, &store, &opts).unwrap();
    let choice = &report.resolution_choice;
    assert_eq!((choice.mode.as_str(), choice.resolution, choice.voxel_size), ("voxel-size", 128, 0.01));
    let manifest = voxstream::store::open_scene(&store, "strip").unwrap().manifest;
    assert_eq!((manifest.grid.resolution, manifest.grid.voxel_size), (128, 0.01));
    assert_eq!(manifest.grid.origin, [0.0; 3], "the origin stays at the bounds' minimum");

    // Explicit still works, and says so.
    let opts = BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() };
    let report = build_scene(&input, &store, &opts).unwrap();
    assert_eq!(
        (report.resolution_choice.mode.as_str(), report.resolution_choice.resolution),
        ("explicit", 64)
    );

    // A voxel size finer than 65536 voxels across is refused with the smallest that works.
    let opts = BuildOptions { resolution: Resolution::VoxelSize(1e-6), ..Default::default() };
    let err = build_scene(&input, &store, &opts).unwrap_err().to_string();
    assert!(err.contains("voxel size") && err.contains("at least"), "{err}");
}
