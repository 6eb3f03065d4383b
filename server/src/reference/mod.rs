//! `voxstream reference-ao`: the AO definition of issue 9 evaluated on the
//! CPU against the original triangles, at exactly the positions and normals a
//! `voxstream render` wrote, plus a ray-traced image of the mesh from the same
//! camera ("what the user sees"), and the comparison.
//!
//! V(p, n) = 1 − mean over N cosine-weighted rays of w(d), w(d) = 1 / (1 +
//! λ·d/R) for a hit at d ≤ R, else 0; both sides of every triangle count
//! (obvhs' Möller–Trumbore without back-face culling). Rays start at p + ε·n
//! with ε = [`EPSILON_VOXELS`] level-0 voxels. Each pixel has its own
//! deterministic random stream (SplitMix64 seeded by the pixel index), so
//! results do not depend on thread count. Triangles and points are taken
//! relative to the grid origin in f64 before rounding to f32: a scene moved by
//! 1e6 gives the same reference.

pub mod analytic;
pub mod bench;
pub mod chromium;
pub mod metrics;

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, ensure};
use glam::{DVec3, Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::pipeline::read::TriangleMesh;
use crate::render::{RenderInfo, grey_rgba, read_outputs, write_file, write_png_rgba};
use metrics::{Comparison, compare};

/// Ray start offset along the normal, in level-0 voxels (at least [`MeshBvh::offset_floor`]).
pub const EPSILON_VOXELS: f64 = 1e-3;

/// The BVH is f32: a start point rounds by half a unit in the last place (ulp) of its
/// coordinates, the triangles' corners by as much, and a hit point comes back within a few
/// more. A start offset of this many ulps of the largest coordinate clears them all.
const OFFSET_FLOOR_ULPS: f64 = 8.0;
/// Default rays per pixel.
pub const DEFAULT_RAYS: u32 = 4096;

/// A deterministic random stream (SplitMix64).
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9e37_79b9_7f4a_7c15)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// An orthonormal basis (t, b, n) around unit `n` (Duff et al. 2017).
pub fn basis(n: DVec3) -> (DVec3, DVec3) {
    let sign = 1f64.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (DVec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x), DVec3::new(b, sign + n.y * n.y * a, -n.y))
}

