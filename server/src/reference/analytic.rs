//! Analytic scenes for the AO tests and the benchmark: meshes generated in
//! code (so nothing external is needed) and the exact geometry they
//! tessellate, whose V is computed by a fine deterministic hemisphere
//! quadrature with analytic ray–sphere and ray–rectangle intersections (not
//! the BVH): a sphere on a plane, parallel plates, a lone sphere and a closed
//! room seen from inside.

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use crate::pipeline::read::TriangleMesh;
use crate::reference::{basis, falloff_weight};
use crate::render::CameraSpec;

/// A piece of exact geometry; both sides count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    Sphere {
        centre: DVec3,
        radius: f64,
    },
    /// The parallelogram corner + s·u + t·v, s, t in [0, 1].
    Rect {
        corner: DVec3,
        u: DVec3,
        v: DVec3,
    },
}

impl Shape {
    /// Distance along unit `dir` from `o` to the first intersection beyond `tmin`.
    pub fn intersect(&self, o: DVec3, dir: DVec3, tmin: f64) -> Option<f64> {
        match *self {
            Shape::Sphere { centre, radius } => {
                let oc = o - centre;
                let b = oc.dot(dir);
                let c = oc.length_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                [-b - s, -b + s].into_iter().find(|&t| t > tmin)
            }
            Shape::Rect { corner, u, v } => {
                let n = u.cross(v);
                let denom = n.dot(dir);
                if denom.abs() < 1e-300 {
                    return None;
                }
                let t = n.dot(corner - o) / denom;
                if t <= tmin {
                    return None;
                }
                let q = o + dir * t - corner;
                // Coordinates in the (u, v) basis.
                let (uu, uv, vv) = (u.dot(u), u.dot(v), v.dot(v));
                let (qu, qv) = (q.dot(u), q.dot(v));
                let det = uu * vv - uv * uv;
                let s = (qu * vv - qv * uv) / det;
                let r = (qv * uu - qu * uv) / det;
                ((0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&r)).then_some(t)
            }
        }
    }
}

/// Exact V(p, n) against `shapes` by midpoint quadrature of the
/// cosine-weighted hemisphere on an `m`×`m` grid of (u1, u2) cells
/// (u1 = sin²θ, u2 = φ / 2π: equal projected solid angle per cell).
pub fn exact_visibility(
    shapes: &[Shape],
    p: DVec3,
    n: DVec3,
    max_distance: f64,
    falloff: f64,
    m: u32,
) -> f64 {
    let n = n.normalize();
    let (t, b) = basis(n);
    let mut sum = 0.0;
    for i in 0..m {
        let u1 = (i as f64 + 0.5) / m as f64;
        let r = u1.sqrt();
        let z = (1.0 - u1).sqrt();
        for j in 0..m {
            let phi = std::f64::consts::TAU * (j as f64 + 0.5) / m as f64;
            let dir = t * (r * phi.cos()) + b * (r * phi.sin()) + n * z;
            let d = shapes.iter().filter_map(|s| s.intersect(p, dir, 1e-9)).fold(f64::INFINITY, f64::min);
            if d.is_finite() {
                sum += falloff_weight(d, max_distance, falloff);
            }
        }
    }
    1.0 - sum / (m as f64 * m as f64)
}

/// A scene with its exact geometry, its tessellation and a camera.
#[derive(Debug, Clone)]
pub struct AnalyticScene {
    pub name: &'static str,
    pub shapes: Vec<Shape>,
    pub mesh: TriangleMesh,
    pub camera: CameraSpec,
}

impl AnalyticScene {
    /// The same scene moved by `offset` (source units).
    pub fn translated(&self, offset: [f64; 3]) -> Self {
        let o = DVec3::from(offset);
        let mut s = self.clone();
        for p in &mut s.mesh.positions {
            *p = (DVec3::from(*p) + o).to_array();
        }
        for shape in &mut s.shapes {
            match shape {
                Shape::Sphere { centre, .. } => *centre += o,
                Shape::Rect { corner, .. } => *corner += o,
            }
        }
        s.camera.eye = (DVec3::from(s.camera.eye) + o).to_array();
        s.camera.target = (DVec3::from(s.camera.target) + o).to_array();
        s
    }

    /// Writes the mesh as an OBJ (17 significant digits: exact f64).
    pub fn write_obj(&self, path: &Path) -> std::io::Result<()> {
        let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
        for p in &self.mesh.positions {
            writeln!(out, "v {:?} {:?} {:?}", p[0], p[1], p[2])?;
        }
        for t in &self.mesh.triangles {
            writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
        }
        out.flush()
    }
}

/// Triangles wound so that their normal is u × v.
fn push_rect(mesh: &mut TriangleMesh, corner: DVec3, u: DVec3, v: DVec3, cells: u32) {
    let base = mesh.positions.len() as u32;
    for j in 0..=cells {
        for i in 0..=cells {
            let p = corner + u * (i as f64 / cells as f64) + v * (j as f64 / cells as f64);
            mesh.positions.push(p.to_array());
        }
    }
    let row = cells + 1;
    for j in 0..cells {
        for i in 0..cells {
            let a = base + j * row + i;
            mesh.triangles.push([a, a + 1, a + row + 1]);
            mesh.triangles.push([a, a + row + 1, a + row]);
        }
    }
}

