//! The AO's multi-resolution occupancy structure (issue 9, item 1): a clipmap
//! of nested levels around the camera, built and kept up to date on the GPU
//! by compute passes (shaders/clipmap_clear.wgsl, shaders/clipmap_splat.wgsl)
//! and traced by shaders/ao.wgsl.
//!
//! - **Levels.** Level k is a cube of [`ClipmapLayout::cells`]³ cells of edge
//!   `finest_cell · 2^k` grid units (so each covers twice the extent of the one
//!   inside it). The finest cell is the finest drawn voxel edge; there are as
//!   many levels as it takes for the coarsest to hold the whole scene grid, so
//!   occluders outside the view or behind the camera count everywhere.
//! - **Placement.** Level k's origin is an integer cell coordinate
//!   ([`ClipmapLayout::origin`]): the eye plus a quarter of the level's extent
//!   along the view direction, snapped to the level's cells, then clamped so
//!   the level stays on the scene grid (a level the grid's size is centred
//!   on it, so it holds all of it). Cells outside the scene grid are empty
//!   by definition: the tracer reads them as 0 without a load, so a level
//!   whose face lies on the grid's face holds samples right up to it.
//!   Addresses are integer grid cells, never world coordinates, so a scene
//!   moved by 1e6 units is the same clipmap.
//! - **Storage.** One storage buffer of u32: level k's cells follow level
//!   k−1's, cell (x, y, z) of the grid at storage slot (x mod N, y mod N,
//!   z mod N) (toroidal addressing), so when a level moves only the cells
//!   that newly enter it are cleared and splatted; the rest stay. A slot is
//!   [`CELL_WORDS`] words: the cell's opacity to rays along x, y and z.
//! - **Texels.** The splats add up in the buffer (WebGPU's atomics need
//!   one); the trace reads a copy in one 3D texture ([`TEXEL_FORMAT`]), so
//!   that a trilinear read is one filtered sample instead of eight cells of
//!   three words (shaders/clipmap_texels.wgsl). Level k is the block of
//!   (N + 1)³ texels from depth k·(N + 1), slot s at texel s, and texel N on
//!   an axis repeats slot 0 (an apron), so a filtered read between slot N − 1
//!   and the slot after it, 0 (toroidal), stays inside its level's block.
//!   Each update copies, per level, the box around the cells it changed.
//! - **Content.** A cell holds its surface opacity per axis as fixed point
//!   ([`DENSITY_ONE`] = 1): each voxel of a source block adds, on each axis
//!   it blocks ([`voxel_axes`]: those of its exposed faces), its level-0
//!   equivalent (its prefiltered coverage · its volume in level-0 voxels) /
//!   cell edge², clamped to 1 per voxel ([`voxel_density_fixed`], integer math
//!   so the GPU and the CPU model agree exactly). Adding and subtracting a
//!   block are exact inverses (atomicAdd / atomicSub), so blocks that arrive
//!   or leave are splatted in or out of just their own cells.
//! - **Sources.** Level k splats the drawn blocks with each finer than its
//!   cell replaced by its decoded ancestor whose voxel is one cell (the cut the
//!   volume used), so a coarse level costs a few coarse blocks, and the voxel
//!   words (position and coverage, 4 bytes a voxel) go to the GPU once per
//!   source block and stay there while any level uses the block.
//!
//! The invariant, checked against [`ClipmapModel`] by tests/tests/ao_clipmap.rs:
//! every cell of level k inside its region holds the sum over level k's
//! sources of their densities there.

use std::collections::BTreeSet;

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use glam::{Mat4, Vec3, Vec4};
use voxstream_format::{BLOCK_SIZE, Block, BlockKey};

use crate::shaders;

/// Cells per level edge (the default).
pub const CLIP_CELLS: u32 = 128;
/// Most levels.
pub const MAX_CLIP_LEVELS: u32 = 8;
/// Fixed-point opacity 1 in a cell.
pub const DENSITY_ONE: u32 = 4096;
/// u32 words a cell holds: its opacity to rays along x, y and z
/// ([`voxel_axes`]), side by side so a cell's three are one cache line.
pub const CELL_WORDS: u32 = 3;
/// Bytes between dispatch records in the dispatch uniform buffer (the
/// alignment of a dynamic uniform offset).
const DISPATCH_STRIDE: u64 = 256;
/// Invocations per workgroup of the compute shaders.
const WORKGROUP: u32 = 64;
/// Format of the levels' filterable texture (clipmap_texels.wgsl): the three
/// axes' opacities and their bound, 8 bits each: the precision of the
/// blocks' coverage the cells are splatted from. (Half floats, at twice the
/// bytes, gave the same V to four digits on every benchmark view and traced
/// 1.3 times slower on lavapipe: docs/ao-benchmark.md, "Filtered texels".)
pub const TEXEL_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Bytes a texel of [`TEXEL_FORMAT`] takes.
pub const TEXEL_BYTES: u64 = 4;

/// The clipmap's shape for one scene and view state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ClipmapLayout {
    /// Cells per level edge (even).
    pub cells: u32,
    /// Edge of a finest-level cell in grid units (a power of two).
    pub finest_cell: u32,
    /// Levels, 1..=[`MAX_CLIP_LEVELS`].
    pub levels: u32,
}

/// Levels it takes for the coarsest to hold `grid_resolution` cells of the
/// finest size with a cell to spare on each side.
fn levels_to_cover(grid_resolution: u32, finest_cell: u32, cells: u32) -> u32 {
    let mut levels = 1;
    while ((cells.saturating_sub(2).max(1) as u64) * (finest_cell as u64)) << (levels - 1)
        < grid_resolution.max(1) as u64
    {
        levels += 1;
    }
    levels
}

impl ClipmapLayout {
    /// The layout for a `grid_resolution`³ scene whose finest drawn voxel is
    /// `finest_voxel` grid units: the finest cell is that voxel, or coarser
    /// where [`MAX_CLIP_LEVELS`] levels would not reach across the grid.
    ///
    /// Levels stop once the coarsest holds the grid. More levels (up to the
    /// widest cone's width, so far samples of wide cones read a level of
    /// their own width) were measured: parallel plates RMSE 0.054 → 0.041,
    /// but the closed room 0.031 → 0.042 and the Cornell box 0.041 → 0.043
    /// (wide cones over-occlude in rooms), so they are not used.
    pub fn for_scene(grid_resolution: u32, finest_voxel: u32, cells: u32) -> Self {
        let cells = cells.max(8).next_power_of_two();
        let mut finest_cell = finest_voxel.clamp(1, 1 << 30).next_power_of_two();
        while levels_to_cover(grid_resolution, finest_cell, cells) > MAX_CLIP_LEVELS {
            finest_cell *= 2;
        }
        Self { cells, finest_cell, levels: levels_to_cover(grid_resolution, finest_cell, cells) }
    }

    /// Edge of a level-`level` cell in grid units.
    pub fn cell(&self, level: u32) -> u32 {
        self.finest_cell << level
    }

    /// Cells in one level.
    pub fn level_len(&self) -> u64 {
        (self.cells as u64).pow(3)
    }

    /// u32 words of one level's cells ([`CELL_WORDS`] a cell).
    pub fn level_words(&self) -> u64 {
        self.level_len() * CELL_WORDS as u64
    }

