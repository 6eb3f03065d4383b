//! CPU reference for what a frame must cover: every exposed face quad of the
//! drawn blocks, projected with the frame's view-projection matrix and
//! rasterised with pixel-centre sampling, back faces culled as the GPU does.
//! Comparing it with the rendered image's silhouette checks selection, GPU face
//! expansion, vertex pulling and the camera matrices end to end, independent of
//! shading (anything not the background colour counts as covered).

use voxstream_format::{BLOCK_SIZE, Block, BlockKey, Face};

/// Anything that holds a decoded block: `Block`, `&Block`, `(BlockKey, Block)`.
pub trait AsBlock {
    fn as_block(&self) -> &Block;
}

impl AsBlock for Block {
    fn as_block(&self) -> &Block {
        self
    }
}

impl AsBlock for &Block {
    fn as_block(&self) -> &Block {
        self
    }
}

impl AsBlock for (BlockKey, Block) {
    fn as_block(&self) -> &Block {
        &self.1
    }
}

type Vec4 = [f64; 4];

fn transform(m: &[f32; 16], p: [f64; 3]) -> Vec4 {
    // Column-major: m[col * 4 + row].
    std::array::from_fn(|row| {
        m[row] as f64 * p[0] + m[4 + row] as f64 * p[1] + m[8 + row] as f64 * p[2] + m[12 + row] as f64
    })
}

/// Clips a polygon in clip space to 0 <= z <= w (wgpu's depth range). The side
/// planes need no clipping: rasterising is bounded by the viewport anyway.
fn clip_depth(poly: &[Vec4]) -> Vec<Vec4> {
    let mut out: Vec<Vec4> = poly.to_vec();
    let planes: [fn(&Vec4) -> f64; 2] = [|p| p[2], |p| p[3] - p[2]];
    for dist in planes {
        let input = std::mem::take(&mut out);
        for i in 0..input.len() {
            let (a, b) = (input[i], input[(i + 1) % input.len()]);
            let (da, db) = (dist(&a), dist(&b));
            if da >= 0.0 {
                out.push(a);
            }
            if (da >= 0.0) != (db >= 0.0) {
                let t = da / (da - db);
                out.push(std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t));
            }
        }
        if out.len() < 3 {
            return Vec::new();
        }
    }
    out
}

/// Marks the pixels whose centres a triangle (in pixel coordinates) covers.
fn raster_triangle(mask: &mut [bool], width: u32, height: u32, t: [[f64; 2]; 3]) {
    let min_x = t.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
    let max_x = t.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max);
    let min_y = t.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
    let max_y = t.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max);
    // Pixel x's centre is x + 0.5.
    let x0 = (min_x - 0.5).ceil().max(0.0) as i64;
    let x1 = ((max_x - 0.5).floor() as i64).min(width as i64 - 1);
    let y0 = (min_y - 0.5).ceil().max(0.0) as i64;
    let y1 = ((max_y - 0.5).floor() as i64).min(height as i64 - 1);
    if x0 > x1 || y0 > y1 {
        return;
    }
    let edge =
        |a: [f64; 2], b: [f64; 2], p: [f64; 2]| (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
    let area = edge(t[0], t[1], t[2]);
    if area == 0.0 {
        return;
    }
    let s = area.signum();
    for y in y0..=y1 {
        for x in x0..=x1 {
            let p = [x as f64 + 0.5, y as f64 + 0.5];
            if edge(t[0], t[1], p) * s >= 0.0
                && edge(t[1], t[2], p) * s >= 0.0
                && edge(t[2], t[0], p) * s >= 0.0
            {
                mask[y as usize * width as usize + x as usize] = true;
            }
        }
    }
}

