//! The conservative voxelizer against an independent brute force: exact
//! clipping of the triangle by each voxel's closed cube (seed 003 §3.1).

use std::collections::BTreeSet;

use rand::{Rng, SeedableRng, rngs::StdRng};
use voxstream::pipeline::pyramid::local_position;
use voxstream::pipeline::read::TriangleMesh;
use voxstream::pipeline::voxelize::{self, BuildVoxel};
use voxstream_format::{BLOCK_SIZE, GridFrame};

const RES: u32 = 128; // 2×2×2 blocks, so triangles cross block boundaries

fn unit_frame() -> GridFrame {
    GridFrame { origin: [0.0; 3], voxel_size: 1.0, resolution: RES, units: None }
}

/// Sutherland–Hodgman clip of a polygon by the closed cube [c, c+1]³; true if anything remains.
fn clip_touches(tri: &[[f64; 3]; 3], c: [i64; 3]) -> bool {
    const EPS: f64 = 1e-12;
    let mut poly: Vec<[f64; 3]> = tri.to_vec();
    for axis in 0..3 {
        for (bound, keep_above) in [(c[axis] as f64, true), (c[axis] as f64 + 1.0, false)] {
            let inside =
                |p: &[f64; 3]| if keep_above { p[axis] >= bound - EPS } else { p[axis] <= bound + EPS };
            let mut out = Vec::new();
            for i in 0..poly.len() {
                let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                let (ia, ib) = (inside(&a), inside(&b));
                if ia {
                    out.push(a);
                }
                if ia != ib {
                    let t = (bound - a[axis]) / (b[axis] - a[axis]);
                    out.push(std::array::from_fn(|k| a[k] + t * (b[k] - a[k])));
                }
            }
            poly = out;
            if poly.is_empty() {
                return false;
            }
        }
    }
    true
}

