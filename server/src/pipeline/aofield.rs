//! The precomputed AO field (issue 9 item 2, seed 002's "spatial ambient
//! occlusion", docs: ARCHITECTURE.md, docs/ao-benchmark.md).
//!
//! At build time, between binning and voxelization:
//! 1. **Occupancy.** Every valid triangle of the stream is sampled at points at
//!    most half a cell apart and marks the cells of a `cells`³ bit grid over the
//!    whole scene grid (`cells` = min(resolution, [`FIELD_CELLS`])). ORing bits
//!    is order-free, so the grid is the same for any thread count. A hollow
//!    shell, as in the thesis (§3.3): no inside/outside classification.
//! 2. **Opacity mips.** Level 0 is 1 where a cell is marked; level m+1 is
//!    min(1, sum of its 8 children / 4) (a plane through 2×2×2 cells marks 4).
//! 3. **Field.** For every cell within [`DILATE`] cells of a marked one, the
//!    visibility V (the definition, with R and λ) along each of the six
//!    axis directions, each estimated by the viewer's default cone set (6
//!    cosine-weighted cones, the viewer's start-offset rule and width clamp) traced
//!    through the mips: an ambient cube per cell. Cells are independent, so
//!    this runs on all cores and stays deterministic.
//! 4. **Per voxel.** Each drawn voxel of every level gets one byte,
//!    `1 + round(254·V)`, V read from the field at the voxel's centre moved one
//!    cell along its normal: the ambient cubes of the 8 nearest cells (those
//!    not behind the voxel's tangent plane, trilinear weights renormalised),
//!    each evaluated for the normal as Σ nᵢ²·V(±axisᵢ). 0 where no cell
//!    qualifies (the viewer then cone-traces that pixel).
//!
//! The block codec stores the byte as its AO field column; the viewer's
//! G-buffer carries it and the `field` AO mode shows it instead of tracing.
//!
//! Limits: the field sees occluders at the resolution of `cells` (128³ over
//! the scene: a cell is grid/128, R = 12.8 cells at the default R), so detail
//! finer than a cell shades as in the coarse grid; the field is computed for
//! one R and λ (recorded in the manifest), the viewer cannot change them; the
//! ambient cube blends the axis lobes for slanted normals.

use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;
use voxstream_format::{AoFieldInfo, GridFrame};

use crate::pipeline::BuildError;
use crate::pipeline::stream::{ChunkStore, RecordLayout};
use crate::pipeline::voxelize::to_grid;

/// The most cells per edge of the field's occupancy grid.
pub const FIELD_CELLS: u32 = 128;
/// Cells around a marked cell whose ambient cube is computed: a voxel reads
/// the cells around its centre moved one cell along its normal.
pub const DILATE: i32 = 2;

/// The most heap the field takes at once (while computing: occupancy bits,
/// opacity mips and the ambient cubes; pass 3 keeps the cubes only), whatever
/// the scene: counted in the build's `MemoryPlan` reserve.
pub fn peak_bytes(resolution: u32) -> u64 {
    peak_bytes_cells(FIELD_CELLS.min(resolution))
}

/// [`peak_bytes`] for `cells` an edge.
pub fn peak_bytes_cells(cells: u32) -> u64 {
    let n = cells.max(1) as u64;
    let cells = n * n * n;
    cells / 8 + 8 + cells * 4 * 8 / 7 + 64 + cells * 6 + cells * 2
}

/// How a build computes its AO field (`BuildOptions::ao_field`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AoFieldOptions {
    /// Cells per edge at most (the grid's resolution when smaller).
    pub cells: u32,
    /// R in grid units; `None`: the viewer's default for the grid
    /// (`voxstream_viewer::ao::default_max_distance`), so the field and the cone
    /// tracer's defaults agree.
    pub max_distance: Option<f32>,
    /// λ.
    pub falloff: f32,
    /// V is stored rounded to this many evenly spaced values (2..=255) before it
    /// becomes a byte: fewer distinct bytes compress better (lz4 finds runs in
    /// the delta-coded column); 64 keeps the rounding within 0.008.
    pub levels: u32,
}