/// A cosine-weighted direction around unit `n`.
pub fn cosine_direction(n: DVec3, rng: &mut Rng) -> DVec3 {
    let (t, b) = basis(n);
    let u1 = rng.next_f64();
    let phi = std::f64::consts::TAU * rng.next_f64();
    let r = u1.sqrt();
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

/// w(d) of the definition.
pub fn falloff_weight(d: f64, max_distance: f64, falloff: f64) -> f64 {
    if d <= max_distance { 1.0 / (1.0 + falloff * d / max_distance) } else { 0.0 }
}

/// The mesh in a BVH, coordinates relative to `origin` (source units).
pub struct MeshBvh {
    tris: Vec<Triangle>,
    bvh: Bvh2,
    pub origin: DVec3,
    /// The largest |coordinate| of a triangle corner, local (f32).
    extent: f32,
}

impl MeshBvh {
    /// Skips degenerate and non-finite triangles.
    pub fn new(mesh: &TriangleMesh, origin: [f64; 3]) -> Self {
        let origin = DVec3::from(origin);
        let local = |p: [f64; 3]| Vec3A::from((DVec3::from(p) - origin).as_vec3());
        let tris: Vec<Triangle> = (0..mesh.triangles.len())
            .map(|t| {
                let [a, b, c] = mesh.triangle(t);
                Triangle { v0: local(a), v1: local(b), v2: local(c) }
            })
            .filter(|t| {
                t.v0.is_finite()
                    && t.v1.is_finite()
                    && t.v2.is_finite()
                    && (t.v1 - t.v0).cross(t.v2 - t.v0).length() > 0.0
            })
            .collect();
        let bvh = build_bvh2_from_tris(&tris, BvhBuildParams::medium_build(), &mut Duration::default());
        let extent =
            tris.iter().flat_map(|t| [t.v0, t.v1, t.v2]).map(|v| v.abs().max_element()).fold(0.0, f32::max);
        Self { tris, bvh, origin, extent }
    }

    /// The smallest start offset (source units) this BVH resolves: [`OFFSET_FLOOR_ULPS`] ulps of
    /// its largest coordinate. Below it a ray from a point on a surface can hit that surface
    /// itself (a scene 2,700 units across at 32768³ has voxels of 0.08 and f32 ulps of 2.4e-4,
    /// so 1e-3 voxel is under one ulp and V came out 0 on open walls).
    pub fn offset_floor(&self) -> f64 {
        let ulp = if self.extent > 0.0 { (self.extent.next_up() - self.extent) as f64 } else { 0.0 };
        OFFSET_FLOOR_ULPS * ulp
    }

    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// The nearest hit along a ray from `o` (local, f32) within (tmin, tmax): distance and triangle.
    pub fn closest_hit(&self, o: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<(f32, usize)> {
        if self.tris.is_empty() {
            return None;
        }
        let ray = Ray::new(o.into(), dir.into(), tmin, tmax);
        let mut hit = RayHit::none();
        if self.bvh.ray_traverse(ray, &mut hit, |r, id| {
            self.tris[self.bvh.primitive_indices[id] as usize].intersect(r)
        }) {
            Some((hit.t, self.bvh.primitive_indices[hit.primitive_id as usize] as usize))
        } else {
            None
        }
    }

    pub fn geometric_normal(&self, tri: usize) -> Vec3 {
        Vec3::from(self.tris[tri].compute_normal())
    }

    /// V at `p` (source units) with normal `n`: mean and standard error of the
    /// estimate from `rays` samples, and the sample variance of w.
    pub fn visibility(&self, p: DVec3, n: DVec3, params: &AoParams, rays: u32, seed: u64) -> Sample {
        let n = n.normalize_or(DVec3::Z);
        let start = p - self.origin + n * params.epsilon;
        let o = start.as_vec3();
        let mut rng = Rng::new(seed);
        let (mut sum, mut sum2) = (0.0, 0.0);
        let tmax = params.max_distance as f32;
        for _ in 0..rays {
            let dir = cosine_direction(n, &mut rng);
            let w = match self.closest_hit(o, dir.as_vec3(), 0.0, tmax) {
                Some((t, _)) => {
                    falloff_weight(t as f64 + params.epsilon, params.max_distance, params.falloff)
                }
                None => 0.0,
            };
            sum += w;
            sum2 += w * w;
        }
        let k = rays.max(1) as f64;
        let mean = sum / k;
        let variance = if rays > 1 { ((sum2 - k * mean * mean) / (k - 1.0)).max(0.0) } else { 0.0 };
        Sample { v: 1.0 - mean, stderr: (variance / k).sqrt(), variance }
    }
}

/// R, λ (source units) and the start offset.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AoParams {
    pub max_distance: f64,
    pub falloff: f64,
    pub epsilon: f64,
}

impl AoParams {
    /// The R and λ a render recorded, and the start offset for its voxel size (at least what
    /// `bvh` resolves): the reference for exactly that render's AO.
    pub fn of_render(info: &RenderInfo, bvh: &MeshBvh) -> Self {
        Self {
            max_distance: info.ao.max_distance,
            falloff: info.ao.falloff,
            epsilon: (EPSILON_VOXELS * info.voxel_size).max(bvh.offset_floor()),
        }
    }
}

/// One pixel's reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub v: f64,
    pub stderr: f64,
    /// Sample variance of w over the rays (σ² of a one-ray estimate).
    pub variance: f64,
}

/// Per-pixel reference images (NaN where there is no point).
#[derive(Debug, Clone)]
pub struct ReferenceImage {
    pub v: Vec<f32>,
    pub stderr: Vec<f32>,
    pub variance: Vec<f32>,
}

/// V at each given point; NaN where the position or normal is not finite.
pub fn reference_at(
    bvh: &MeshBvh,
    positions: &[[f64; 3]],
    normals: &[[f32; 3]],
    params: &AoParams,
    rays: u32,
) -> ReferenceImage {
    let samples: Vec<Option<Sample>> = positions
        .par_iter()
        .zip(normals)
        .enumerate()
        .map(|(i, (p, n))| {
            let p = DVec3::from(*p);
            let n = Vec3::from(*n).as_dvec3();
            (p.is_finite() && n.is_finite() && n.length() > 0.0)
                .then(|| bvh.visibility(p, n, params, rays, i as u64))
        })
        .collect();
    let pick = |f: fn(&Sample) -> f64| {
        samples.iter().map(|s| s.as_ref().map_or(f32::NAN, |s| f(s) as f32)).collect()
    };
    ReferenceImage { v: pick(|s| s.v), stderr: pick(|s| s.stderr), variance: pick(|s| s.variance) }
}