/// Distance from a point to a triangle (Ericson, Real-Time Collision Detection §5.1.5).
fn point_triangle_distance(p: [f64; 3], t: &[[f64; 3]; 3]) -> f64 {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (a, b, c) = (t[0], t[1], t[2]);
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let at = |q: [f64; 3]| dot(sub(p, q), sub(p, q)).sqrt();
    let lerp = |o: [f64; 3], d: [f64; 3], s: f64| [o[0] + s * d[0], o[1] + s * d[1], o[2] + s * d[2]];
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return at(a);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return at(b);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return at(lerp(a, ab, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return at(c);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return at(lerp(a, ac, d2 / (d2 - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return at(lerp(b, sub(c, b), w));
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    at([a[0] + ab[0] * v + ac[0] * w, a[1] + ab[1] * v + ac[1] * w, a[2] + ab[2] * v + ac[2] * w])
}

fn is_degenerate(t: &[[f64; 3]; 3]) -> bool {
    let e1 = [t[1][0] - t[0][0], t[1][1] - t[0][1], t[1][2] - t[0][2]];
    let e2 = [t[2][0] - t[0][0], t[2][1] - t[0][1], t[2][2] - t[0][2]];
    let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
    n == [0.0; 3]
}

fn random_mesh(rng: &mut StdRng) -> TriangleMesh {
    let mut mesh = TriangleMesh::default();
    for _ in 0..40 {
        let kind = rng.random_range(0..4);
        let centre: [f64; 3] = std::array::from_fn(|_| rng.random_range(2.0..RES as f64 - 2.0));
        let size = match kind {
            0 => 1.5,
            1 => 6.0,
            _ => 40.0,
        };
        let base = mesh.positions.len() as u32;
        for _ in 0..3 {
            let mut p: [f64; 3] = std::array::from_fn(|a| {
                (centre[a] + rng.random_range(-size..size)).clamp(0.0, RES as f64 - 1e-3)
            });
            if kind == 3 {
                // Axis-aligned on an integer plane: every contact is a touching case.
                p[2] = centre[2].floor();
            }
            mesh.positions.push(p);
        }
        mesh.triangles.push([base, base + 1, base + 2]);
    }
    mesh
}

fn global_voxels(blocks: &[voxstream::pipeline::voxelize::SparseBlock]) -> BTreeSet<[i64; 3]> {
    let mut set = BTreeSet::new();
    for b in blocks {
        assert!(
            b.voxels.windows(2).all(|w| w[0].morton < w[1].morton),
            "block {} not in Morton order",
            b.key
        );
        for v in &b.voxels {
            let v: &BuildVoxel = v;
            let p = local_position(v);
            set.insert(std::array::from_fn(|a| (b.key.coord()[a] * BLOCK_SIZE + p[a]) as i64));
        }
    }
    set
}

#[test]
fn conservative_coverage_matches_brute_force() {
    let frame = unit_frame();
    for seed in 0..12 {
        let mut rng = StdRng::seed_from_u64(seed);
        let mesh = random_mesh(&mut rng);
        let (blocks, stats) = voxelize::voxelize(&mesh, &frame).unwrap();
        assert_eq!(stats.triangles + stats.skipped, 40);
        let got = global_voxels(&blocks);

        // Every voxel the brute force finds touched is present.
        let mut expected = BTreeSet::new();
        for t in 0..mesh.triangles.len() {
            let tri = mesh.triangle(t);
            if is_degenerate(&tri) {
                continue; // skipped by design, and counted above
            }
            for z in 0..RES as i64 {
                let zs = tri.iter().map(|p| p[2]);
                if zs.clone().fold(f64::INFINITY, f64::min) > z as f64 + 1.0
                    || zs.fold(f64::NEG_INFINITY, f64::max) < z as f64
                {
                    continue;
                }
                for y in 0..RES as i64 {
                    for x in 0..RES as i64 {
                        if clip_touches(&tri, [x, y, z]) {
                            expected.insert([x, y, z]);
                        }
                    }
                }
            }
        }
        let missing: Vec<_> = expected.difference(&got).take(5).collect();
        assert!(
            missing.is_empty(),
            "seed {seed}: {} voxels missing, e.g. {missing:?}",
            expected.difference(&got).count()
        );

        // Nothing is farther than half a voxel diagonal (touching) from some triangle.
        let half_diag = 3f64.sqrt() / 2.0 + 1e-6;
        for v in &got {
            let centre = v.map(|c| c as f64 + 0.5);
            let d = (0..mesh.triangles.len())
                .map(|t| point_triangle_distance(centre, &mesh.triangle(t)))
                .fold(f64::INFINITY, f64::min);
            assert!(d <= half_diag, "seed {seed}: voxel {v:?} is {d} voxels from every triangle");
        }
        assert!(got.len() >= expected.len());
    }
}

#[test]
fn degenerate_and_non_finite_triangles_are_skipped_and_counted() {
    let mesh = TriangleMesh {
        positions: vec![
            [1.0, 1.0, 1.0],
            [5.0, 1.0, 1.0],
            [1.0, 5.0, 1.0],
            [f64::NAN, 0.0, 0.0],
            [9.0, 1.0, 1.0],
        ],
        triangles: vec![[0, 1, 2], [0, 1, 3], [0, 1, 4], [2, 2, 2]],
        ..Default::default()
    };
    let (_, stats) = voxelize::voxelize(&mesh, &unit_frame()).unwrap();
    assert_eq!((stats.triangles, stats.skipped), (1, 3));
    let only_bad = TriangleMesh {
        positions: mesh.positions.clone(),
        triangles: vec![[0, 1, 3], [2, 2, 2]],
        ..Default::default()
    };
    assert!(matches!(
        voxelize::voxelize(&only_bad, &unit_frame()),
        Err(voxelize::VoxelizeError::NoValidTriangle { skipped: 2 })
    ));
    assert!(voxelize::choose_frame(&only_bad, 512).is_err());
    assert!(voxelize::choose_frame(&mesh, 500).is_err());
}
