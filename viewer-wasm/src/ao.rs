//! Cone-traced ambient occlusion (shaders/ao.wgsl): the settings the shader
//! reads ([`AoSettings`], [`AoUniform`]) and the occupancy volume it traces.
//!
//! **The definition** (issue 9; the reference in `voxstream reference-ao` uses
//! the same): V(p, n) = 1 − (1/π) ∫ w(d(ω)) cos θ dω over the hemisphere of n,
//! d(ω) the distance to the first surface (both sides count), w(d) = 1 / (1 +
//! λ·d/R) for d ≤ R, else 0. The shader estimates it with cones whose axes are
//! a fixed cosine-weighted set (equal weights, so the estimator is 1 − mean of
//! the cones' weighted occlusion); along a cone, front-to-back opacity α is
//! accumulated and each step adds (1 − α)·α_step·w(d_step).
//!
//! The cones are traced through the occupancy clipmap ([`crate::clipmap`]:
//! nested levels around the camera, built on the GPU) or, with
//! [`AoStructure::Volume`] (for comparison), through the older structure
//! defined here: the drawn blocks splatted into a cubic grid of at most 128³
//! cells over the whole scene grid, with a mip chain of averaged occupancy
//! built on the CPU, and uploaded as an r8unorm 3D texture the shader samples
//! at the mip matching each cone's width.
//!
//! Each voxel brings its prefiltered coverage (the stored fraction of occupied
//! level-0 voxels below it), so a coarse block puts the same occluding mass
//! into the volume as the fine blocks it stands for would: the AO does not
//! darken or brighten as the LOD changes.

use voxstream_format::{BLOCK_SIZE, Block, BlockKey, FULL_COVERAGE, PackedVoxel, oct_decode};

/// Cone counts with a fixed direction set ([`cone_directions`]).
pub const CONE_COUNTS: [u32; 5] = [3, 5, 6, 8, 16];
/// Most cones the uniform holds.
pub const MAX_CONES: usize = 16;

/// Every setting of the cone tracer, in the units the user gives them; turned
/// into the shader's [`AoUniform`] by [`AoSettings::uniform`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AoSettings {
    /// 3, 5, 6, 8 or 16 cones (others are rounded to the nearest of these).
    pub cones: u32,
    /// Half-angle of each cone in degrees; `None`: asin(1/√cones), the cone
    /// whose projected disk has the area of its share (π/cones) of the
    /// projected hemisphere. The trace also keeps a cone no wider than a third
    /// of its height above the tangent plane (so it never reads its own
    /// surface), which caps the half-angle at atan(1/6) ≈ 9.5°: wider apertures
    /// (the default ones included) change nothing (docs/ao-benchmark.md, "Eight
    /// frames, not four").
    pub aperture_deg: Option<f32>,
    /// Step along a cone as a fraction of its diameter there.
    pub step: f32,
    /// Start offset along the normal in finest occupancy cells (see the shader:
    /// this is what keeps a surface from occluding itself).
    pub offset_cells: f32,
    /// R in grid units; `None`: [`default_max_distance`].
    pub max_distance: Option<f32>,
    /// λ in w(d) = 1 / (1 + λ·d/R).
    pub falloff: f32,
    /// Skip ahead where a coarser mip is empty.
    pub empty_skip: bool,
    /// Test only: cones laid around +Z whatever the normal (a deliberately wrong AO).
    pub ignore_normal: bool,
    /// Trace one pixel of each f×f block (f = 1, 2 or 4; others are rounded
    /// down to one of these) and upsample to full resolution (seed 001).
    pub trace_downscale: u32,
    /// How a reduced-resolution trace is brought to full resolution.
    pub upsample: Upsample,
    /// Rotate the cone set about the normal every frame (and, at reduced
    /// resolution, move the traced pixel within its block), from a
    /// low-discrepancy sequence; frame 0 is the fixed set.
    pub jitter: bool,
    /// Interleaved sampling: each traced pixel also turns the cone set by its
    /// own angle (interleaved gradient noise), so neighbours, which the
    /// upsample and the temporal history average, see different cone sets.
    pub interleave: bool,
    /// N: frames the temporal history averages (a new frame's weight falls to
    /// 1/N); 1 = no accumulation.
    pub temporal_frames: u32,
    /// Test only: keep the history where the reprojected surface disagrees (a
    /// deliberately wrong accumulation).
    pub keep_disoccluded_history: bool,
    /// What the cones are traced through.
    #[serde(default)]
    pub structure: AoStructure,
    /// Cone tracing, or the precomputed AO field the blocks carry.
    #[serde(default)]
    pub mode: AoMode,
}