    /// Level `level`'s first cell (grid cells of that level) for an eye at
    /// `eye` looking along `forward` (grid units): centred a quarter of its
    /// extent ahead of the eye, clamped to the grid (a level larger than the
    /// grid is centred on it). Non-finite input falls back to the grid centre.
    pub fn origin(&self, level: u32, eye: Vec3, forward: Vec3, grid_resolution: u32) -> [i32; 3] {
        let cell = self.cell(level) as f64;
        let n = self.cells as i64;
        let res = grid_resolution.max(1) as f64;
        let forward = if forward.is_finite() { forward.normalize_or_zero() } else { Vec3::ZERO };
        let centre =
            if eye.is_finite() { eye + forward * (0.25 * n as f32 * cell as f32) } else { Vec3::NAN };
        let extent_cells = (res / cell).ceil() as i64;
        std::array::from_fn(|a| {
            let c = centre[a] as f64;
            let c = if c.is_finite() { c.clamp(-4.0 * res, 5.0 * res) } else { res / 2.0 };
            let (lo, hi) = (-1i64, extent_cells + 1 - n);
            // A level no larger than the grid plus a cell a side is centred
            // on it: it then holds the whole grid, where following the eye
            // would leave a one-cell layer at one face to a coarser level.
            let o = if hi <= lo + 2 {
                (lo + hi).div_euclid(2)
            } else {
                ((c / cell).floor() as i64 - n / 2).clamp(lo, hi)
            };
            o as i32
        })
    }
}

/// A box of grid cells of one level, `min` inclusive, `max` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CellBox {
    pub min: [i32; 3],
    pub max: [i32; 3],
}

impl CellBox {
    pub const EMPTY: CellBox = CellBox { min: [0; 3], max: [0; 3] };

    pub fn region(origin: [i32; 3], cells: u32) -> Self {
        Self { min: origin, max: origin.map(|o| o + cells as i32) }
    }

    pub fn contains(&self, c: [i64; 3]) -> bool {
        (0..3).all(|a| c[a] >= self.min[a] as i64 && c[a] < self.max[a] as i64)
    }

    /// Whether `inner` lies inside this box.
    pub fn covers(&self, inner: &CellBox) -> bool {
        (0..3).all(|a| inner.min[a] >= self.min[a] && inner.max[a] <= self.max[a])
    }

    fn intersects(&self, other: &CellBox) -> bool {
        (0..3).all(|a| self.min[a] < other.max[a] && other.min[a] < self.max[a])
    }

    fn intersection(&self, other: &CellBox) -> Option<CellBox> {
        self.intersects(other).then(|| CellBox {
            min: std::array::from_fn(|a| self.min[a].max(other.min[a])),
            max: std::array::from_fn(|a| self.max[a].min(other.max[a])),
        })
    }

    fn union(&self, other: &CellBox) -> CellBox {
        CellBox {
            min: std::array::from_fn(|a| self.min[a].min(other.min[a])),
            max: std::array::from_fn(|a| self.max[a].max(other.max[a])),
        }
    }

    fn size(&self) -> [u32; 3] {
        std::array::from_fn(|a| (self.max[a] - self.min[a]).max(0) as u32)
    }
}

/// The cells of `level` a block overlaps (its bounds, rounded out to cells).
fn block_cells(key: &BlockKey, cell: u32) -> CellBox {
    let edge = (BLOCK_SIZE as u64) << key.level;
    let cell = cell as u64;
    let min = key.coord().map(|c| c as u64 * edge);
    CellBox {
        min: min.map(|m| (m / cell).min(i32::MAX as u64) as i32),
        max: min.map(|m| (m + edge).div_ceil(cell).min(i32::MAX as u64) as i32),
    }
}

/// The fixed-point density one voxel of `coverage` (0..=255), edge
/// `voxel_edge`, adds to each cell of edge `cell` it overlaps:
/// coverage/255 · voxel_edge³ / cell² spread over the (voxel_edge/cell)³
/// cells of a voxel larger than a cell, clamped to [`DENSITY_ONE`]. Integer
/// arithmetic (the edges are powers of two), as in clipmap_splat.wgsl.
pub fn voxel_density_fixed(coverage: u32, voxel_edge: u32, cell: u32) -> u32 {
    let t = coverage.min(255) * DENSITY_ONE;
    let (e, c) = (voxel_edge.max(1).ilog2() as i32, cell.max(1).ilog2() as i32);
    // A voxel no larger than a cell: coverage · e³/c²; larger: coverage · c per cell.
    let shift = if e <= c { 3 * e - 2 * c } else { c };
    let q = if shift >= 8 {
        if coverage > 0 { DENSITY_ONE } else { 0 }
    } else if shift >= 0 {
        (t << shift) / 255
    } else if -shift >= 24 {
        0
    } else {
        t / (255u32 << -shift)
    };
    q.min(DENSITY_ONE)
}

/// The axes along which a voxel with exposed-face mask `faces` blocks rays:
/// those of its exposed faces (bit 2a or 2a + 1: axis a, as in
/// [`voxstream_format::Face`]); all three for a voxel with none (inside a solid).
///
/// Why: voxels stand for a surface. A voxel of a floor (faces ±y exposed)
/// blocks rays that cross the floor, not rays running along it; a cell
/// crossed by a floor is opaque along y but open along x and z. Counted
/// alike on every axis (as before), a coarse cell a floor runs through was
/// opaque to the cones running along the floor above it, which darkened
/// every room (seed 001's anisotropic opacity; docs/ao-benchmark.md,
/// "Opacity per axis").
pub fn voxel_axes(faces: u8) -> [bool; 3] {
    let on = |a: usize| faces & (3 << (2 * a)) != 0 || faces & 63 == 0;
    [on(0), on(1), on(2)]
}

/// The CPU model of the clipmap: what every cell of a level must hold for a
/// set of sources and a region (the GPU's result is compared with it).
#[derive(Debug, Clone, PartialEq)]
pub struct ClipmapModel {
    pub layout: ClipmapLayout,
    /// Per level, its cells in storage order (toroidal slots), as on the GPU.
    pub levels: Vec<Vec<u32>>,
}

