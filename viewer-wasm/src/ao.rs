//! Occupancy volume for cone-traced ambient occlusion (shaders/ao.wgsl).
//!
//! The drawn blocks are splatted into a cubic grid of at most 128³ cells over
//! the whole scene grid, with a mip chain of averaged occupancy built on the
//! CPU, and uploaded as an r8unorm 3D texture the fragment shader samples at
//! the mip matching each cone's width.
//!
//! Each voxel brings its prefiltered coverage (the stored fraction of occupied
//! level-0 voxels below it), so a coarse block puts the same occluding mass
//! into the volume as the fine blocks it stands for would: the AO does not
//! darken or brighten as the LOD changes.

use voxstream_format::{BLOCK_SIZE, Block, FULL_COVERAGE};

/// Cells per edge of the finest occupancy mip (or the grid resolution if smaller).
pub const MAX_CELLS: u32 = 128;

/// The CPU side of the volume: one byte per cell per mip, x fastest.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyVolume {
    /// Grid units per volume edge (the scene grid resolution).
    pub grid_resolution: u32,
    /// Cells per edge at mip 0.
    pub cells: u32,
    /// mips[0] is cells³ bytes, each next one an eighth of it, down to 1³.
    pub mips: Vec<Vec<u8>>,
}

/// Cells per edge for a grid: a power of two no larger than [`MAX_CELLS`].
pub fn cells_for_grid(grid_resolution: u32) -> u32 {
    grid_resolution.clamp(1, MAX_CELLS).next_power_of_two().min(MAX_CELLS)
}

impl OccupancyVolume {
    /// Splats `blocks` into a volume over a `grid_resolution`³ grid.
    ///
    /// The blocks store surface voxels only, so a cell's density is its
    /// surface opacity: each occupied level-0 voxel adds 1 / (cell edge)², its
    /// share of a surface crossing the cell, and a cell cut by a fine surface
    /// reads as (about) opaque. A voxel of any level brings `coverage · 8^level`
    /// level-0 voxels (its stored coverage), spread evenly over the cells it
    /// overlaps when it is larger than a cell.
    pub fn build<'a>(grid_resolution: u32, blocks: impl IntoIterator<Item = &'a Block>) -> Self {
        let cells = cells_for_grid(grid_resolution);
        let cell_edge = (grid_resolution / cells).max(1) as u64;
        let n = cells as usize;
        let per_level0 = 1.0 / (cell_edge * cell_edge) as f32;
        let mut density = vec![0f32; n * n * n];
        for block in blocks {
            let voxel_edge = 1u64 << block.key.level;
            let volume = (voxel_edge * voxel_edge * voxel_edge) as f32;
            let block_origin = block.key.coord().map(|c| c as u64 * BLOCK_SIZE as u64 * voxel_edge);
            let span = (voxel_edge / cell_edge).max(1) as usize;
            let cells_per_voxel = (span * span * span) as f32;
            for v in &block.voxels {
                let level0 = v.coverage() as f32 / FULL_COVERAGE as f32 * volume;
                let share = level0 * per_level0 / cells_per_voxel;
                let local = v.local();
                let first: [u64; 3] =
                    std::array::from_fn(|a| (block_origin[a] + local[a] as u64 * voxel_edge) / cell_edge);
                if first.iter().any(|&c| c >= cells as u64) {
                    continue;
                }
                let [x0, y0, z0] = first.map(|c| c as usize);
                for z in z0..(z0 + span).min(n) {
                    for y in y0..(y0 + span).min(n) {
                        let row = (z * n + y) * n;
                        for d in &mut density[row + x0..row + (x0 + span).min(n)] {
                            *d += share;
                        }
                    }
                }
            }
        }
        fill_enclosed(&mut density, n);
        let mut mips = Vec::new();
        let mut level = density;
        let mut edge = n;
        loop {
            mips.push(level.iter().map(|&d| (d.clamp(0.0, 1.0) * 255.0).round() as u8).collect());
            if edge == 1 {
                break;
            }
            level = downsample(&level, edge);
            edge /= 2;
        }
        Self { grid_resolution, cells, mips }
    }

    pub fn mip_count(&self) -> u32 {
        self.mips.len() as u32
    }

    /// Occupancy 0..=1 of one cell of one mip.
    pub fn value(&self, mip: usize, x: usize, y: usize, z: usize) -> f32 {
        let edge = (self.cells as usize) >> mip;
        self.mips[mip][(z * edge + y) * edge + x] as f32 / 255.0
    }
}