/// How V is computed (issue 9 items 1 and 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AoMode {
    /// Cones traced every frame through the occupancy structure.
    #[default]
    Cone,
    /// The server's precomputed AO field (server `pipeline/aofield.rs`): each
    /// voxel's V, computed at build time for its normal from a 128³ occupancy
    /// of the whole scene, carried into the G-buffer; a pixel whose voxel has
    /// none (a scene built without it) is cone-traced.
    Field,
}

impl AoMode {
    pub fn name(self) -> &'static str {
        match self {
            AoMode::Cone => "cone",
            AoMode::Field => "field",
        }
    }
}

/// The occupancy structure the cones are traced through.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AoStructure {
    /// One volume of at most 128³ cells over the whole scene, built on the CPU (comparison).
    Volume,
    /// Nested levels around the camera, the finest at the finest drawn voxel,
    /// built and scrolled on the GPU ([`crate::clipmap`]).
    #[default]
    Clipmap,
}

impl AoStructure {
    pub fn name(self) -> &'static str {
        match self {
            AoStructure::Volume => "volume",
            AoStructure::Clipmap => "clipmap",
        }
    }
}

/// Upsampling of a reduced-resolution trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Upsample {
    /// Joint bilateral: bilinear weights times depth (plane distance) and
    /// normal likeness; a pixel whose surface no traced texel around it shares
    /// (their likeness-weighted share of the bilinear weight under
    /// [`RETRACE_BELOW`]) is traced itself.
    Bilateral,
    /// Joint bilateral without tracing: a pixel no texel matches takes the
    /// most alike one (comparison: the upsample before re-tracing).
    BilateralOnly,
    /// Plain bilinear (comparison: it blurs across depth edges).
    Bilinear,
}

/// The share of a pixel's bilinear weight that must fall on traced texels of
/// its own surface for [`Upsample::Bilateral`] to blend them; below it the
/// pixel is traced itself. At a depth edge or a crease the texels of the other
/// side get no weight, and the few of the pixel's own side (or, with none, the
/// most alike texel of another surface) stood in for it: on the benchmark's
/// real views most of the upsample's error lay in those pixels
/// (docs/ao-benchmark.md, "Tracing the pixels the upsample cannot match").
/// `shaders/ao_upsample.wgsl` holds the same number.
pub const RETRACE_BELOW: f32 = 0.25;

/// Most frames the temporal accumulation averages.
pub const MAX_TEMPORAL_FRAMES: u32 = 256;

impl Default for AoSettings {
    fn default() -> Self {
        Self {
            cones: 6,
            aperture_deg: None,
            // With cells of half the cone's width, a step of 0.7 diameters is
            // 1.4 cells: inside the two-cell tent every surface casts
            // (docs/ao-benchmark.md, "Cells of half the cone's width").
            step: 0.7,
            offset_cells: 1.5,
            max_distance: None,
            falloff: 1.0,
            empty_skip: false,
            ignore_normal: false,
            // Measured (docs/ao-benchmark.md, "Reduced resolution and
            // temporal accumulation"): half resolution with bilateral
            // upsampling, jittered and interleaved, has the lowest converged
            // error at a quarter of the full-resolution trace's cost. 8
            // frames, not 4: on all nine views of the benchmark the error
            // falls from 4 to 8 frames and not beyond ("Eight frames").
            trace_downscale: 2,
            upsample: Upsample::Bilateral,
            jitter: true,
            interleave: true,
            temporal_frames: 8,
            keep_disoccluded_history: false,
            structure: AoStructure::Clipmap,
            mode: AoMode::Cone,
        }
    }
}

/// The default R in grid units: a tenth of the scene's grid edge (its bounding
/// cube), so a statue and a building get the same relative reach, and at least
/// four finest occupancy cells.
pub fn default_max_distance(grid_resolution: u32) -> f32 {
    let cell = (grid_resolution as f32 / cells_for_grid(grid_resolution) as f32).max(1.0);
    (grid_resolution as f32 * 0.1).max(4.0 * cell)
}

/// The cone count actually used for a requested one: the nearest of [`CONE_COUNTS`].
pub fn supported_cones(cones: u32) -> u32 {
    *CONE_COUNTS.iter().min_by_key(|&&c| c.abs_diff(cones)).expect("non-empty")
}