impl Default for AoFieldOptions {
    fn default() -> Self {
        Self { cells: FIELD_CELLS, max_distance: None, falloff: 1.0, levels: 64 }
    }
}

/// The whole-grid occupancy bits (step 1).
pub struct Occupancy {
    n: usize,
    /// Grid units per cell.
    cell: f64,
    bits: Vec<AtomicU64>,
}

impl Occupancy {
    pub fn new(resolution: u32, cells: u32) -> Self {
        let n = cells.min(resolution).max(1) as usize;
        let words = (n * n * n).div_ceil(64);
        Self { n, cell: resolution as f64 / n as f64, bits: (0..words).map(|_| AtomicU64::new(0)).collect() }
    }

    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.n + c[1]) * self.n + c[0]
    }

    pub fn get(&self, c: [usize; 3]) -> bool {
        let i = self.index(c);
        self.bits[i / 64].load(Ordering::Relaxed) >> (i % 64) & 1 == 1
    }

    fn set(&self, c: [usize; 3]) {
        let i = self.index(c);
        self.bits[i / 64].fetch_or(1 << (i % 64), Ordering::Relaxed);
    }

    /// Marks the cells of a triangle in grid units: points of a barycentric
    /// lattice at most half a cell apart.
    pub fn mark_triangle(&self, g: &[[f64; 3]; 3]) {
        let t = g.map(|p| p.map(|c| c / self.cell));
        let edge = |a: usize, b: usize| (0..3).map(|k| (t[a][k] - t[b][k]).powi(2)).sum::<f64>().sqrt();
        let longest = edge(0, 1).max(edge(1, 2)).max(edge(2, 0));
        let k = ((longest * 2.0).ceil() as usize).clamp(1, 1 << 14);
        let top = self.n as f64 - 1.0;
        for i in 0..=k {
            for j in 0..=k - i {
                let (a, b) = (i as f64 / k as f64, j as f64 / k as f64);
                let c: [usize; 3] = std::array::from_fn(|d| {
                    let p = t[0][d] + a * (t[1][d] - t[0][d]) + b * (t[2][d] - t[0][d]);
                    p.floor().clamp(0.0, top) as usize
                });
                self.set(c);
            }
        }
    }

    /// Marks every valid triangle of the stream (pass 2's input).
    pub fn from_stream(
        stream: &ChunkStore,
        layout: RecordLayout,
        frame: &GridFrame,
        cells: u32,
        check: &(dyn Fn() -> Result<(), BuildError> + Sync),
    ) -> Result<Self, BuildError> {
        let occ = Self::new(frame.resolution, cells);
        let rec = layout.size();
        for id in 0..stream.len() {
            check()?;
            stream
                .with_records(id, |raw| {
                    raw.par_chunks_exact(rec).with_min_len(256).for_each(|record| {
                        let (tri, _) = layout.decode(record);
                        if let Some(g) = to_grid(tri, frame) {
                            occ.mark_triangle(&g);
                        }
                    });
                    Ok(())
                })
                .map_err(|e| BuildError::Temp(e.to_string()))?;
        }
        Ok(occ)
    }

    pub fn marked(&self) -> u64 {
        self.bits.iter().map(|w| w.load(Ordering::Relaxed).count_ones() as u64).sum()
    }
}

/// The field: an ambient cube (V along −x, +x, −y, +y, −z, +z, each as
/// `1 + round(254·V)`, 0 = not computed) per cell.
pub struct AoField {
    n: usize,
    cell: f32,
    levels: f32,
    info: AoFieldInfo,
    cube: Vec<[u8; 6]>,
}