impl ClipmapModel {
    /// Splats `sources[k]` into level k over the region at `origins[k]`.
    pub fn build(layout: ClipmapLayout, origins: &[[i32; 3]], sources: &[Vec<&Block>]) -> Self {
        let n = layout.cells as usize;
        let levels = (0..layout.levels as usize)
            .map(|k| {
                let mut cells = vec![0u32; n * n * n * CELL_WORDS as usize];
                let region = CellBox::region(origins[k], layout.cells);
                let cell = layout.cell(k as u32);
                for block in sources.get(k).into_iter().flatten() {
                    let edge = 1u32 << block.key.level;
                    let origin = block.key.coord().map(|c| c as i64 * BLOCK_SIZE as i64 * edge as i64);
                    let span = (edge / cell).max(1) as i64;
                    for v in &block.voxels {
                        let q = voxel_density_fixed(v.coverage() as u32, edge, cell);
                        let axes = voxel_axes(v.faces());
                        let local = v.local();
                        let first: [i64; 3] = std::array::from_fn(|a| {
                            (origin[a] + local[a] as i64 * edge as i64) / cell as i64
                        });
                        for z in first[2]..first[2] + span {
                            for y in first[1]..first[1] + span {
                                for x in first[0]..first[0] + span {
                                    if region.contains([x, y, z]) {
                                        let at = slot([x, y, z], n) * CELL_WORDS as usize;
                                        for (a, _) in axes.iter().enumerate().filter(|(_, on)| **on) {
                                            cells[at + a] += q;
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                cells
            })
            .collect();
        Self { layout, levels }
    }
}

/// The storage slot of grid cell `c` in a level of `n`³ cells.
fn slot(c: [i64; 3], n: usize) -> usize {
    let m = c.map(|v| v.rem_euclid(n as i64) as usize);
    (m[2] * n + m[1]) * n + m[0]
}

/// One level's state on the CPU: where it is and what it was splatted from.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ClipLevel {
    /// First cell of the region its cells hold; `None` before the first build.
    pub origin: Option<[i32; 3]>,
    /// The blocks splatted into it.
    pub sources: BTreeSet<BlockKey>,
}

/// The trace's view of the clipmap (group 0, binding 3; `Clipmap` in frame.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ClipmapUniform {
    /// x: levels, y: cells per edge, z: finest cell edge (grid units), w: 1 = trace the clipmap.
    pub info: [f32; 4],
    /// Per level: its first cell (grid cells of that level), w unused.
    pub origins: [[i32; 4]; MAX_CLIP_LEVELS as usize],
}

/// One compute dispatch's parameters (`Dispatch` in clipmap_clear.wgsl and clipmap_splat.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct DispatchRecord {
    /// xyz: the block's corner (grid units), w: its voxel edge.
    block: [u32; 4],
    /// x: level, y: its cell edge, z: cells per edge, w: 1 = subtract.
    level: [u32; 4],
    /// xyz: the level's first cell, w: the block's voxel count.
    region: [i32; 4],
    /// Cells already right (skipped): [keep_min, keep_max).
    keep_min: [i32; 4],
    keep_max: [i32; 4],
}

enum Op {
    Clear { level: u32, origin: [i32; 3], keep: CellBox },
    Splat { level: u32, key: BlockKey, origin: [i32; 3], keep: CellBox, subtract: bool },
}

/// What the last updates did (the viewer's stats and the tests).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ClipmapCounters {
    /// Updates that changed something.
    pub updates: u64,
    /// Level clears (whole or the newly exposed slabs of a scroll).
    pub clears: u64,
    /// Block splats (in or out).
    pub splats: u64,
    /// Voxels those splats read.
    pub voxels_splatted: u64,
    /// Source blocks whose voxel words were uploaded.
    pub blocks_uploaded: u64,
    /// Full rebuilds (layout changes).
    pub rebuilds: u64,
    /// Times the source blocks' voxel words moved into a larger buffer.
    pub word_moves: u64,
}

/// Bytes of `levels` levels of `cells`³: their cells ([`CELL_WORDS`] u32 a
/// cell) and their block of the texel atlas ((`cells` + 1)³ texels a level).
fn level_bytes(cells: u32, levels: u32) -> (u64, u64) {
    let (cells, levels) = (cells as u64, levels as u64);
    (levels * cells.pow(3) * CELL_WORDS as u64 * 4, levels * (cells + 1).pow(3) * TEXEL_BYTES)
}

/// The levels' filterable copy of their cells (clipmap_texels.wgsl), what
/// the trace samples: `levels` blocks of (`cells` + 1)³ texels stacked in
/// depth (a 1³ placeholder before the first layout).
fn texel_atlas(device: &wgpu::Device, cells: u32, levels: u32) -> wgpu::Texture {
    let edge = cells + 1;
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("clipmap texels"),
        size: wgpu::Extent3d { width: edge, height: edge, depth_or_array_layers: edge * levels },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format: TEXEL_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

/// One texel copy's parameters (`TexelDispatch` in clipmap_texels.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct TexelRecord {
    /// xyz: the box's first cell, w: the level.
    box_min: [i32; 4],
    /// xyz: the box's size in cells, w: cells per edge.
    box_size: [u32; 4],
}

/// The clipmap on the GPU with its CPU bookkeeping.
pub struct OccupancyClipmap {
    /// Cells per level edge.
    cells: u32,
    /// The levels of the current layout, cells³ u32 each (grown when a layout needs more).
    pub cells_buffer: wgpu::Buffer,
    /// The levels' cells as one filterable texture ([`texel_atlas`]): the
    /// trace reads it, the cells buffer is where the splats add up (atomics
    /// need a buffer).
    texels: wgpu::Texture,
    texel_view: wgpu::TextureView,
    /// Linear; the aprons make each level's wrap (toroidal addressing).
    pub texel_sampler: wgpu::Sampler,
    texel_pipeline: wgpu::ComputePipeline,
    texel_layout: wgpu::BindGroupLayout,
    texel_dispatch_buffer: wgpu::Buffer,
    /// The copy's bind groups, one a level (each binds that level's range of
    /// the cells buffer), kept while its buffers and texture stay (in a
    /// browser each one made is a call across to the GPU process).
    texel_groups: Vec<wgpu::BindGroup>,
    /// [`ClipmapUniform`].
    pub uniform_buffer: wgpu::Buffer,
    layout: Option<ClipmapLayout>,
    levels: Vec<ClipLevel>,
    /// Voxel words of the source blocks (position, faces and coverage).
    voxel_words: VoxelWordArena,
    dispatch_buffer: wgpu::Buffer,
    clear_pipeline: wgpu::ComputePipeline,
    splat_pipeline: wgpu::ComputePipeline,
    clear_layout: wgpu::BindGroupLayout,
    splat_layout: wgpu::BindGroupLayout,
    pub counters: ClipmapCounters,
    /// The device's largest storage binding in u32 words, read once: in a
    /// browser each `limits()` is a call into JavaScript.
    max_binding_words: u64,
    /// The most words the source-voxel buffer may grow to under the GPU
    /// budget ([`OccupancyClipmap::limit_source_bytes`]); no limit by default.
    source_word_limit: u64,
    /// Test only: scrolls leave the newly exposed cells as they were (a deliberately wrong clipmap).
    pub skip_scroll_clear: bool,
    /// Test only: updates leave the level textures as they were (textures behind their cells).
    pub skip_texel_copy: bool,
}

fn layout_entry(binding: u32, ty: wgpu::BufferBindingType, dynamic: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer { ty, has_dynamic_offset: dynamic, min_binding_size: None },
        count: None,
    }
}

fn compute_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    source: &str,
    entry: &str,
) -> wgpu::ComputePipeline {
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(entry),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(entry),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: Some(&pipeline_layout),
        module: &module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// The source blocks' voxel words in one storage buffer, a range a block.
/// A splat finds its block's words by the first word in its dispatch record,
/// so an update binds one buffer for all its splats instead of making a
/// buffer and a bind group per block: in a browser every WebGPU call costs
/// the page's main thread, and the first frames splat every block.
///
/// Ranges are handed out in order and never reused in place: commands
/// already submitted may still read them. A batch that does not fit moves
/// the live blocks (from their CPU copies) into a new buffer with room to spare.
struct VoxelWordArena {
    buffer: wgpu::Buffer,
    /// Each block's first word, and its words (for that move).
    blocks: HashMap<BlockKey, (u32, Vec<u32>)>,
    /// The first word never handed out.
    end: u64,
    /// Words of the blocks held.
    live: u64,
    /// Times the live words moved into a new buffer.
    moves: u64,
}

/// Words of the smallest arena: a few small blocks.
const ARENA_MIN_WORDS: u64 = 1 << 14;

impl VoxelWordArena {
    fn new(device: &wgpu::Device) -> Self {
        Self {
            buffer: Self::buffer(device, ARENA_MIN_WORDS),
            blocks: HashMap::default(),
            end: 0,
            live: 0,
            moves: 0,
        }
    }

    fn buffer(device: &wgpu::Device, words: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("clipmap source voxels"),
            size: words.max(1) * 4,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    fn contains(&self, key: &BlockKey) -> bool {
        self.blocks.contains_key(key)
    }

    /// A block's first word and word count.
    fn range(&self, key: &BlockKey) -> Option<(u32, u32)> {
        self.blocks.get(key).map(|(first, words)| (*first, words.len() as u32))
    }

    /// Adds blocks not held yet, with one buffer write for all of them.
    /// Returns the blocks refused: those that do not fit `max_words` beside the live ones.
    fn insert_many(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        mut new: Vec<(BlockKey, Vec<u32>)>,
        max_words: u64,
    ) -> HashSet<BlockKey> {
        let mut refused = HashSet::default();
        let mut need: u64 = new.iter().map(|(_, w)| w.len() as u64).sum();
        while self.live + need > max_words {
            let Some((key, words)) = new.pop() else { break };
            need -= words.len() as u64;
            refused.insert(key);
        }
        if new.is_empty() {
            return refused;
        }
        let capacity = self.buffer.size() / 4;
        if self.end + need > capacity {
            // Room to spare, within the binding limit (which the live and new words fit, above).
            let words = (2 * (self.live + need)).max(ARENA_MIN_WORDS).min(max_words).max(self.live + need);
            self.buffer = Self::buffer(device, words);
            // Live blocks first, in key order (deterministic), then the new ones below.
            let mut keys: Vec<BlockKey> = self.blocks.keys().copied().collect();
            keys.sort_unstable();
            let mut moved = Vec::with_capacity(self.live as usize);
            for key in keys {
                let (first, words) = self.blocks.get_mut(&key).expect("listed");
                *first = moved.len() as u32;
                moved.extend_from_slice(words);
            }
            if !moved.is_empty() {
                queue.write_buffer(&self.buffer, 0, bytemuck::cast_slice(&moved));
            }
            self.end = moved.len() as u64;
            self.moves += 1;
        }
        let mut batch = Vec::with_capacity(need as usize);
        for (key, words) in new {
            let first = self.end + batch.len() as u64;
            batch.extend_from_slice(&words);
            self.live += words.len() as u64;
            self.blocks.insert(key, (first as u32, words));
        }
        if !batch.is_empty() {
            queue.write_buffer(&self.buffer, self.end * 4, bytemuck::cast_slice(&batch));
        }
        self.end += batch.len() as u64;
        refused
    }

    /// Drops the blocks `keep` refuses (their words stay in the buffer until the next move).
    fn retain(&mut self, mut keep: impl FnMut(&BlockKey) -> bool) {
        let live = &mut self.live;
        self.blocks.retain(|k, (_, words)| {
            let kept = keep(k);
            if !kept {
                *live -= words.len() as u64;
            }
            kept
        });
    }
}

impl OccupancyClipmap {
    /// A clipmap of `cells`³ levels; its cells are allocated by the first
    /// [`OccupancyClipmap::update`] (a placeholder until then).
    pub fn new(device: &wgpu::Device, cells: u32) -> Self {
        // A power of two: the trace finds a cell's toroidal slot by a mask (ao.wgsl).
        let cells = cells.max(8).next_power_of_two();
        let uniform_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("clipmap uniform"),
            size: size_of::<ClipmapUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let clear_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("clipmap clear"),
            entries: &[
                layout_entry(0, wgpu::BufferBindingType::Uniform, true),
                layout_entry(1, wgpu::BufferBindingType::Storage { read_only: false }, false),
            ],
        });
        let splat_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("clipmap splat"),
            entries: &[
                layout_entry(0, wgpu::BufferBindingType::Uniform, true),
                layout_entry(1, wgpu::BufferBindingType::Storage { read_only: false }, false),
                layout_entry(2, wgpu::BufferBindingType::Storage { read_only: true }, false),
            ],
        });
        let texel_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("clipmap texels"),
            entries: &[
                layout_entry(0, wgpu::BufferBindingType::Uniform, true),
                layout_entry(1, wgpu::BufferBindingType::Storage { read_only: true }, false),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: TEXEL_FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D3,
                    },
                    count: None,
                },
            ],
        });
        let texels = texel_atlas(device, 0, 1);
        let texel_view = texels.create_view(&Default::default());
        let texel_sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("clipmap texels"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Self {
            cells,
            cells_buffer: Self::cells_buffer(device, 4),
            texels,
            texel_view,
            texel_sampler,
            texel_pipeline: compute_pipeline(
                device,
                &texel_layout,
                shaders::CLIPMAP_TEXELS_WGSL,
                "copy_texels",
            ),
            texel_layout,
            texel_dispatch_buffer: Self::dispatch_buffer(device, MAX_CLIP_LEVELS as u64),
            texel_groups: Vec::new(),
            uniform_buffer,
            layout: None,
            levels: Vec::new(),
            voxel_words: VoxelWordArena::new(device),
            dispatch_buffer: Self::dispatch_buffer(device, 64),
            clear_pipeline: compute_pipeline(
                device,
                &clear_layout,
                shaders::CLIPMAP_CLEAR_WGSL,
                "clear_cells",
            ),
            splat_pipeline: compute_pipeline(
                device,
                &splat_layout,
                shaders::CLIPMAP_SPLAT_WGSL,
                "splat_block",
            ),
            clear_layout,
            splat_layout,
            counters: ClipmapCounters::default(),
            max_binding_words: device.limits().max_storage_buffer_binding_size / 4,
            source_word_limit: u64::MAX,
            skip_scroll_clear: false,
            skip_texel_copy: false,
        }
    }

    fn cells_buffer(device: &wgpu::Device, bytes: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("clipmap cells"),
            size: bytes.max(4),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    fn dispatch_buffer(device: &wgpu::Device, records: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("clipmap dispatches"),
            size: records.max(1) * DISPATCH_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Cells per level edge.
    pub fn cells(&self) -> u32 {
        self.cells
    }

    /// The layout of the last update (`None` before the first).
    pub fn layout(&self) -> Option<ClipmapLayout> {
        self.layout
    }

    /// The levels' state.
    pub fn levels(&self) -> &[ClipLevel] {
        &self.levels
    }

    /// The levels' texture's view (the frame's bind group).
    pub fn texel_view(&self) -> &wgpu::TextureView {
        &self.texel_view
    }

    /// The levels' texture ([`texel_atlas`]).
    pub fn texels(&self) -> &wgpu::Texture {
        &self.texels
    }

    /// Bytes of the cells buffer, the levels' textures and the source blocks' voxel words.
    pub fn gpu_bytes(&self) -> u64 {
        self.cells_buffer.size() + self.texel_bytes() + self.voxel_words_bytes()
    }

    fn texel_bytes(&self) -> u64 {
        let t = &self.texels;
        t.width() as u64 * t.height() as u64 * t.depth_or_array_layers() as u64 * TEXEL_BYTES
    }

    fn voxel_words_bytes(&self) -> u64 {
        self.voxel_words.buffer.size()
    }

    /// Bytes of the buffer of source voxels (it grows as sources arrive).
    pub fn source_bytes(&self) -> u64 {
        self.voxel_words_bytes()
    }

    /// Caps what the buffer of source voxels may grow to (the residency's
    /// headroom plus what it holds now); sources that do not fit are refused
    /// and added by a later update.
    pub fn limit_source_bytes(&mut self, bytes: u64) {
        self.source_word_limit = bytes / 4;
    }

    /// Allocates the cells and the levels' texture for the most levels any
    /// layout of a `grid_resolution`³ scene can have, once (before streaming
    /// starts): the budget reserves them from the first frame anyway
    /// ([`OccupancyClipmap::budget_bytes`]), and allocating them when a
    /// layout first needs them put a 200 MB allocation into a streaming frame
    /// each time the finest drawn level fell (10–12 ms of main thread
    /// natively at 32768³: docs/streaming.md). Returns whether the buffers
    /// were replaced (bind groups naming them must be remade).
    pub fn reserve(&mut self, device: &wgpu::Device, grid_resolution: u32) -> bool {
        let most = self.most_levels(grid_resolution);
        self.reserve_levels(device, most.cells, most.levels)
    }

    /// The layout of a `grid_resolution`³ scene with the most levels (level-0
    /// voxels drawn): what [`OccupancyClipmap::reserve`] allocates and
    /// [`OccupancyClipmap::budget_bytes`] counts.
    fn most_levels(&self, grid_resolution: u32) -> ClipmapLayout {
        ClipmapLayout::for_scene(grid_resolution, 1, self.cells)
    }

    /// Cells and texels for `levels` levels of `cells`³, where the present ones are smaller.
    fn reserve_levels(&mut self, device: &wgpu::Device, cells: u32, levels: u32) -> bool {
        let mut replaced = false;
        let (bytes, _) = level_bytes(cells, levels);
        if self.cells_buffer.size() < bytes {
            self.cells_buffer = Self::cells_buffer(device, bytes);
            self.texel_groups.clear();
            replaced = true;
        }
        let edge = cells + 1;
        if self.texels.width() != edge || self.texels.depth_or_array_layers() < edge * levels {
            self.texels = texel_atlas(device, cells, levels);
            self.texel_groups.clear();
            self.texel_view = self.texels.create_view(&Default::default());
            replaced = true;
        }
        replaced
    }

    /// What the residency budget counts for the clipmap of a
    /// `grid_resolution`³ scene: the cells of the most levels any layout of
    /// it can have (reserved from the first frame, so the fixed bytes do not
    /// jump when the cells are allocated) plus the voxel words held now.
    pub fn budget_bytes(&self, grid_resolution: u32) -> u64 {
        let most = self.most_levels(grid_resolution);
        let (reserve, texels) = level_bytes(most.cells, most.levels);
        reserve.max(self.cells_buffer.size()) + texels.max(self.texel_bytes()) + self.voxel_words_bytes()
    }

    /// The trace's uniform: the layout and the levels' origins; `enabled`
    /// false (or no layout yet) makes the trace read the volume instead.
    pub fn uniform(&self, enabled: bool) -> ClipmapUniform {
        let mut origins = [[0i32; 4]; MAX_CLIP_LEVELS as usize];
        for (o, level) in origins.iter_mut().zip(&self.levels) {
            let [x, y, z] = level.origin.unwrap_or([0; 3]);
            *o = [x, y, z, 0];
        }
        match self.layout {
            Some(l) => ClipmapUniform {
                info: [
                    l.levels as f32,
                    l.cells as f32,
                    l.finest_cell as f32,
                    if enabled { 1.0 } else { 0.0 },
                ],
                origins,
            },
            None => ClipmapUniform { info: [1.0, self.cells as f32, 1.0, 0.0], origins },
        }
    }

    /// Brings the clipmap to `layout`, the levels placed for `eye` and
    /// `forward` (grid units) and splatted from `sources[k]` (level k's
    /// blocks; `block` gives their voxels the first time a block is used).
    /// Only what changed is cleared or splatted, recorded into `encoder` (the
    /// caller submits it, with the frame; this call's queue writes land
    /// first). Returns whether the cells buffer was replaced (the frame's bind
    /// group must be rebuilt).
    #[allow(clippy::too_many_arguments)]
    pub fn update<'a>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        grid_resolution: u32,
        layout: ClipmapLayout,
        eye: Vec3,
        forward: Vec3,
        sources: &[Vec<BlockKey>],
        block: impl Fn(&BlockKey) -> Option<&'a Block>,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) -> bool {
        let layout = ClipmapLayout { levels: layout.levels.clamp(1, MAX_CLIP_LEVELS), ..layout };
        let mut replaced = false;
        let mut ops = Vec::new();
        // Levels that moved (or were rebuilt): (level, new region, cells kept).
        let mut moved = Vec::new();
        if self.layout != Some(layout) {
            replaced = self.reserve_levels(
                device,
                layout.cells,
                layout.levels.max(self.most_levels(grid_resolution).levels),
            );
            self.layout = Some(layout);
            self.levels = vec![ClipLevel::default(); layout.levels as usize];
            self.counters.rebuilds += 1;
        }
        for k in 0..layout.levels {
            let level = &mut self.levels[k as usize];
            let origin = layout.origin(k, eye, forward, grid_resolution);
            let region = CellBox::region(origin, layout.cells);
            let cell = layout.cell(k);
            match level.origin {
                Some(old) if old == origin => {}
                old => {
                    // Cells still inside the old region hold the right sums: keep them.
                    let keep = old.map_or(CellBox::EMPTY, |o| CellBox::region(o, layout.cells));
                    moved.push((k, region, keep));
                    if !(self.skip_scroll_clear && old.is_some()) {
                        ops.push(Op::Clear { level: k, origin, keep });
                    }
                    for key in &level.sources {
                        let b = block_cells(key, cell);
                        if b.intersects(&region) && !keep.covers(&b) {
                            ops.push(Op::Splat { level: k, key: *key, origin, keep, subtract: false });
                        }
                    }
                    level.origin = Some(origin);
                }
            }
            let wanted: BTreeSet<BlockKey> = sources.get(k as usize).into_iter().flatten().copied().collect();
            for key in level.sources.difference(&wanted) {
                if block_cells(key, cell).intersects(&region) {
                    ops.push(Op::Splat { level: k, key: *key, origin, keep: CellBox::EMPTY, subtract: true });
                }
            }
            for key in wanted.difference(&level.sources) {
                if block_cells(key, cell).intersects(&region) {
                    ops.push(Op::Splat {
                        level: k,
                        key: *key,
                        origin,
                        keep: CellBox::EMPTY,
                        subtract: false,
                    });
                }
            }
            level.sources = wanted;
        }
        // Voxel words for every block a splat reads (a removed block's are still here).
        let mut new_words: Vec<(BlockKey, Vec<u32>)> = Vec::new();
        let mut listed: HashSet<BlockKey> = HashSet::default();
        for op in &ops {
            if let Op::Splat { key, .. } = op
                && !self.voxel_words.contains(key)
                && listed.insert(*key)
                && let Some(b) = block(key)
            {
                new_words.push((*key, b.voxels.iter().map(|v| v.pos_faces).collect()));
            }
        }
        self.counters.blocks_uploaded += new_words.len() as u64;
        let max_words = self.max_binding_words.min(self.source_word_limit);
        let refused = self.voxel_words.insert_many(device, queue, new_words, max_words);
        self.counters.word_moves = self.voxel_words.moves;
        if !refused.is_empty() {
            // Never added, so never to be subtracted: a later update adds them when there is room.
            ops.retain(|op| !matches!(op, Op::Splat { key, .. } if refused.contains(key)));
            for level in &mut self.levels {
                level.sources.retain(|k| !refused.contains(k));
            }
        }
        if !ops.is_empty() {
            self.encode(device, queue, encoder, layout, &ops, timer);
            if !self.skip_texel_copy {
                let boxes = texel_boxes(layout, &ops, &moved);
                self.encode_texels(device, queue, encoder, layout, &boxes, timer);
            }
            self.counters.updates += 1;
        }
        // Voxel words no level uses any more go (the commands above keep theirs alive).
        let used: BTreeSet<BlockKey> = self.levels.iter().flat_map(|l| l.sources.iter().copied()).collect();
        self.voxel_words.retain(|k| used.contains(k));
        queue.write_buffer(&self.uniform_buffer, 0, bytemuck::bytes_of(&self.uniform(true)));
        replaced
    }

    fn encode(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        layout: ClipmapLayout,
        ops: &[Op],
        timer: Option<&crate::pass_timer::PassTimer>,
    ) {
        let mut records = Vec::with_capacity(ops.len());
        // Per record: a splat (or a clear).
        let mut splats = Vec::with_capacity(ops.len());
        for op in ops {
            let (level, origin, keep) = match op {
                Op::Clear { level, origin, keep } => (*level, *origin, *keep),
                Op::Splat { level, origin, keep, .. } => (*level, *origin, *keep),
            };
            let mut record = DispatchRecord {
                block: [0; 4],
                level: [level, layout.cell(level), layout.cells, 0],
                region: [origin[0], origin[1], origin[2], 0],
                keep_min: [keep.min[0], keep.min[1], keep.min[2], 0],
                keep_max: [keep.max[0], keep.max[1], keep.max[2], 0],
            };
            match op {
                Op::Clear { .. } => {
                    records.push(record);
                    splats.push(false);
                    self.counters.clears += 1;
                }
                Op::Splat { key, subtract, .. } => {
                    let Some((first, count)) = self.voxel_words.range(key) else { continue };
                    if count == 0 {
                        continue;
                    }
                    let edge = 1u32 << key.level;
                    let corner = key.coord().map(|c| c.saturating_mul(BLOCK_SIZE << key.level));
                    record.block = [corner[0], corner[1], corner[2], edge];
                    record.level[3] = *subtract as u32;
                    record.region[3] = count as i32;
                    record.keep_min[3] = first as i32;
                    records.push(record);
                    splats.push(true);
                    self.counters.splats += 1;
                    self.counters.voxels_splatted += count as u64;
                }
            }
        }
        if records.is_empty() {
            return;
        }
        if self.dispatch_buffer.size() < records.len() as u64 * DISPATCH_STRIDE {
            self.dispatch_buffer = Self::dispatch_buffer(device, (records.len() as u64).next_power_of_two());
        }
        queue.write_buffer(&self.dispatch_buffer, 0, &strided_records(&records));
        let record_binding = wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.dispatch_buffer,
            offset: 0,
            size: wgpu::BufferSize::new(size_of::<DispatchRecord>() as u64),
        });
        // A clear and a splat group per level the records touch, each binding that level's cells.
        let mut clear_groups: Vec<Option<wgpu::BindGroup>> = vec![None; layout.levels as usize];
        let mut splat_groups: Vec<Option<wgpu::BindGroup>> = vec![None; layout.levels as usize];
        for (record, &splat) in records.iter().zip(&splats) {
            let level = record.level[0] as usize;
            let cells = level_cells(&self.cells_buffer, layout, record.level[0]);
            if splat && splat_groups[level].is_none() {
                splat_groups[level] = Some(device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("clipmap splat"),
                    layout: &self.splat_layout,
                    entries: &[
                        wgpu::BindGroupEntry { binding: 0, resource: record_binding.clone() },
                        wgpu::BindGroupEntry { binding: 1, resource: cells },
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: self.voxel_words.buffer.as_entire_binding(),
                        },
                    ],
                }));
            } else if !splat && clear_groups[level].is_none() {
                clear_groups[level] = Some(device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("clipmap clear"),
                    layout: &self.clear_layout,
                    entries: &[
                        wgpu::BindGroupEntry { binding: 0, resource: record_binding.clone() },
                        wgpu::BindGroupEntry { binding: 1, resource: cells },
                    ],
                }));
            }
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("clipmap update"),
                timestamp_writes: timer.and_then(|t| t.compute_writes("clipmap update")),
            });
            let level_groups = (layout.level_len() as u32).div_ceil(WORKGROUP);
            for (i, (record, &splat)) in records.iter().zip(&splats).enumerate() {
                let offset = (i as u64 * DISPATCH_STRIDE) as u32;
                let level = record.level[0] as usize;
                if splat {
                    pass.set_pipeline(&self.splat_pipeline);
                    pass.set_bind_group(0, splat_groups[level].as_ref(), &[offset]);
                    pass.dispatch_workgroups((record.region[3] as u32).div_ceil(WORKGROUP), 1, 1);
                } else {
                    pass.set_pipeline(&self.clear_pipeline);
                    pass.set_bind_group(0, clear_groups[level].as_ref(), &[offset]);
                    pass.dispatch_workgroups(level_groups, 1, 1);
                }
            }
        }
    }

    /// Copies the cells of `boxes` (level, cells: [`texel_boxes`]) into the
    /// levels' texture, one dispatch a box, after the clears and splats.
    fn encode_texels(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        layout: ClipmapLayout,
        boxes: &[(u32, CellBox)],
        timer: Option<&crate::pass_timer::PassTimer>,
    ) {
        if boxes.is_empty() {
            return;
        }
        if self.texel_dispatch_buffer.size() < boxes.len() as u64 * DISPATCH_STRIDE {
            self.texel_dispatch_buffer =
                Self::dispatch_buffer(device, (boxes.len() as u64).next_power_of_two());
            self.texel_groups.clear();
        }
        let records: Vec<TexelRecord> = boxes
            .iter()
            .map(|(level, b)| {
                let size = b.size();
                TexelRecord {
                    box_min: [b.min[0], b.min[1], b.min[2], *level as i32],
                    box_size: [size[0], size[1], size[2], layout.cells],
                }
            })
            .collect();
        queue.write_buffer(&self.texel_dispatch_buffer, 0, &strided_records(&records));
        if self.texel_groups.len() != layout.levels as usize {
            self.texel_groups = (0..layout.levels)
                .map(|level| {
                    device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("clipmap texels"),
                        layout: &self.texel_layout,
                        entries: &[
                            wgpu::BindGroupEntry {
                                binding: 0,
                                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                    buffer: &self.texel_dispatch_buffer,
                                    offset: 0,
                                    size: wgpu::BufferSize::new(size_of::<TexelRecord>() as u64),
                                }),
                            },
                            wgpu::BindGroupEntry {
                                binding: 1,
                                resource: level_cells(&self.cells_buffer, layout, level),
                            },
                            wgpu::BindGroupEntry {
                                binding: 2,
                                resource: wgpu::BindingResource::TextureView(&self.texel_view),
                            },
                        ],
                    })
                })
                .collect();
        }
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("clipmap texels"),
            timestamp_writes: timer.and_then(|t| t.compute_writes("clipmap texels")),
        });
        pass.set_pipeline(&self.texel_pipeline);
        for (i, (level, b)) in boxes.iter().enumerate() {
            let [x, y, z] = b.size();
            pass.set_bind_group(
                0,
                &self.texel_groups[*level as usize],
                &[(i as u64 * DISPATCH_STRIDE) as u32],
            );
            pass.dispatch_workgroups((x * y * z).div_ceil(WORKGROUP), 1, 1);
        }
    }
}