/// `cones` unit axes in the local frame (x, y tangent, z = normal): Malley's
/// method on a Vogel spiral, i.e. points spread evenly (equal area) over the
/// unit disk lifted to the hemisphere. Equal-area disk cells are equal
/// projected solid angle, so the directions are cosine-weighted and every cone
/// has the weight 1/cones.
pub fn cone_directions(cones: u32) -> Vec<[f32; 3]> {
    cone_directions_jittered(cones, ConeJitter::NONE)
}

/// One frame's jitter of the cones: `turn` (0..1 of a full turn of the set
/// about the normal), `radial` (0..1, where in its equal-area ring band each
/// cone sits; 0.5 is the band's middle) and `step_phase` (0..1, where along
/// each cone its samples fall, as the shader's `ao_mode.y`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConeJitter {
    pub turn: f64,
    pub radial: f64,
    pub step_phase: f64,
}

impl ConeJitter {
    /// The fixed set ([`cone_directions`]).
    pub const NONE: ConeJitter = ConeJitter { turn: 0.0, radial: 0.5, step_phase: 0.0 };

    /// Frame `index`'s jitter: a turn about the normal from the golden-ratio
    /// sequence (frac(k/φ), the 1D low-discrepancy sequence), frame 0 being
    /// [`ConeJitter::NONE`]; any N consecutive frames spread their turns
    /// evenly. The cones stay in the middle of their equal-area bands: moving
    /// them within the bands as well (the R2 sequence's second coordinate)
    /// was measured to bias short runs (4 frames whose band positions average
    /// 0.35, not 0.5, tilted the set towards the normal: parallel plates MAE
    /// 0.085 → 0.100).
    ///
    /// The step phase follows the R2 sequence's second coordinate, so that
    /// frames that share a turn do not share a phase. With samples at fixed
    /// distances a cone read a surface at the same points of its cells every
    /// frame, and the error swung with the step: parallel plates RMSE 0.018
    /// to 0.038 between steps of 0.5 and 0.7 diameters (docs/ao-benchmark.md,
    /// "Cells of half the cone's width").
    pub fn for_frame(index: u32) -> Self {
        const INVERSE_GOLDEN: f64 = 0.618_033_988_749_894_8;
        const INVERSE_PLASTIC_SQUARED: f64 = 0.569_840_290_998_053_2;
        ConeJitter {
            turn: (index as f64 * INVERSE_GOLDEN).fract(),
            radial: 0.5,
            step_phase: (index as f64 * INVERSE_PLASTIC_SQUARED).fract(),
        }
    }
}

/// [`cone_directions`] turned by `jitter`: still cosine-weighted with equal
/// weights (each cone stays inside its own equal-area band).
pub fn cone_directions_jittered(cones: u32, jitter: ConeJitter) -> Vec<[f32; 3]> {
    let n = cones.max(1);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let radial = jitter.radial.clamp(0.0, 1.0);
    (0..n)
        .map(|i| {
            let r = ((i as f64 + radial) / n as f64).sqrt();
            let phi = i as f64 * golden + std::f64::consts::TAU * jitter.turn;
            let z = (1.0 - r * r).max(0.0).sqrt();
            [(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]
        })
        .collect()
}

/// The AO part of the frame uniform (layout shared with `Frame` in voxel.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct AoUniform {
    /// x: cone count, y: tan(half aperture), z: step (fraction of the
    /// diameter), w: start offset along the normal (grid units).
    pub cone: [f32; 4],
    /// x: R (grid units), y: λ, z: 1 = empty-space skipping, w: 1 = ignore the normal.
    pub range: [f32; 4],
    /// Cone axes in the local frame, w: weight.
    pub dirs: [[f32; 4]; MAX_CONES],
}

impl AoSettings {
    pub fn cone_count(&self) -> u32 {
        supported_cones(self.cones)
    }

    /// Half-angle in degrees, the default applied.
    pub fn aperture(&self) -> f32 {
        self.aperture_deg
            .filter(|a| a.is_finite())
            .unwrap_or_else(|| (1.0 / (self.cone_count() as f32).sqrt()).asin().to_degrees())
            .clamp(1.0, 80.0)
    }

    /// R in grid units, the default applied.
    pub fn max_distance_grid(&self, grid_resolution: u32) -> f32 {
        self.max_distance
            .filter(|r| r.is_finite() && *r > 0.0)
            .unwrap_or_else(|| default_max_distance(grid_resolution))
    }