/// The ray-traced view: the first mesh hit through each pixel centre (NaN
/// where none), with the triangle's normal turned towards the camera.
pub fn primary_hits(bvh: &MeshBvh, info: &RenderInfo) -> (Vec<[f64; 3]>, Vec<[f32; 3]>) {
    let cam = &info.camera;
    let eye = DVec3::from(cam.eye) - bvh.origin;
    let (w, h) = (info.width, info.height);
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let dir = cam.pixel_ray(w, h, i % w, i / w);
            match bvh.closest_hit(eye.as_vec3(), dir.as_vec3(), cam.near as f32, cam.far as f32) {
                Some((t, tri)) => {
                    let p = eye + dir * t as f64 + bvh.origin;
                    let mut n = bvh.geometric_normal(tri);
                    if n.as_dvec3().dot(dir) > 0.0 {
                        n = -n;
                    }
                    (p.to_array(), n.to_array())
                }
                None => ([f64::NAN; 3], [f32::NAN; 3]),
            }
        })
        .unzip()
}

/// compare.json.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CompareReport {
    pub rays: u32,
    pub ao: AoParams,
    /// Epsilon in level-0 voxels.
    pub epsilon_voxels: f64,
    pub triangles: usize,
    /// The renderer's AO against the reference at the renderer's own points:
    /// the AO method's error.
    pub at_render_points: Comparison,
    /// The renderer's AO against the ray-traced view of the mesh (primary
    /// hits, mesh normals): what the user sees, voxelization included.
    pub against_primary: Option<Comparison>,
    /// Pixels with a surface in exactly one of the render and the primary view.
    pub silhouette_mismatch: Option<usize>,
    pub seconds: f64,
}

/// A stored scene's level-0 voxels as triangles in source units: two per
/// exposed face (the faces the renderer draws). `reference-ao --voxels` traces
/// the reference against these instead of the original mesh: the AO of the
/// voxelized geometry itself, which separates the error the voxelization puts
/// in from the error of the cone tracer (which sees only these voxels).
pub fn voxel_mesh(scene_dir: &Path) -> anyhow::Result<TriangleMesh> {
    use voxstream_format::{BLOCK_SIZE, Face, decode_block};
    let store = scene_dir.parent().context("the scene directory has no parent (the store)")?;
    let id = scene_dir.file_name().and_then(|n| n.to_str()).context("the scene directory's name")?;
    let scene = crate::store::open_scene(store, id)?;
    let grid = &scene.manifest.grid;
    let mut mesh = TriangleMesh { positions: Vec::new(), triangles: Vec::new(), colors: Vec::new() };
    for entry in scene.blocks().iter().filter(|e| e.key.level == 0) {
        let block = decode_block(&scene.read_block(entry)?)?;
        let origin = block.key.coord().map(|c| c as u64 * BLOCK_SIZE as u64);
        for v in &block.voxels {
            let local = v.local();
            // In grid units (integers, exact in f64), then source units.
            let corner: [f64; 3] = std::array::from_fn(|a| (origin[a] + local[a] as u64) as f64);
            for face in Face::ALL {
                if v.faces() & face.bit() == 0 {
                    continue;
                }
                let base = mesh.positions.len() as u32;
                for g in face.corners(corner, 1.0) {
                    mesh.positions.push(std::array::from_fn(|k| grid.origin[k] + g[k] * grid.voxel_size));
                }
                mesh.triangles.push([base, base + 1, base + 2]);
                mesh.triangles.push([base, base + 2, base + 3]);
            }
        }
    }
    ensure!(!mesh.triangles.is_empty(), "{} has no level-0 voxels", scene_dir.display());
    Ok(mesh)
}