/// Level `level`'s range of the cells buffer, which the clear, splat and texel passes bind
/// one level at a time: all levels together (8 of 128³ cells, 12 bytes each: 192 MiB) pass
/// WebGPU's 128 MiB limit on a storage binding from 6 levels on, which scenes of 4096³ and
/// more reach. A level's bytes (cells³ × 12, cells ≥ 8 a power of two) are a multiple of 256,
/// the storage offset alignment.
fn level_cells(buffer: &wgpu::Buffer, layout: ClipmapLayout, level: u32) -> wgpu::BindingResource<'_> {
    let bytes = layout.level_words() * 4;
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer,
        offset: level as u64 * bytes,
        size: wgpu::BufferSize::new(bytes),
    })
}

/// `records` one [`DISPATCH_STRIDE`] apart, as a dynamic uniform offset reads them.
fn strided_records<T: bytemuck::Pod>(records: &[T]) -> Vec<u8> {
    let mut bytes = vec![0u8; records.len() * DISPATCH_STRIDE as usize];
    for (record, at) in records.iter().zip(bytes.chunks_exact_mut(DISPATCH_STRIDE as usize)) {
        at[..size_of::<T>()].copy_from_slice(bytemuck::bytes_of(record));
    }
    bytes
}

/// The boxes of cells an update changes, per level, which the texels must
/// copy: for each level in `moved` (level, region, cells kept) the slabs it
/// newly exposed (its whole region on a rebuild), where its clear and its
/// scroll's splats (`keep` set) write; and one box around the blocks
/// splatted in or out of a level's unmoved cells (`keep` empty).
fn texel_boxes(layout: ClipmapLayout, ops: &[Op], moved: &[(u32, CellBox, CellBox)]) -> Vec<(u32, CellBox)> {
    let mut boxes: Vec<(u32, CellBox)> = moved
        .iter()
        .flat_map(|(k, region, keep)| exposed_slabs(region, keep).into_iter().map(|b| (*k, b)))
        .collect();
    let mut splats: Vec<Option<CellBox>> = vec![None; layout.levels as usize];
    for op in ops {
        if let Op::Splat { level, key, origin, keep, .. } = op
            && *keep == CellBox::EMPTY
        {
            let changed =
                block_cells(key, layout.cell(*level)).intersection(&CellBox::region(*origin, layout.cells));
            if let (Some(changed), Some(slot)) = (changed, splats.get_mut(*level as usize)) {
                *slot = Some(slot.map_or(changed, |d| d.union(&changed)));
            }
        }
    }
    boxes.extend(splats.into_iter().enumerate().filter_map(|(k, b)| b.map(|b| (k as u32, b))));
    boxes
}