    /// Start offset along the normal in grid units for a finest cell of
    /// `finest_cell` grid units (the clipmap's finest level, or the volume's cell).
    pub fn offset_grid(&self, finest_cell: f32) -> f32 {
        let cell = if finest_cell.is_finite() { finest_cell.clamp(1.0, 1e9) } else { 1.0 };
        finite_or(self.offset_cells, 1.5).clamp(0.0, 8.0) * cell
    }

    /// 1, 2 or 4: the requested downscale rounded down to one of these.
    pub fn downscale(&self) -> u32 {
        match self.trace_downscale {
            0 | 1 => 1,
            2 | 3 => 2,
            _ => 4,
        }
    }

    /// These settings with the fields `patch` (a JSON object, the field names
    /// of this struct) names replaced: the browser's `window.voxstream.set({aoSettings})`.
    /// An unknown field or a value of the wrong type is an error naming it, and
    /// nothing changes. Values in range are not checked here: the uniform
    /// clamps every one ([`AoSettings::uniform_jittered`]).
    pub fn patched(&self, patch: &serde_json::Value) -> Result<AoSettings, String> {
        let fields =
            patch.as_object().ok_or_else(|| format!("AO settings: expected an object, got {patch}"))?;
        let mut merged = serde_json::to_value(self).map_err(|e| e.to_string())?;
        let current = merged.as_object_mut().expect("a struct serializes to an object");
        for (name, value) in fields {
            let slot = current.get_mut(name).ok_or_else(|| format!("AO settings: no setting {name:?}"))?;
            *slot = value.clone();
        }
        serde_json::from_value(merged).map_err(|e| format!("AO settings: {e}"))
    }

    /// N of the temporal accumulation, in 1..=[`MAX_TEMPORAL_FRAMES`].
    pub fn accumulated_frames(&self) -> u32 {
        self.temporal_frames.clamp(1, MAX_TEMPORAL_FRAMES)
    }

    /// The cone set's jitter in frame `index` of an accumulation.
    pub fn jitter_for_frame(&self, index: u32) -> ConeJitter {
        if self.jitter { ConeJitter::for_frame(index) } else { ConeJitter::NONE }
    }

    /// The shader's uniform for the fixed cone set. Every value is finite and
    /// in range whatever the settings hold: NaN or degenerate settings never
    /// reach the shader.
    pub fn uniform(&self, grid_resolution: u32) -> AoUniform {
        self.uniform_jittered(grid_resolution, volume_cell(grid_resolution), ConeJitter::NONE)
    }

    /// [`AoSettings::uniform`] for a finest cell of `finest_cell` grid units,
    /// with the cone set turned by `jitter`.
    pub fn uniform_jittered(&self, grid_resolution: u32, finest_cell: f32, jitter: ConeJitter) -> AoUniform {
        let cones = self.cone_count();
        let mut dirs = [[0.0; 4]; MAX_CONES];
        for (d, axis) in dirs.iter_mut().zip(cone_directions_jittered(cones, jitter)) {
            *d = [axis[0], axis[1], axis[2], 1.0 / cones as f32];
        }
        AoUniform {
            cone: [
                cones as f32,
                self.aperture().to_radians().tan(),
                finite_or(self.step, 0.5).clamp(0.05, 4.0),
                self.offset_grid(finest_cell),
            ],
            range: [
                self.max_distance_grid(grid_resolution).min(4.0 * grid_resolution.max(1) as f32),
                finite_or(self.falloff, 1.0).clamp(0.0, 1e3),
                if self.empty_skip { 1.0 } else { 0.0 },
                if self.ignore_normal { 1.0 } else { 0.0 },
            ],
            dirs,
        }
    }
}

fn finite_or(v: f32, default: f32) -> f32 {
    if v.is_finite() { v } else { default }
}

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

/// Bytes before each block's voxels in an [`encode_sources`] payload: level,
/// then x, y, z and the voxel count as little-endian u32.
const SOURCE_HEADER: usize = 1 + 4 * 4;