/// Pixels (row-major, top row first) covered by the front faces of the
/// blocks' exposed voxel faces under `view_proj` (column-major, grid units →
/// wgpu clip space with depth 0..1).
pub fn coverage_mask<B: AsBlock>(blocks: &[B], view_proj: &[f32; 16], width: u32, height: u32) -> Vec<bool> {
    let mut mask = vec![false; width as usize * height as usize];
    let (w, h) = (width as f64, height as f64);
    for block in blocks {
        let block = block.as_block();
        let size = (1u64 << block.key.level) as f64;
        let origin = block.key.coord().map(|c| c as f64 * BLOCK_SIZE as f64 * size);
        for voxel in &block.voxels {
            let local = voxel.local();
            let min: [f64; 3] = std::array::from_fn(|a| origin[a] + local[a] as f64 * size);
            for face in Face::ALL {
                if voxel.faces() & face.bit() == 0 {
                    continue;
                }
                let clip = face.corners(min, size).map(|p| transform(view_proj, p));
                let poly = clip_depth(&clip);
                if poly.is_empty() {
                    continue;
                }
                // Pixel coordinates: x right, y down.
                let screen: Vec<[f64; 2]> = poly
                    .iter()
                    .map(|c| [(c[0] / c[3] + 1.0) * 0.5 * w, (1.0 - c[1] / c[3]) * 0.5 * h])
                    .collect();
                // Counter-clockwise in NDC (y up) is clockwise in pixels (y down):
                // front faces have negative pixel-space area.
                let twice_area: f64 = (0..screen.len())
                    .map(|i| {
                        let (a, b) = (screen[i], screen[(i + 1) % screen.len()]);
                        a[0] * b[1] - b[0] * a[1]
                    })
                    .sum();
                if twice_area >= 0.0 {
                    continue;
                }
                for i in 1..screen.len() - 1 {
                    raster_triangle(&mut mask, width, height, [screen[0], screen[i], screen[i + 1]]);
                }
            }
        }
    }
    mask
}

/// Pixels of an RGBA8 image (row-major, top row first) that differ from `background`.
pub fn silhouette_from_rgba(pixels: &[u8], width: u32, height: u32, background: [u8; 4]) -> Vec<bool> {
    assert_eq!(pixels.len(), width as usize * height as usize * 4, "RGBA8 image of {width}x{height}");
    pixels.chunks_exact(4).map(|p| p != background).collect()
}

/// How a rendered silhouette compares with a coverage mask.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaskComparison {
    /// |actual ∩ expected| / |actual ∪ expected|; 1 when both are empty.
    pub iou: f64,
    pub expected_pixels: usize,
    pub actual_pixels: usize,
    /// Covered in the reference but background in the image.
    pub missing: usize,
    /// Covered in the image but not in the reference.
    pub extra: usize,
    /// Mismatches with no reference edge in their 3×3 neighbourhood. Sampling
    /// and rounding differences can only move edges by a pixel, so anything
    /// here is a real difference (a hole, a misplaced block).
    pub off_edge: usize,
}

/// The tolerance the native and browser tests hold renders to.
pub const MIN_IOU: f64 = 0.98;
/// Mismatches away from any edge allowed, as a fraction of the reference's pixels.
pub const MAX_OFF_EDGE_FRACTION: f64 = 0.001;

impl MaskComparison {
    pub fn mismatches(&self) -> usize {
        self.missing + self.extra
    }

    /// IoU ≥ [`MIN_IOU`] and off-edge mismatches ≤ [`MAX_OFF_EDGE_FRACTION`] of the reference.
    pub fn within_tolerance(&self) -> bool {
        self.iou >= MIN_IOU
            && self.off_edge as f64 <= MAX_OFF_EDGE_FRACTION * self.expected_pixels.max(1) as f64
    }
}