/// Marks empty cells that the outside cannot reach (6-connected through empty
/// cells) as full. The blocks hold surface voxels only, so without this a solid
/// body would read as a thin shell and coarse mips (wide cones) would see
/// through it. Where the shell has a gap (say, between blocks of different
/// levels while streaming) the flood leaks in and that body simply stays hollow.
fn fill_enclosed(density: &mut [f32], n: usize) {
    let index = |x: usize, y: usize, z: usize| (z * n + y) * n + x;
    let mut outside = vec![false; density.len()];
    let mut stack = Vec::new();
    for a in 0..n {
        for b in 0..n {
            for (x, y, z) in [(0, a, b), (n - 1, a, b), (a, 0, b), (a, n - 1, b), (a, b, 0), (a, b, n - 1)] {
                let i = index(x, y, z);
                if density[i] == 0.0 && !outside[i] {
                    outside[i] = true;
                    stack.push((x, y, z));
                }
            }
        }
    }
    while let Some((x, y, z)) = stack.pop() {
        let mut visit = |x: usize, y: usize, z: usize| {
            let i = index(x, y, z);
            if density[i] == 0.0 && !outside[i] {
                outside[i] = true;
                stack.push((x, y, z));
            }
        };
        if x > 0 {
            visit(x - 1, y, z);
        }
        if x + 1 < n {
            visit(x + 1, y, z);
        }
        if y > 0 {
            visit(x, y - 1, z);
        }
        if y + 1 < n {
            visit(x, y + 1, z);
        }
        if z > 0 {
            visit(x, y, z - 1);
        }
        if z + 1 < n {
            visit(x, y, z + 1);
        }
    }
    for (d, out) in density.iter_mut().zip(outside) {
        if *d == 0.0 && !out {
            *d = 1.0;
        }
    }
}

/// Averages 2×2×2 cells (values clamped to 1 first, as the texture stores them).
fn downsample(src: &[f32], edge: usize) -> Vec<f32> {
    let half = edge / 2;
    let mut out = vec![0f32; half * half * half];
    for z in 0..half {
        for y in 0..half {
            for x in 0..half {
                let mut sum = 0.0;
                for dz in 0..2 {
                    for dy in 0..2 {
                        let row = ((2 * z + dz) * edge + 2 * y + dy) * edge + 2 * x;
                        sum += src[row].min(1.0) + src[row + 1].min(1.0);
                    }
                }
                out[(z * half + y) * half + x] = sum / 8.0;
            }
        }
    }
    out
}

/// The GPU side: an r8unorm 3D texture with a full mip chain and a trilinear sampler.
pub struct OccupancyTexture {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub sampler: wgpu::Sampler,
    pub cells: u32,
}