/// The blocks a volume is splatted from as one flat buffer, for a worker:
/// per block its key, its voxel count and its voxels' raw bytes.
pub fn encode_sources<'a>(blocks: impl IntoIterator<Item = &'a Block>) -> Vec<u8> {
    let mut out = Vec::new();
    for b in blocks {
        out.push(b.key.level);
        for v in [b.key.x, b.key.y, b.key.z, b.voxels.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(bytemuck::cast_slice(&b.voxels));
    }
    out
}

/// The inverse of [`encode_sources`]; a payload cut short or with trailing bytes is an error.
pub fn decode_sources(mut bytes: &[u8]) -> Result<Vec<Block>, String> {
    let voxel = size_of::<PackedVoxel>();
    let mut blocks = Vec::new();
    while !bytes.is_empty() {
        let header = bytes.get(..SOURCE_HEADER).ok_or("occupancy sources: a block header is cut short")?;
        let word = |i: usize| u32::from_le_bytes(header[1 + 4 * i..5 + 4 * i].try_into().expect("4 bytes"));
        let key = BlockKey::new(header[0], word(0), word(1), word(2));
        let len = (word(3) as usize).checked_mul(voxel).ok_or("occupancy sources: voxel count overflows")?;
        let body = bytes
            .get(SOURCE_HEADER..SOURCE_HEADER + len)
            .ok_or_else(|| format!("occupancy sources: block {key} is cut short"))?;
        let voxels = body.chunks_exact(voxel).map(bytemuck::pod_read_unaligned).collect();
        blocks.push(Block { key, voxels });
        bytes = &bytes[SOURCE_HEADER + len..];
    }
    Ok(blocks)
}

/// The volume's cell edge in grid units.
pub fn volume_cell(grid_resolution: u32) -> f32 {
    (grid_resolution as f32 / cells_for_grid(grid_resolution) as f32).max(1.0)
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
        // Summed surface normals per cell: they tell a solid's inside from a room's.
        let mut normals = vec![[0f32; 3]; n * n * n];
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
                let normal = oct_decode(v.normal);
                for z in z0..(z0 + span).min(n) {
                    for y in y0..(y0 + span).min(n) {
                        let row = (z * n + y) * n;
                        for i in row + x0..row + (x0 + span).min(n) {
                            density[i] += share;
                            for a in 0..3 {
                                normals[i][a] += normal[a] * share;
                            }
                        }
                    }
                }
            }
        }
        fill_enclosed(&mut density, &normals, n);
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

    /// All mips back to back, finest first (what a worker sends back).
    pub fn into_bytes(self) -> Vec<u8> {
        self.mips.concat()
    }

    /// The inverse of [`OccupancyVolume::into_bytes`] for a `grid_resolution`³ grid;
    /// a length that is not exactly that volume's is an error.
    pub fn from_bytes(grid_resolution: u32, bytes: &[u8]) -> Result<Self, String> {
        let cells = cells_for_grid(grid_resolution);
        let sizes: Vec<usize> = (0..=cells.ilog2()).map(|m| ((cells >> m) as usize).pow(3)).collect();
        let total: usize = sizes.iter().sum();
        if bytes.len() != total {
            return Err(format!(
                "occupancy volume: {} bytes, a {cells}³ volume with mips has {total}",
                bytes.len()
            ));
        }
        let mut at = 0;
        let mips = sizes
            .iter()
            .map(|&n| {
                at += n;
                bytes[at - n..at].to_vec()
            })
            .collect();
        Ok(Self { grid_resolution, cells, mips })
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
/// cells) as full when they are the inside of a solid. The blocks hold surface
/// voxels only, so without this a solid body would read as a thin shell and
/// coarse mips (wide cones) would see through it. An enclosed region is a
/// solid's inside when the surface around it faces away from it (the summed
/// normals of the occupied cells next to it point outwards), and free space,
/// say a closed room scanned from inside, when they face into it. Where a
/// shell has a gap (say, between blocks of different levels while streaming)
/// the flood leaks in and that body simply stays hollow.
fn fill_enclosed(density: &mut [f32], normals: &[[f32; 3]], n: usize) {
    let index = |x: usize, y: usize, z: usize| (z * n + y) * n + x;
    let neighbours = |i: usize| {
        let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
        let mut out = [None; 6];
        if x > 0 {
            out[0] = Some((index(x - 1, y, z), [-1.0, 0.0, 0.0]));
        }
        if x + 1 < n {
            out[1] = Some((index(x + 1, y, z), [1.0, 0.0, 0.0]));
        }
        if y > 0 {
            out[2] = Some((index(x, y - 1, z), [0.0, -1.0, 0.0]));
        }
        if y + 1 < n {
            out[3] = Some((index(x, y + 1, z), [0.0, 1.0, 0.0]));
        }
        if z > 0 {
            out[4] = Some((index(x, y, z - 1), [0.0, 0.0, -1.0]));
        }
        if z + 1 < n {
            out[5] = Some((index(x, y, z + 1), [0.0, 0.0, 1.0]));
        }
        out
    };
    // 0: not yet reached, 1: outside, 2..: enclosed component ids.
    let mut label = vec![0u32; density.len()];
    let mut stack = Vec::new();
    for a in 0..n {
        for b in 0..n {
            for (x, y, z) in [(0, a, b), (n - 1, a, b), (a, 0, b), (a, n - 1, b), (a, b, 0), (a, b, n - 1)] {
                let i = index(x, y, z);
                if density[i] == 0.0 && label[i] == 0 {
                    label[i] = 1;
                    stack.push(i);
                }
            }
        }
    }
    while let Some(i) = stack.pop() {
        for (j, _) in neighbours(i).into_iter().flatten() {
            if density[j] == 0.0 && label[j] == 0 {
                label[j] = 1;
                stack.push(j);
            }
        }
    }
    for seed in 0..density.len() {
        if density[seed] != 0.0 || label[seed] != 0 {
            continue;
        }
        // One enclosed component: collect it and let its walls vote.
        let mut members = vec![seed];
        label[seed] = 2;
        let mut vote = 0.0f64;
        let mut k = 0;
        while k < members.len() {
            let i = members[k];
            k += 1;
            for (j, step) in neighbours(i).into_iter().flatten() {
                if density[j] == 0.0 {
                    if label[j] == 0 {
                        label[j] = 2;
                        members.push(j);
                    }
                } else {
                    // The wall cell j lies at `step` from i: its normal faces i when it points along −step.
                    let nj = normals[j];
                    vote -= (nj[0] * step[0] + nj[1] * step[1] + nj[2] * step[2]) as f64;
                }
            }
        }
        if vote <= 0.0 {
            for i in members {
                density[i] = 1.0;
            }
        }
    }
}

/// The pixel of each f×f block that frame `index` traces, as an offset in the
/// block: always (0, 0) without jitter; with it, the blocks' pixels in the
/// order of an f×f Bayer matrix, so any f² consecutive frames trace each pixel
/// once and consecutive ones lie far apart.
pub fn traced_pixel_offset(downscale: u32, index: u32, jitter: bool) -> [u32; 2] {
    let f = downscale.max(1);
    if !jitter || f == 1 {
        return [0, 0];
    }
    let rank = index % (f * f);
    (0..f * f)
        .map(|i| [i % f, i / f])
        .find(|&[x, y]| bayer_rank(x, y, f) == rank)
        .expect("a Bayer matrix ranks every pixel once")
}

/// The rank of (x, y) in the f×f Bayer (ordered-dither) matrix, f a power of two.
fn bayer_rank(x: u32, y: u32, f: u32) -> u32 {
    let mut rank = 0;
    let mut size = f;
    let (mut x, mut y) = (x, y);
    while size > 1 {
        size /= 2;
        let (bx, by) = (x / size, y / size);
        // 2×2 ranks: (0,0) 0, (1,1) 1, (1,0) 2, (0,1) 3.
        let quadrant = match (bx, by) {
            (0, 0) => 0,
            (1, 1) => 1,
            (1, 0) => 2,
            _ => 3,
        };
        rank = rank * 4 + quadrant;
        x %= size;
        y %= size;
    }
    rank
}

/// The next mip: a cell's opacity to a ray crossing it, estimated as twice the
/// mean of its 2×2×2 children (values clamped to 1 first, as the texture stores
/// them), clamped to 1. A surface sheet through a cell fills 4 of its 8
/// children and stays opaque (2 · 4/8) at every mip, a solid stays 1, and a
/// lone child covers a quarter of the cell's cross-section (2 · 1/8): the
/// projected-area estimate, where a plain mean would thin a wall out by half
/// per mip and let wide cones see through it.
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
                out[(z * half + y) * half + x] = (sum / 4.0).min(1.0);
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
    use voxstream_format::oct_encode;

    #[test]
    fn a_patch_replaces_only_the_settings_it_names() {
        let d = AoSettings::default();
        let p = d.patched(&serde_json::json!({"cones": 16, "step": 0.5, "trace_downscale": 1})).unwrap();
        assert_eq!((p.cones, p.step, p.trace_downscale), (16, 0.5, 1));
        assert_eq!(AoSettings { cones: d.cones, step: d.step, trace_downscale: d.trace_downscale, ..p }, d);
        let p = d.patched(&serde_json::json!({"mode": "field", "aperture_deg": null})).unwrap();
        assert_eq!(p.mode, AoMode::Field);
        // Controls: unknown names, wrong types and non-objects are errors naming the problem.
        let e = d.patched(&serde_json::json!({"cone": 16})).unwrap_err();
        assert!(e.contains("\"cone\""), "{e}");
        let e = d.patched(&serde_json::json!({"step": "fast"})).unwrap_err();
        assert!(e.contains("AO settings"), "{e}");
        assert!(d.patched(&serde_json::json!([1])).is_err());
    }

    #[test]
    fn a_volume_built_from_a_worker_payload_equals_the_direct_build() {
        let blocks = vec![
            block(0, [0, 0, 0], &[[1, 2, 3], [4, 5, 6], [63, 63, 63]]),
            block(1, [1, 0, 1], &[[0, 0, 0], [10, 20, 30]]),
            block(2, [0, 1, 0], &[]),
        ];
        let payload = encode_sources(&blocks);
        let decoded = decode_sources(&payload).expect("decodes");
        assert_eq!(decoded, blocks);
        let direct = OccupancyVolume::build(512, &blocks);
        let via_worker = OccupancyVolume::build(512, &decoded);
        let round_trip =
            OccupancyVolume::from_bytes(512, &via_worker.clone().into_bytes()).expect("sizes match");
        assert_eq!(round_trip, direct);
        // Controls: a payload missing a block gives another volume; cut or padded payloads and
        // wrongly sized volumes are errors.
        let fewer = OccupancyVolume::build(512, &decode_sources(&encode_sources(&blocks[1..])).unwrap());
        assert_ne!(fewer, direct);
        assert!(decode_sources(&payload[..payload.len() - 1]).is_err());
        assert!(decode_sources(&[payload.as_slice(), &[0u8; 3]].concat()).is_err());
        assert!(OccupancyVolume::from_bytes(512, &direct.clone().into_bytes()[1..]).is_err());
        assert!(
            OccupancyVolume::from_bytes(64, &direct.into_bytes()).is_err(),
            "a 64³ grid has a 64³ volume"
        );
    }

    fn block(level: u8, coord: [u32; 3], locals: &[[u32; 3]]) -> Block {
        let mut voxels: Vec<PackedVoxel> =
            locals.iter().map(|&p| PackedVoxel::new(p, 1, oct_encode([0.0, 0.0, 1.0]))).collect();
        voxels.sort_by_key(|v| v.morton());
        Block { key: BlockKey::new(level, coord[0], coord[1], coord[2]), voxels }
    }

    #[test]
    fn cone_directions_are_unit_cosine_weighted_and_in_the_hemisphere() {
        for cones in CONE_COUNTS {
            let dirs = cone_directions(cones);
            assert_eq!(dirs.len(), cones as usize);
            let mut mean_cos = 0.0;
            for d in &dirs {
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((len - 1.0).abs() < 1e-5 && d[2] > 0.0, "{cones}: {d:?}");
                mean_cos += d[2] as f64 / cones as f64;
            }
            // E[cos θ] under the cosine-weighted density is 2/3.
            assert!((mean_cos - 2.0 / 3.0).abs() < 0.03, "{cones} cones: mean cos {mean_cos}");
        }
        assert_eq!(supported_cones(7), 6);
        assert_eq!(supported_cones(100), 16);
    }

    #[test]
    fn jittered_cone_sets_stay_cosine_weighted_and_frame_zero_is_the_fixed_set() {
        assert_eq!(cone_directions_jittered(6, ConeJitter::for_frame(0)), cone_directions(6));
        let mut mean_z = 0.0;
        let frames = 64;
        for k in 0..frames {
            let j = ConeJitter::for_frame(k);
            assert!((0.0..1.0).contains(&j.turn) && j.radial == 0.5);
            for d in cone_directions_jittered(3, j) {
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((len - 1.0).abs() < 1e-5 && d[2] >= 0.0);
                mean_z += d[2] as f64 / (3 * frames) as f64;
            }
        }
        // Over many frames 3 cones sample the cosine-weighted hemisphere: E[cos θ] = 2/3.
        assert!((mean_z - 2.0 / 3.0).abs() < 0.01, "mean cos {mean_z}");
        // Control: without jitter every frame has the same set.
        let fixed = AoSettings { jitter: false, ..AoSettings::default() };
        assert_eq!(fixed.jitter_for_frame(5), ConeJitter::NONE);
        assert_ne!(AoSettings::default().jitter_for_frame(5), ConeJitter::NONE);
    }

    #[test]
    fn the_upsample_shader_retraces_below_the_same_share() {
        let line = crate::shaders::AO_UPSAMPLE_WGSL
            .lines()
            .find_map(|l| l.strip_prefix("const RETRACE_BELOW: f32 = "))
            .expect("ao_upsample.wgsl declares RETRACE_BELOW");
        let value: f32 = line.trim_end_matches(';').parse().expect("a number");
        assert_eq!(value, RETRACE_BELOW);
        // The default upsample is the one that re-traces (uniform value 2).
        assert_eq!(AoSettings::default().upsample, Upsample::Bilateral);
    }

    #[test]
    fn traced_pixel_offsets_visit_every_pixel_of_the_block() {
        for f in [2u32, 4] {
            let mut seen: Vec<[u32; 2]> = (0..f * f).map(|k| traced_pixel_offset(f, k, true)).collect();
            assert_eq!(seen[0], [0, 0]);
            seen.sort();
            seen.dedup();
            assert_eq!(seen.len(), (f * f) as usize, "f = {f}");
        }
        assert_eq!(traced_pixel_offset(2, 1, true), [1, 1]);
        assert_eq!(traced_pixel_offset(2, 3, false), [0, 0]);
        assert_eq!(traced_pixel_offset(1, 3, true), [0, 0]);
        let s = AoSettings { trace_downscale: 3, temporal_frames: 0, ..AoSettings::default() };
        assert_eq!((s.downscale(), s.accumulated_frames()), (2, 1));
    }

    #[test]
    fn nan_settings_never_reach_the_uniform() {
        let bad = AoSettings {
            aperture_deg: Some(f32::NAN),
            step: f32::INFINITY,
            offset_cells: f32::NAN,
            max_distance: Some(f32::NAN),
            falloff: f32::NEG_INFINITY,
            ..AoSettings::default()
        };
        let u = bad.uniform(512);
        let all = u.cone.iter().chain(&u.range).chain(u.dirs.iter().flatten());
        for v in all {
            assert!(v.is_finite(), "{u:?}");
        }
        assert!(u.range[0] > 0.0 && u.cone[1] > 0.0 && u.cone[2] > 0.0);
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
        // The sheet crosses the whole mip-1 cell: opaque; a quarter of a mip-2 cell.
        assert_eq!(fine.value(1, 0, 0, 0), 1.0);
        assert!((fine.value(2, 0, 0, 0) - 0.25).abs() < 2.0 / 255.0);
        // At mip 0 the coarse voxel spreads its sheet's mass (half opaque per
        // cell); a full-coverage one would read opaque.
        assert!((coarse.value(0, 1, 1, 1) - 0.5).abs() < 2.0 / 255.0);
        let full = OccupancyVolume::build(512, [&block(3, [0, 0, 0], &[[0, 0, 0]])]);
        assert_eq!(full.value(0, 1, 1, 1), 1.0);
    }

    #[test]
    fn mips_average_down_to_one_cell() {
        let b = block(3, [0, 0, 0], &[[0, 0, 0]]);
        let vol = OccupancyVolume::build(512, [&b]);
        assert_eq!(vol.mip_count(), 8);
        assert_eq!(vol.mips.last().unwrap().len(), 1);
        // 2³ full cells: mip 1 has one full cell, which covers a quarter of a
        // mip-2 cell's cross-section and a 16th of a mip-3 cell's.
        assert_eq!(vol.value(1, 0, 0, 0), 1.0);
        assert!((vol.value(2, 0, 0, 0) - 0.25).abs() < 1.0 / 255.0);
        assert!((vol.value(3, 0, 0, 0) - 1.0 / 16.0).abs() < 1.0 / 255.0);
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
    fn a_room_seen_from_inside_stays_empty() {
        // The shell of a cube whose normals all point inwards: a closed room.
        let mut room = cube_shell(8, 40, false);
        for v in &mut room.voxels {
            let p = v.local().map(|c| c as f32 - 23.5);
            let axis = (0..3).max_by(|&a, &b| p[a].abs().total_cmp(&p[b].abs())).unwrap();
            let mut n = [0.0; 3];
            n[axis] = -p[axis].signum();
            v.normal = oct_encode(n);
        }
        let vol = OccupancyVolume::build(64, [&room]);
        assert_eq!(vol.value(0, 20, 20, 20), 0.0, "the room's air is not solid");
        assert_eq!(vol.value(0, 8, 20, 20), 1.0);
        // The same shell with outward normals is a solid box.
        for v in &mut room.voxels {
            let n = oct_decode(v.normal);
            v.normal = oct_encode([-n[0], -n[1], -n[2]]);
        }
        let vol = OccupancyVolume::build(64, [&room]);
        assert_eq!(vol.value(0, 20, 20, 20), 1.0, "a closed solid is filled");
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