/// Compares a rendered silhouette (`actual`) with a reference mask (`expected`).
pub fn compare_masks(actual: &[bool], expected: &[bool], width: u32, height: u32) -> MaskComparison {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(actual.len(), w * h, "actual mask size");
    assert_eq!(expected.len(), w * h, "expected mask size");
    let near_edge = |x: usize, y: usize| {
        let v = expected[y * w + x];
        (y.saturating_sub(1)..=(y + 1).min(h - 1))
            .any(|ny| (x.saturating_sub(1)..=(x + 1).min(w - 1)).any(|nx| expected[ny * w + nx] != v))
    };
    let (mut both, mut missing, mut extra, mut off_edge) = (0, 0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let (a, e) = (actual[y * w + x], expected[y * w + x]);
            match (a, e) {
                (true, true) => both += 1,
                (false, true) => missing += 1,
                (true, false) => extra += 1,
                (false, false) => {}
            }
            if a != e && !near_edge(x, y) {
                off_edge += 1;
            }
        }
    }
    let union = both + missing + extra;
    MaskComparison {
        iou: if union == 0 { 1.0 } else { both as f64 / union as f64 },
        expected_pixels: both + missing,
        actual_pixels: both + extra,
        missing,
        extra,
        off_edge,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxstream_format::PackedVoxel;

    /// Looking down -Z at the unit square [0,1]² from z = 10 with a 2×2 orthographic frame.
    fn ortho_over(min: f32, max: f32) -> [f32; 16] {
        let s = 2.0 / (max - min);
        let t = -(max + min) / (max - min);
        // x, y scaled into -1..1; z: depth = (10 - z) / 20 so z in (-10, 10) is inside.
        [s, 0.0, 0.0, 0.0, 0.0, s, 0.0, 0.0, 0.0, 0.0, -0.05, 0.0, t, t, 0.5, 1.0]
    }

    fn one_voxel(faces: u8) -> Block {
        Block { key: BlockKey::new(0, 0, 0, 0), voxels: vec![PackedVoxel::new([0, 0, 0], faces, 0)] }
    }

    #[test]
    fn a_front_facing_quad_covers_its_pixels() {
        // Voxel [0,1]³ seen from +z, frame [-1, 3]: the +Z face spans pixels 25%..50% of 8.
        let mask = coverage_mask(&[one_voxel(Face::PosZ.bit())], &ortho_over(-1.0, 3.0), 8, 8);
        let covered: Vec<(usize, usize)> = (0..64).filter(|&i| mask[i]).map(|i| (i % 8, i / 8)).collect();
        assert_eq!(covered, vec![(2, 4), (3, 4), (2, 5), (3, 5)], "y grows downwards");
    }

    #[test]
    fn back_faces_are_culled() {
        let mask = coverage_mask(&[one_voxel(Face::NegZ.bit())], &ortho_over(-1.0, 3.0), 8, 8);
        assert!(mask.iter().all(|&m| !m), "the -Z face looks away from a camera on +z");
        // Side faces are edge-on: zero area, nothing drawn.
        let sides = Face::NegX.bit() | Face::PosX.bit() | Face::NegY.bit() | Face::PosY.bit();
        assert!(coverage_mask(&[one_voxel(sides)], &ortho_over(-1.0, 3.0), 8, 8).iter().all(|&m| !m));
    }

    #[test]
    fn geometry_behind_the_camera_is_clipped() {
        // Everything at depth < 0 (z > 10 here) is clipped away, not mirrored.
        let far_block = Block {
            key: BlockKey::new(0, 0, 0, 0),
            voxels: vec![PackedVoxel::new([0, 0, 20], Face::PosZ.bit(), 0)],
        };
        assert!(coverage_mask(&[far_block], &ortho_over(-1.0, 3.0), 8, 8).iter().all(|&m| !m));
    }

    #[test]
    fn comparison_separates_edge_noise_from_real_differences() {
        let (w, h) = (10, 10);
        let square = |x0: usize, x1: usize| -> Vec<bool> {
            (0..w * h).map(|i| (x0..x1).contains(&(i % w)) && (2..8).contains(&(i / w))).collect()
        };
        let expected = square(2, 8);
        let same = compare_masks(&expected, &expected, w as u32, h as u32);
        assert_eq!((same.iou, same.mismatches(), same.off_edge), (1.0, 0, 0));
        assert!(same.within_tolerance());

        // One column thinner: all mismatches sit on the edge.
        let thin = compare_masks(&square(2, 7), &expected, w as u32, h as u32);
        assert_eq!((thin.missing, thin.extra, thin.off_edge), (6, 0, 0));

        // A hole in the middle is off-edge.
        let mut holed = expected.clone();
        holed[5 * w + 5] = false;
        let c = compare_masks(&holed, &expected, w as u32, h as u32);
        assert_eq!((c.missing, c.off_edge), (1, 1));
        assert!(!c.within_tolerance());

        // Shifted far: poor IoU.
        let shifted = compare_masks(&square(5, 10), &expected, w as u32, h as u32);
        assert!(shifted.iou < 0.5 && !shifted.within_tolerance());
    }

    #[test]
    fn silhouette_is_anything_not_background() {
        let bg = [20, 24, 36, 255];
        let px = [20, 24, 36, 255, 20, 24, 37, 255, 200, 190, 170, 255, 20, 24, 36, 255];
        assert_eq!(silhouette_from_rgba(&px, 2, 2, bg), vec![false, true, true, false]);
    }
}