/// The cells of `region` outside `keep`, as at most six slabs (the whole
/// region where `keep` misses it).
fn exposed_slabs(region: &CellBox, keep: &CellBox) -> Vec<CellBox> {
    if region.intersection(keep).is_none() {
        return vec![*region];
    }
    let mut slabs = Vec::new();
    for a in 0..3 {
        if keep.min[a] > region.min[a] {
            let mut slab = *region;
            slab.max[a] = keep.min[a];
            slabs.push(slab);
        }
        if keep.max[a] < region.max[a] {
            let mut slab = *region;
            slab.min[a] = keep.max[a];
            slabs.push(slab);
        }
    }
    slabs
}

/// The camera's view direction from a view-projection matrix (grid units):
/// from the eye towards the centre of the far half of the frustum.
pub fn view_forward(view_proj: Mat4, eye: Vec3) -> Vec3 {
    let inv = view_proj.inverse();
    let p: Vec4 = inv * Vec4::new(0.0, 0.0, 0.5, 1.0);
    if p.w.abs() < 1e-20 || !p.is_finite() {
        return Vec3::ZERO;
    }
    (p.truncate() / p.w - eye).normalize_or_zero()
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxstream_format::{PackedVoxel, oct_encode};

    #[test]
    fn layout_reaches_across_the_grid_within_the_level_cap() {
        let l = ClipmapLayout::for_scene(256, 1, 128);
        assert_eq!((l.finest_cell, l.levels), (1, 3), "126·4 ≥ 256 needs 3 levels");
        assert!(126 * l.cell(l.levels - 1) >= 256 && 126 * l.cell(l.levels - 2) < 256);
        let big = ClipmapLayout::for_scene(65536, 1, 128);
        assert_eq!(big.levels, MAX_CLIP_LEVELS);
        assert!(126u64 * big.cell(big.levels - 1) as u64 >= 65536, "{big:?}");
        // The finest cell follows the finest drawn voxel.
        assert_eq!(ClipmapLayout::for_scene(256, 4, 64).finest_cell, 4);
        assert_eq!(ClipmapLayout::for_scene(256, 3, 64).finest_cell, 4);
        // Control: one level fewer would not reach.
        assert!(126 * l.cell(1) < 256);
    }

    #[test]
    fn origins_follow_the_eye_in_integer_cells_and_stay_on_the_grid() {
        let l = ClipmapLayout::for_scene(1024, 1, 64);
        let fwd = Vec3::X;
        let o = l.origin(0, Vec3::new(500.2, 500.0, 500.0), fwd, 1024);
        // Centre a quarter extent (16 cells) ahead of the eye.
        assert_eq!(o, [516 - 32, 468, 468]);
        // Half a cell further: same origin; a cell further: one cell further.
        assert_eq!(l.origin(0, Vec3::new(500.7, 500.0, 500.0), fwd, 1024), o);
        assert_eq!(l.origin(0, Vec3::new(501.2, 500.0, 500.0), fwd, 1024)[0], o[0] + 1);
        // Far outside the grid: clamped so the level stays on it.
        let out = l.origin(0, Vec3::new(-1e9, 5000.0, 7.0), fwd, 1024);
        assert_eq!(out, [-1, 1024 + 1 - 64, -1]);
        // Control: a NaN eye is placed at the grid centre, not at NaN or 0.
        assert_eq!(l.origin(0, Vec3::new(f32::NAN, 0.0, 0.0), fwd, 1024), [480; 3]);
        // The coarsest level holds the whole grid wherever the eye is.
        let top = l.levels - 1;
        for eye in [Vec3::ZERO, Vec3::splat(1024.0), Vec3::new(-5e5, 7.0, 1e6)] {
            let o = l.origin(top, eye, fwd, 1024);
            let cell = l.cell(top) as i32;
            for a in 0..3 {
                assert!(o[a] * cell <= 0 && (o[a] + 64) * cell >= 1024, "{eye}: {o:?}");
            }
        }
    }

    #[test]
    fn a_level_the_grids_size_is_centred_on_it_wherever_the_eye_is() {
        // 256 grid units, finest cell 1, 128 cells: level 1 (cells of 2) is the grid exactly.
        let l = ClipmapLayout::for_scene(256, 1, 128);
        assert_eq!(l.cell(1) * l.cells, 256);
        for eye in [Vec3::ZERO, Vec3::splat(255.0), Vec3::new(10.0, 250.0, 128.0), Vec3::splat(-1e6)] {
            for fwd in [Vec3::X, Vec3::NEG_Y, Vec3::new(1.0, 1.0, -1.0)] {
                assert_eq!(l.origin(1, eye, fwd, 256), [0; 3], "eye {eye}, forward {fwd}");
            }
        }
        // Control: a level one cell larger than the grid on each side is not
        // forced to 0 by the rule: level 0 (half the grid) still follows the eye.
        assert_ne!(l.origin(0, Vec3::ZERO, Vec3::X, 256), l.origin(0, Vec3::splat(255.0), Vec3::X, 256));
    }

    #[test]
    fn voxel_density_matches_the_volume_rule() {
        // A level-0 voxel fills a level-0 cell; a sixteenth of a 4-unit cell.
        assert_eq!(voxel_density_fixed(255, 1, 1), DENSITY_ONE);
        assert_eq!(voxel_density_fixed(255, 1, 4), DENSITY_ONE / 16);
        // A full level-3 voxel in 4-unit cells: 4 per cell, clamped to 1.
        assert_eq!(voxel_density_fixed(255, 8, 4), DENSITY_ONE);
        // A level-3 voxel standing for 64 level-0 voxels (coverage 64/512)
        // in an 8-unit cell: 64 / 64 = one sheet, opaque.
        let c = voxstream_format::coverage_from_count(64, 3) as u32;
        let q = voxel_density_fixed(c, 8, 8) as f64 / DENSITY_ONE as f64;
        assert!((q - 1.0).abs() < 0.02, "{q}");
        // Half coverage: half as dense. Control: no coverage adds nothing.
        assert_eq!(voxel_density_fixed(0, 2, 2), 0);
        assert!(voxel_density_fixed(128, 1, 2) < voxel_density_fixed(255, 1, 2));
        assert_eq!(voxel_density_fixed(255, 1, 1 << 20), 0);
    }

    #[test]
    fn the_model_puts_each_voxel_in_its_cell() {
        // Face 0 (-x) exposed: the voxels block rays along x only.
        let mut voxels = vec![PackedVoxel::new([3, 4, 5], 1, oct_encode([0.0, 0.0, 1.0]))];
        voxels.push(PackedVoxel::new([60, 0, 0], 1, oct_encode([0.0, 0.0, 1.0])));
        let block = Block { key: BlockKey::new(0, 1, 0, 0), voxels };
        let layout = ClipmapLayout { cells: 64, finest_cell: 1, levels: 2 };
        let model = ClipmapModel::build(layout, &[[64, 0, 0], [0, 0, 0]], &[vec![&block], vec![&block]]);
        let x = |c: [i64; 3]| slot(c, 64) * CELL_WORDS as usize;
        // Level 0: region x 64..128 holds both voxels at full density, along x.
        assert_eq!(model.levels[0][x([67, 4, 5])], DENSITY_ONE);
        assert_eq!(model.levels[0][x([124, 0, 0])], DENSITY_ONE);
        assert_eq!(model.levels[0].iter().filter(|&&v| v > 0).count(), 2);
        // Level 1 (2-unit cells, region 0..128): a quarter each.
        assert_eq!(model.levels[1][x([33, 2, 2])], DENSITY_ONE / 4);
        // Control: a region that misses the block holds nothing.
        let away = ClipmapModel::build(layout, &[[0, 0, 0], [100, 0, 0]], &[vec![&block], vec![&block]]);
        assert!(away.levels.iter().all(|l| l.iter().all(|&v| v == 0)));
    }

    #[test]
    fn a_voxel_blocks_the_axes_of_its_exposed_faces() {
        use voxstream_format::Face;
        let mask = |faces: &[Face]| faces.iter().fold(0u8, |m, f| m | f.bit());
        assert_eq!(voxel_axes(mask(&[Face::NegY, Face::PosY])), [false, true, false]);
        assert_eq!(voxel_axes(mask(&[Face::PosX, Face::NegZ])), [true, false, true]);
        assert_eq!(voxel_axes(mask(&Face::ALL)), [true; 3]);
        // Inside a solid (no face exposed): every axis.
        assert_eq!(voxel_axes(0), [true; 3]);

        // A floor: one layer of voxels with ±y exposed fills a 4-voxel cell
        // along y only, at full opacity (16 voxels × 1/16).
        let floor = mask(&[Face::NegY, Face::PosY]);
        let voxels: Vec<PackedVoxel> = (0..4)
            .flat_map(|x| {
                (0..4).map(move |z| PackedVoxel::new([x, 1, z], floor, oct_encode([0.0, 1.0, 0.0])))
            })
            .collect();
        let block = Block { key: BlockKey::new(0, 0, 0, 0), voxels };
        let layout = ClipmapLayout { cells: 8, finest_cell: 4, levels: 1 };
        let model = ClipmapModel::build(layout, &[[0, 0, 0]], &[vec![&block]]);
        let at = slot([0, 0, 0], 8) * CELL_WORDS as usize;
        assert_eq!(model.levels[0][at..at + 3], [0, DENSITY_ONE, 0]);
        // Control: the same voxels with no face exposed count on every axis.
        let solid = Block {
            key: block.key,
            voxels: block
                .voxels
                .iter()
                .map(|v| PackedVoxel::new(v.local(), 0, oct_encode([0.0, 1.0, 0.0])))
                .collect(),
        };
        let model = ClipmapModel::build(layout, &[[0, 0, 0]], &[vec![&solid]]);
        assert_eq!(model.levels[0][at..at + 3], [DENSITY_ONE; 3]);
    }

    #[test]
    fn exposed_slabs_cover_exactly_the_cells_a_scroll_exposes() {
        let region = CellBox::region([10, -4, 7], 16);
        for shift in [[3, 0, 0], [-5, 2, 0], [1, -1, 15], [0, 0, 0], [20, 0, 0]] {
            let keep = CellBox::region([10 - shift[0], -4 - shift[1], 7 - shift[2]], 16);
            let slabs = exposed_slabs(&region, &keep);
            for x in region.min[0]..region.max[0] {
                for y in region.min[1]..region.max[1] {
                    for z in region.min[2]..region.max[2] {
                        let c = [x as i64, y as i64, z as i64];
                        let in_slab = slabs.iter().any(|s| s.contains(c));
                        assert_eq!(in_slab, !keep.contains(c), "cell {c:?}, shift {shift:?}");
                    }
                }
            }
            assert!(slabs.iter().all(|s| region.covers(s)), "a slab leaves the region: {slabs:?}");
        }
    }

    #[test]
    fn forward_comes_from_the_view_projection() {
        let eye = Vec3::new(10.0, 20.0, 30.0);
        use glam::camera::rh::{proj::directx, view};
        let view = view::look_at_mat4(eye, eye + Vec3::new(0.0, 0.0, -1.0), Vec3::Y);
        let proj = directx::perspective(1.0, 1.5, 0.1, 100.0);
        let f = view_forward(proj * view, eye);
        assert!((f - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-3, "{f}");
    }
}