fn push_sphere(mesh: &mut TriangleMesh, centre: DVec3, radius: f64) {
    let (rings, segments) = (48u32, 96u32);
    let base = mesh.positions.len() as u32;
    for i in 0..=rings {
        let theta = std::f64::consts::PI * i as f64 / rings as f64;
        for j in 0..segments {
            let phi = std::f64::consts::TAU * j as f64 / segments as f64;
            let d = DVec3::new(theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin());
            mesh.positions.push((centre + d * radius).to_array());
        }
    }
    for i in 0..rings {
        for j in 0..segments {
            let a = base + i * segments + j;
            let b = base + i * segments + (j + 1) % segments;
            let (c, d) = (a + segments, b + segments);
            // Counter-clockwise seen from outside: normals point outwards.
            mesh.triangles.push([a, b, c]);
            mesh.triangles.push([b, d, c]);
        }
    }
}

fn camera(eye: [f64; 3], target: [f64; 3]) -> CameraSpec {
    CameraSpec { eye, target, up: [0.0, 1.0, 0.0], fov_y_deg: 45.0, near: 0.05, far: 50.0 }
}

/// A scene of `shapes`, tessellated (rectangles 8×8 cells, spheres 48×96).
pub fn scene_from_shapes(name: &'static str, shapes: Vec<Shape>, camera: CameraSpec) -> AnalyticScene {
    let mut mesh = TriangleMesh::default();
    for s in &shapes {
        match *s {
            Shape::Sphere { centre, radius } => push_sphere(&mut mesh, centre, radius),
            Shape::Rect { corner, u, v } => push_rect(&mut mesh, corner, u, v, 8),
        }
    }
    AnalyticScene { name, shapes, mesh, camera }
}

fn rect(corner: [f64; 3], u: [f64; 3], v: [f64; 3]) -> Shape {
    Shape::Rect { corner: corner.into(), u: u.into(), v: v.into() }
}

/// The four scenes, each about 2–4 units across.
pub fn scenes() -> Vec<AnalyticScene> {
    let sphere = |c: [f64; 3], r: f64| Shape::Sphere { centre: c.into(), radius: r };
    vec![
        scene_from_shapes(
            "sphere_on_plane",
            vec![rect([-2.0, 0.0, -2.0], [0.0, 0.0, 4.0], [4.0, 0.0, 0.0]), sphere([0.0, 0.5, 0.0], 0.5)],
            camera([1.6, 1.3, 1.9], [0.0, 0.25, 0.0]),
        ),
        scene_from_shapes(
            "parallel_plates",
            vec![
                rect([-1.5, 0.0, -1.5], [0.0, 0.0, 3.0], [3.0, 0.0, 0.0]),
                rect([-1.5, 0.2, -1.5], [0.0, 0.0, 3.0], [3.0, 0.0, 0.0]),
            ],
            // Inside the gap, looking up at the upper plate from near the lower one.
            camera([0.0, 0.04, 0.0], [0.6, 0.2, 0.3]),
        ),
        scene_from_shapes(
            "lone_sphere",
            vec![sphere([0.0, 0.0, 0.0], 0.8)],
            camera([0.4, 0.6, 2.6], [0.0, 0.0, 0.0]),
        ),
        scene_from_shapes(
            "closed_room",
            {
                let (x, y, z) = (2.0, 1.5, 2.5);
                vec![
                    rect([0.0, 0.0, 0.0], [0.0, 0.0, z], [x, 0.0, 0.0]),
                    rect([0.0, y, 0.0], [x, 0.0, 0.0], [0.0, 0.0, z]),
                    rect([0.0, 0.0, 0.0], [x, 0.0, 0.0], [0.0, y, 0.0]),
                    rect([0.0, 0.0, z], [0.0, y, 0.0], [x, 0.0, 0.0]),
                    rect([0.0, 0.0, 0.0], [0.0, y, 0.0], [0.0, 0.0, z]),
                    rect([x, 0.0, 0.0], [0.0, 0.0, z], [0.0, y, 0.0]),
                ]
            },
            camera([1.7, 1.15, 2.3], [0.4, 0.35, 0.3]),
        ),
    ]
}

/// Writes the scene's mesh beside `store` and builds it into `store` at
/// `resolution`; returns the scene directory.
pub fn build(scene: &AnalyticScene, store: &Path, resolution: u32) -> anyhow::Result<std::path::PathBuf> {
    build_with_field(scene, store, resolution, Some(Default::default()))
}