/// Runs `reference-ao` on a render directory and writes its outputs there.
pub fn reference_command(
    mesh_path: &Path,
    render_dir: &Path,
    rays: u32,
    primary: bool,
    voxels: Option<&Path>,
) -> anyhow::Result<CompareReport> {
    ensure!((1..=1 << 20).contains(&rays), "--rays must be 1..=1048576, got {rays}");
    let start = std::time::Instant::now();
    let (info, ao, positions, normals) = read_outputs(render_dir)?;
    let mesh = match voxels {
        Some(scene_dir) => voxel_mesh(scene_dir)?,
        None => {
            crate::pipeline::read::read_mesh(mesh_path)
                .with_context(|| format!("reading {}", mesh_path.display()))?
                .0
        }
    };
    ensure!(!mesh.triangles.is_empty(), "{} has no triangles", mesh_path.display());
    let bvh = MeshBvh::new(&mesh, info.grid_origin);
    let params = AoParams::of_render(&info, &bvh);
    let reference = reference_at(&bvh, &positions, &normals, &params, rays);
    let at_render_points = compare(&ao, &reference.v, &reference.variance, rays, info.width, info.height);
    write_file(&render_dir.join("reference.f32"), &crate::render::f32_bytes(&reference.v))?;
    write_file(&render_dir.join("reference_stderr.f32"), &crate::render::f32_bytes(&reference.stderr))?;
    write_png_rgba(&render_dir.join("reference.png"), info.width, info.height, &grey_rgba(&reference.v))?;
    write_png_rgba(&render_dir.join("ao.png"), info.width, info.height, &grey_rgba(&ao))?;
    let (mut against_primary, mut silhouette_mismatch) = (None, None);
    if primary {
        let (pp, pn) = primary_hits(&bvh, &info);
        let prim = reference_at(&bvh, &pp, &pn, &params, rays);
        against_primary = Some(compare(&ao, &prim.v, &prim.variance, rays, info.width, info.height));
        silhouette_mismatch =
            Some(ao.iter().zip(&prim.v).filter(|(a, b)| a.is_finite() != b.is_finite()).count());
        write_file(&render_dir.join("primary.f32"), &crate::render::f32_bytes(&prim.v))?;
        write_png_rgba(&render_dir.join("primary.png"), info.width, info.height, &grey_rgba(&prim.v))?;
    }
    let report = CompareReport {
        rays,
        ao: params,
        epsilon_voxels: params.epsilon / info.voxel_size,
        triangles: bvh.triangle_count(),
        at_render_points,
        against_primary,
        silhouette_mismatch,
        seconds: start.elapsed().as_secs_f64(),
    };
    write_file(&render_dir.join("compare.json"), &serde_json::to_vec_pretty(&report)?)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One slanted triangle thousands of units from the BVH's origin, nothing else: V is 1 at
    /// every point of it. With a start offset below the f32 coordinates' resolution (1e-3 of a
    /// 1e-4 voxel, the negative control) rays start behind the surface and hit it; the offset
    /// floor keeps every point open.
    #[test]
    fn the_start_offset_clears_the_f32_resolution_far_from_the_origin() {
        let corners = [[2000.0, 3100.0, 3900.0], [4100.0, 2900.0, 2600.0], [2300.0, 4200.0, 2800.0]];
        let mesh =
            TriangleMesh { positions: corners.to_vec(), triangles: vec![[0, 1, 2]], colors: Vec::new() };
        let bvh = MeshBvh::new(&mesh, [0.0; 3]);
        let [a, b, c] = corners.map(DVec3::from);
        let n = (b - a).cross(c - a).normalize();
        let mut rng = Rng::new(7);
        let points: Vec<DVec3> = (0..200)
            .map(|_| {
                let (u, v) = (rng.next_f64(), rng.next_f64());
                let (u, v) = if u + v > 1.0 { (1.0 - u, 1.0 - v) } else { (u, v) };
                a + (b - a) * u + (c - a) * v
            })
            .collect();
        let closed = |epsilon: f64| {
            let params = AoParams { max_distance: 50.0, falloff: 1.0, epsilon };
            points
                .iter()
                .enumerate()
                .filter(|(i, p)| bvh.visibility(**p, n, &params, 16, *i as u64).v < 1.0)
                .count()
        };
        let floor = bvh.offset_floor();
        assert!(floor > 1e-4 && floor < 1e-2, "{floor}");
        assert_eq!(closed(floor), 0, "points on an open surface saw it");
        assert!(closed(1e-7) > 20, "control: an offset under one ulp must let rays hit their own surface");
    }
}