const AXES: [[f32; 3]; 6] =
    [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]];

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn add(a: [f32; 3], b: [f32; 3], s: f32) -> [f32; 3] {
    [a[0] + b[0] * s, a[1] + b[1] * s, a[2] + b[2] * s]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn normalize(a: [f32; 3]) -> [f32; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 && l.is_finite() { a.map(|c| c / l) } else { [0.0, 0.0, 1.0] }
}

/// Opacity mips (step 2): level m has n >> m cells per edge.
struct Mips {
    levels: Vec<(usize, Vec<f32>)>,
}

impl Mips {
    fn new(occ: &Occupancy) -> Self {
        let n = occ.n;
        let mut base = vec![0f32; n * n * n];
        base.par_chunks_mut(n * n).enumerate().for_each(|(z, slab)| {
            for y in 0..n {
                for x in 0..n {
                    slab[y * n + x] = if occ.get([x, y, z]) { 1.0 } else { 0.0 };
                }
            }
        });
        let mut levels = vec![(n, base)];
        while levels.last().expect("one").0 > 1 {
            let (m, prev) = levels.last().expect("one");
            let (m, h) = (*m, m / 2);
            let mut next = vec![0f32; h * h * h];
            next.par_chunks_mut(h * h).enumerate().for_each(|(z, slab)| {
                for y in 0..h {
                    for x in 0..h {
                        let mut s = 0.0;
                        for c in 0..8 {
                            let (cx, cy, cz) = (2 * x + (c & 1), 2 * y + (c >> 1 & 1), 2 * z + (c >> 2));
                            s += prev[(cz * m + cy) * m + cx];
                        }
                        slab[y * h + x] = (s / 4.0).min(1.0);
                    }
                }
            });
            levels.push((h, next));
        }
        Self { levels }
    }

    fn cell(&self, level: usize, c: [i64; 3]) -> f32 {
        let (n, v) = &self.levels[level];
        let n = *n as i64;
        if c.iter().any(|&k| k < 0 || k >= n) {
            return 0.0;
        }
        v[((c[2] * n + c[1]) * n + c[0]) as usize]
    }

    /// Trilinear opacity of one level at `p` (level-0 cell units).
    fn trilinear(&self, level: usize, p: [f32; 3]) -> f32 {
        let edge = (1u32 << level) as f32;
        let q = p.map(|c| c / edge - 0.5);
        let b = q.map(|c| c.floor());
        let f = [q[0] - b[0], q[1] - b[1], q[2] - b[2]];
        let b = b.map(|c| c as i64);
        let mut v = 0.0;
        for k in 0..8 {
            let o = [k & 1, k >> 1 & 1, k >> 2];
            let w: f32 = (0..3).map(|a| if o[a] == 1 { f[a] } else { 1.0 - f[a] }).product();
            if w > 0.0 {
                v += w * self.cell(level, [b[0] + o[0] as i64, b[1] + o[1] as i64, b[2] + o[2] as i64]);
            }
        }
        v
    }

    /// Quadrilinear: levels floor(lod) and the next, blended by lod's fraction.
    fn sample(&self, p: [f32; 3], lod: f32) -> f32 {
        let top = self.levels.len() - 1;
        let l = (lod.max(0.0).floor() as usize).min(top);
        let frac = (lod - l as f32).clamp(0.0, 1.0);
        let v = self.trilinear(l, p);
        if frac > 0.0 && l < top { v + (self.trilinear(l + 1, p) - v) * frac } else { v }
    }
}

/// The cone set of the viewer's default (6 cosine-weighted cones, equal weights), local frame.
struct Cones {
    dirs: Vec<[f32; 3]>,
    tan_half: f32,
    step: f32,
    offset: f32,
}

impl Cones {
    fn viewer_default() -> Self {
        let s = voxstream_viewer::ao::AoSettings::default();
        let dirs = voxstream_viewer::ao::cone_directions(s.cones);
        let half =
            s.aperture_deg.map(f32::to_radians).unwrap_or_else(|| (1.0 / (s.cones as f32).sqrt()).asin());
        Self { dirs, tan_half: half.tan(), step: s.step, offset: s.offset_cells }
    }
}

impl AoField {
    /// Step 3: the ambient cubes of every cell within [`DILATE`] of a marked one.
    pub fn compute(occ: &Occupancy, resolution: u32, opts: &AoFieldOptions) -> Self {
        let n = occ.n;
        let cell = occ.cell as f32;
        let radius_grid =
            opts.max_distance.unwrap_or_else(|| voxstream_viewer::ao::default_max_distance(resolution));
        let info = AoFieldInfo { cells: n as u32, max_distance: radius_grid, falloff: opts.falloff };
        let radius = radius_grid / cell;
        let mips = Mips::new(occ);
        let cones = Cones::viewer_default();
        let mut cube = vec![[0u8; 6]; n * n * n];
        // Cells within DILATE (Chebyshev) of a marked one: the base mip dilated one axis at a time.
        let mut near: Vec<bool> = mips.levels[0].1.iter().map(|&o| o > 0.0).collect();
        for stride in [1, n, n * n] {
            let prev = near.clone();
            for (i, v) in near.iter_mut().enumerate() {
                let c = i / stride % n;
                let (lo, hi) = (c.saturating_sub(DILATE as usize), (c + DILATE as usize).min(n - 1));
                *v = (lo..=hi).any(|k| prev[i - c * stride + k * stride]);
            }
        }
        cube.par_chunks_mut(n * n).enumerate().for_each(|(z, slab)| {
            for y in 0..n {
                for x in 0..n {
                    if !near[(z * n + y) * n + x] {
                        continue;
                    }
                    let p = [x as f32 + 0.5, y as f32 + 0.5, z as f32 + 0.5];
                    slab[y * n + x] = AXES.map(|a| {
                        let v = visibility(&mips, &cones, p, a, radius, opts.falloff, n as f32);
                        1 + (v.clamp(0.0, 1.0) * 254.0).round() as u8
                    });
                }
            }
        });
        Self { n, cell, levels: (opts.levels.clamp(2, 255) - 1) as f32, info, cube }
    }

    pub fn info(&self) -> &AoFieldInfo {
        &self.info
    }

    /// Heap bytes held.
    pub fn bytes(&self) -> usize {
        self.cube.len() * 6
    }

    /// Step 4: the byte for a voxel centred at `x` (grid units) with normal
    /// `normal_sum` (any length): `1 + round(254·V)`, 0 when no cell qualifies.
    pub fn voxel_byte(&self, x: [f32; 3], normal_sum: [f32; 3]) -> u8 {
        let nrm = normalize(normal_sum);
        let xc = x.map(|c| c / self.cell);
        let q = add(xc, nrm, 1.0).map(|c| c - 0.5);
        let b = q.map(|c| c.floor());
        let f = [q[0] - b[0], q[1] - b[1], q[2] - b[2]];
        let lobes: [f32; 6] = std::array::from_fn(|i| {
            let c = nrm[i / 2] * if i % 2 == 1 { 1.0 } else { -1.0 };
            if c > 0.0 { c * c } else { 0.0 }
        });
        let (mut sum, mut weight) = (0.0f32, 0.0f32);
        for k in 0..8 {
            let o = [k & 1, k >> 1 & 1, k >> 2];
            let w: f32 = (0..3).map(|a| if o[a] == 1 { f[a] } else { 1.0 - f[a] }).product();
            let c: [i64; 3] = std::array::from_fn(|a| b[a] as i64 + o[a] as i64);
            if w <= 0.0 || c.iter().any(|&k| k < 0 || k >= self.n as i64) {
                continue;
            }
            let centre = c.map(|k| k as f32 + 0.5);
            // A cell centred behind the voxel's tangent plane sees the inside.
            if dot([centre[0] - xc[0], centre[1] - xc[1], centre[2] - xc[2]], nrm) < -0.5 {
                continue;
            }
            let cube = self.cube[((c[2] as usize * self.n) + c[1] as usize) * self.n + c[0] as usize];
            if cube[0] == 0 {
                continue;
            }
            let v: f32 = (0..6).map(|i| lobes[i] * (cube[i] - 1) as f32 / 254.0).sum();
            sum += w * v;
            weight += w;
        }
        if weight <= 1e-6 || !sum.is_finite() {
            return 0;
        }
        let v = ((sum / weight).clamp(0.0, 1.0) * self.levels).round() / self.levels;
        1 + (v * 254.0).round() as u8
    }
}

/// V at `p` (cell units) for the hemisphere around the unit axis `n`: the cone
/// set turned to `n`, each cone traced through the mips as `shaders/ao.wgsl`
/// traces the volume (start offset, width clamp, w(d) half an edge on).
fn visibility(
    mips: &Mips,
    cones: &Cones,
    p: [f32; 3],
    n: [f32; 3],
    radius: f32,
    falloff: f32,
    size: f32,
) -> f32 {
    let helper = if n[1].abs() > 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let t = normalize(cross(helper, n));
    let b = cross(n, t);
    let max_mip = (mips.levels.len() - 1) as f32;
    let mut occluded = 0.0;
    for a in &cones.dirs {
        let dir = normalize([
            t[0] * a[0] + b[0] * a[1] + n[0] * a[2],
            t[1] * a[0] + b[1] * a[1] + n[1] * a[2],
            t[2] * a[0] + b[2] * a[1] + n[2] * a[2],
        ]);
        let origin = add(p, n, cones.offset);
        let (mut alpha, mut occ, mut dist) = (0.0f32, 0.0f32, 0.0f32);
        for _ in 0..128 {
            let s = add(origin, dir, dist);
            let d = dot(add(s, p, -1.0), add(s, p, -1.0)).sqrt();
            if d > radius || alpha > 0.995 || s.iter().any(|&c| c < 0.0 || c > size) {
                break;
            }
            let height = dot(add(s, p, -1.0), n).max(1.0);
            let diameter = (2.0 * cones.tan_half * d).clamp(1.0, (height / 3.0).max(1.0));
            // Cells of half the diameter, as the viewer's trace (shaders/ao.wgsl).
            let mip = (diameter.log2() - 1.0).clamp(0.0, max_mip);
            let step = (cones.step * diameter).max(0.5);
            let o = mips.sample(s, mip);
            if o > 0.0 {
                let edge = mip.exp2();
                let a = 1.0 - (1.0 - o).max(0.0).powf(step / edge);
                let w = 1.0 / (1.0 + falloff * (d + 0.5 * edge) / radius);
                occ += (1.0 - alpha) * a * w;
                alpha += (1.0 - alpha) * a;
            }
            dist += step;
        }
        occluded += occ / cones.dirs.len() as f32;
    }
    1.0 - occluded
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor at z = 8 cells of a 64³ grid (64 cells).
    fn floor() -> Occupancy {
        let occ = Occupancy::new(64, 64);
        occ.mark_triangle(&[[0.0, 0.0, 8.5], [64.0, 0.0, 8.5], [0.0, 64.0, 8.5]]);
        occ.mark_triangle(&[[64.0, 64.0, 8.5], [64.0, 0.0, 8.5], [0.0, 64.0, 8.5]]);
        occ
    }

    #[test]
    fn a_triangle_marks_its_cells_and_only_them() {
        let occ = floor();
        assert_eq!(occ.marked(), 64 * 64);
        assert!(occ.get([10, 20, 8]) && !occ.get([10, 20, 9]) && !occ.get([10, 20, 7]));
    }

    #[test]
    fn an_open_floor_is_visible_from_above_and_blocked_from_below() {
        let occ = floor();
        let field = AoField::compute(
            &occ,
            64,
            &AoFieldOptions { cells: 64, max_distance: Some(8.0), ..Default::default() },
        );
        let up = field.voxel_byte([32.5, 32.5, 8.5], [0.0, 0.0, 1.0]);
        assert!(up >= 240, "{up}");
        // Control: a voxel under the floor, facing it, is occluded.
        let down = field.voxel_byte([32.5, 32.5, 4.5], [0.0, 0.0, 1.0]);
        assert!(down < 200, "{down}");
        // Far from everything: no field.
        assert_eq!(field.voxel_byte([32.5, 32.5, 40.5], [0.0, 0.0, 1.0]), 0);
    }
}