/// [`build`] with the given AO field options (`None`: no field).
pub fn build_with_field(
    scene: &AnalyticScene,
    store: &Path,
    resolution: u32,
    ao_field: Option<crate::pipeline::aofield::AoFieldOptions>,
) -> anyhow::Result<std::path::PathBuf> {
    std::fs::create_dir_all(store)?;
    let mesh = store.join(format!("{}.obj", scene.name));
    scene.write_obj(&mesh)?;
    let options = crate::pipeline::BuildOptions {
        resolution: crate::pipeline::Resolution::Explicit(resolution),
        name: Some(scene.name.replace('_', "-")),
        ao_field,
        ..crate::pipeline::BuildOptions::default()
    };
    Ok(crate::pipeline::build_scene(&mesh, store, &options)?.scene_dir)
}

/// The exact V at every surface pixel of a render (its positions and normals,
/// its R and λ), NaN elsewhere; `m`² quadrature directions per pixel.
pub fn exact_image(shapes: &[Shape], out: &crate::render::RenderOutput, m: u32) -> Vec<f32> {
    use rayon::prelude::*;
    let (r, lambda) = (out.info.ao.max_distance, out.info.ao.falloff);
    out.position
        .par_iter()
        .zip(&out.normal)
        .map(|(p, n)| {
            let p = DVec3::from(*p);
            let n = glam::Vec3::from(*n).as_dvec3();
            if p.is_finite() && n.is_finite() {
                exact_visibility(shapes, p, n, r, lambda, m) as f32
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// Per-pixel error of an AO image against exact values, over pixels where both are defined.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExactError {
    pub pixels: usize,
    /// Mean |ao − exact|: the goal's measure ("within 0.03 of the exact value", on average).
    pub mae: f64,
    /// Mean (ao − exact).
    pub bias: f64,
    pub rmse: f64,
    /// 95th percentile of |ao − exact|.
    pub p95: f64,
    pub max_abs: f64,
}

pub fn exact_error(ao: &[f32], exact: &[f32]) -> ExactError {
    let mut d: Vec<f64> = ao
        .iter()
        .zip(exact)
        .filter(|(a, e)| a.is_finite() && e.is_finite())
        .map(|(a, e)| *a as f64 - *e as f64)
        .collect();
    let n = d.len().max(1) as f64;
    let bias = d.iter().sum::<f64>() / n;
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
    d.iter_mut().for_each(|x| *x = x.abs());
    d.sort_by(f64::total_cmp);
    let mae = d.iter().sum::<f64>() / n;
    let p95 =
        d.get(((d.len() as f64 * 0.95) as usize).min(d.len().saturating_sub(1))).copied().unwrap_or(f64::NAN);
    ExactError { pixels: d.len(), mae, bias, rmse, p95, max_abs: d.last().copied().unwrap_or(f64::NAN) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_values_of_known_configurations() {
        let (r, lambda) = (1.0, 1.0);
        // Nothing in reach: fully open.
        let plane = [rect([-10.0, 0.0, -10.0], [0.0, 0.0, 20.0], [20.0, 0.0, 0.0])];
        let v = exact_visibility(&plane, DVec3::new(0.0, 0.5, 0.0), DVec3::Y, r, lambda, 64);
        assert!((v - 1.0).abs() < 1e-12);
        // Facing an infinite-ish plane at height h along the normal: d = h / cos θ;
        // with λ = 0 and R ≫ h, w = 1 everywhere: V = 0.
        let v = exact_visibility(&plane, DVec3::new(0.0, 0.5, 0.0), -DVec3::Y, 100.0, 0.0, 64);
        assert!(v.abs() < 1e-9, "{v}");
        // Outside a convex sphere, looking away from it: open.
        let s = [Shape::Sphere { centre: DVec3::ZERO, radius: 1.0 }];
        let v = exact_visibility(&s, DVec3::new(0.0, 1.0 + 1e-6, 0.0), DVec3::Y, r, lambda, 64);
        assert!((v - 1.0).abs() < 1e-12);
        // Plates at distance h, λ = 0, R = 2h: occluded where cos θ ≥ 1/2, i.e.
        // sin²θ ≤ 3/4: V = 1/4 (up to the plate's finite size: 20 ≫ 2h).
        let v = exact_visibility(&plane, DVec3::new(0.0, -0.5, 0.0), DVec3::Y, 1.0, 0.0, 256);
        assert!((v - 0.25).abs() < 2e-3, "{v}");
    }

    #[test]
    fn scenes_tessellate_their_shapes() {
        for s in scenes() {
            assert!(!s.mesh.triangles.is_empty(), "{}", s.name);
            s.camera.validate().unwrap();
            // Every vertex lies on one of the shapes (within tessellation).
            for p in &s.mesh.positions {
                let p = DVec3::from(*p);
                let on = s.shapes.iter().any(|sh| match *sh {
                    Shape::Sphere { centre, radius } => ((p - centre).length() - radius).abs() < 1e-9,
                    Shape::Rect { corner, u, v } => u.cross(v).normalize().dot(p - corner).abs() < 1e-9,
                });
                assert!(on, "{}: {p}", s.name);
            }
        }
    }
}