impl OccupancyTexture {
    pub fn new(device: &wgpu::Device, cells: u32) -> Self {
        let mip_level_count = cells.max(1).ilog2() + 1;
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("occupancy volume"),
            size: wgpu::Extent3d { width: cells, height: cells, depth_or_array_layers: cells },
            mip_level_count,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: wgpu::TextureFormat::R8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("occupancy sampler"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            address_mode_w: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        Self { texture, view, sampler, cells }
    }

    pub fn mip_count(&self) -> u32 {
        self.texture.mip_level_count()
    }

    /// Uploads every mip of `volume`, which must have been built for the same cell count.
    pub fn upload(&self, queue: &wgpu::Queue, volume: &OccupancyVolume) {
        debug_assert_eq!(volume.cells, self.cells);
        for (mip, bytes) in volume.mips.iter().enumerate().take(self.mip_count() as usize) {
            let edge = (self.cells >> mip).max(1);
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &self.texture,
                    mip_level: mip as u32,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                bytes,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(edge),
                    rows_per_image: Some(edge),
                },
                wgpu::Extent3d { width: edge, height: edge, depth_or_array_layers: edge },
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxstream_format::{BlockKey, PackedVoxel, oct_encode};

    fn block(level: u8, coord: [u32; 3], locals: &[[u32; 3]]) -> Block {
        let mut voxels: Vec<PackedVoxel> =
            locals.iter().map(|&p| PackedVoxel::new(p, 1, oct_encode([0.0, 0.0, 1.0]))).collect();
        voxels.sort_by_key(|v| v.morton());
        Block { key: BlockKey::new(level, coord[0], coord[1], coord[2]), voxels }
    }

    #[test]
    fn cell_count_is_a_bounded_power_of_two() {
        assert_eq!(cells_for_grid(512), 128);
        assert_eq!(cells_for_grid(128), 128);
        assert_eq!(cells_for_grid(64), 64);
        assert_eq!(cells_for_grid(0), 1);
    }

    #[test]
    fn coarse_voxels_fill_every_cell_they_cover() {
        // Grid 512, 128 cells of 4 units: a level-3 voxel (8 units) covers 2³ cells.
        let b = block(3, [0, 0, 0], &[[1, 2, 3]]);
        let vol = OccupancyVolume::build(512, [&b]);
        assert_eq!(vol.cells, 128);
        for (x, y, z) in [(2, 4, 6), (3, 5, 7), (2, 5, 6)] {
            assert_eq!(vol.value(0, x, y, z), 1.0);
        }
        assert_eq!(vol.value(0, 4, 4, 6), 0.0);
        assert_eq!(vol.value(0, 1, 4, 6), 0.0);
        let filled: usize = vol.mips[0].iter().filter(|&&v| v > 0).count();
        assert_eq!(filled, 8);
    }

    #[test]
    fn a_fine_surface_through_a_cell_reads_opaque() {
        // Grid 512, 4-unit cells: a 4×4 sheet of level-0 voxels crosses one cell.
        let sheet: Vec<[u32; 3]> = (0..4).flat_map(|x| (0..4).map(move |y| [x, y, 1])).collect();
        let b = block(0, [1, 0, 0], &sheet);
        let vol = OccupancyVolume::build(512, [&b]);
        assert_eq!(vol.value(0, 16, 0, 0), 1.0);
        // A single voxel in a cell is a sixteenth of a surface.
        let lone = block(0, [0, 0, 0], &[[9, 9, 9]]);
        let vol = OccupancyVolume::build(512, [&lone]);
        assert!((vol.value(0, 2, 2, 2) - 1.0 / 16.0).abs() < 1.0 / 255.0);
    }

    #[test]
    fn coarse_voxels_bring_their_coverage() {
        // Grid 512, 4-unit cells. A flat 8×8 sheet of level-0 voxels at z = 1
        // and the level-3 voxel standing for it (64 of 512 level-0 voxels).
        let sheet: Vec<[u32; 3]> = (0..8).flat_map(|x| (0..8).map(move |y| [x, y, 1])).collect();
        let fine = OccupancyVolume::build(512, [&block(0, [0, 0, 0], &sheet)]);
        let mut coarse = block(3, [0, 0, 0], &[[0, 0, 0]]);
        coarse.voxels[0] = coarse.voxels[0].with_coverage(voxstream_format::coverage_from_count(64, 3));
        let coarse = OccupancyVolume::build(512, [&coarse]);
        // Same occluding mass: equal from the mip that covers the voxel upwards.
        for mip in 1..4 {
            let (f, c) = (fine.value(mip, 0, 0, 0), coarse.value(mip, 0, 0, 0));
            assert!((f - c).abs() <= 2.0 / 255.0, "mip {mip}: fine {f}, coarse {c}");
        }
        assert!((fine.value(1, 0, 0, 0) - 0.5).abs() < 2.0 / 255.0);
        // A full-coverage coarse voxel would read twice as dense here.
        let full = OccupancyVolume::build(512, [&block(3, [0, 0, 0], &[[0, 0, 0]])]);
        assert_eq!(full.value(1, 0, 0, 0), 1.0);
    }

    #[test]
    fn mips_average_down_to_one_cell() {
        let b = block(3, [0, 0, 0], &[[0, 0, 0]]);
        let vol = OccupancyVolume::build(512, [&b]);
        assert_eq!(vol.mip_count(), 8);
        assert_eq!(vol.mips.last().unwrap().len(), 1);
        // 2³ full cells: mip 1 has one full cell, mip 2 an eighth, mip 3 a 64th.
        assert_eq!(vol.value(1, 0, 0, 0), 1.0);
        assert!((vol.value(2, 0, 0, 0) - 0.125).abs() < 1.0 / 255.0);
        assert!((vol.value(3, 0, 0, 0) - 1.0 / 64.0).abs() < 1.0 / 255.0);
        for (mip, bytes) in vol.mips.iter().enumerate() {
            assert_eq!(bytes.len(), (128usize >> mip).pow(3));
        }
    }

    /// The surface voxels of a cube `lo..hi` (level 0, one block), optionally with a hole.
    fn cube_shell(lo: u32, hi: u32, hole: bool) -> Block {
        let mut locals = Vec::new();
        for z in lo..hi {
            for y in lo..hi {
                for x in lo..hi {
                    let on_surface = [x, y, z].iter().any(|&c| c == lo || c == hi - 1);
                    let in_hole =
                        hole && z == lo && (lo + 4..lo + 12).contains(&x) && (lo + 4..lo + 12).contains(&y);
                    if on_surface && !in_hole {
                        locals.push([x, y, z]);
                    }
                }
            }
        }
        block(0, [0, 0, 0], &locals)
    }

    #[test]
    fn closed_shells_are_filled_and_open_ones_are_not() {
        // Grid 64, 64 cells: one cell per voxel.
        let closed = OccupancyVolume::build(64, [&cube_shell(8, 40, false)]);
        assert_eq!(closed.value(0, 20, 20, 20), 1.0, "inside a closed shell is solid");
        assert_eq!(closed.value(0, 50, 20, 20), 0.0, "outside stays empty");
        assert_eq!(closed.value(0, 2, 2, 2), 0.0);
        let open = OccupancyVolume::build(64, [&cube_shell(8, 40, true)]);
        assert_eq!(open.value(0, 20, 20, 20), 0.0, "a shell with a hole is not filled");
        assert_eq!(open.value(0, 8, 20, 20), 1.0, "its walls are");
    }

    #[test]
    fn voxels_outside_the_grid_are_ignored() {
        // A 32-unit grid with one 64-voxel level-0 block: half of it lies outside.
        let b = block(0, [0, 0, 0], &[[40, 0, 0], [1, 1, 1]]);
        let vol = OccupancyVolume::build(32, [&b]);
        assert_eq!(vol.cells, 32);
        assert_eq!(vol.mips[0].iter().filter(|&&v| v > 0).count(), 1);
    }
}
