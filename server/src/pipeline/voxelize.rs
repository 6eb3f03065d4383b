//! Voxelize: triangles → level-0 sparse blocks by exact conservative surface
//! voxelization (every voxel whose closed cube a triangle touches).
//!
//! Work is split the way it will scale out of core: triangles are binned by
//! the 64³ blocks their bounds overlap, then each block is voxelized on its
//! own (rayon) into a dense brick, and only occupied voxels leave it.
//! Within a block, triangles are visited in input order, so normal sums, and
//! therefore the encoded store, are deterministic.

use std::collections::BTreeMap;

use rayon::prelude::*;
use voxstream_format::{BLOCK_SIZE, BLOCK_VOXELS, BlockKey, GridFrame};

use crate::pipeline::progress::{ProgressSink, Stage, StageCounter};
use crate::pipeline::read::TriangleMesh;
use crate::pipeline::stream::Bounds;

/// A voxel while the store is being built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BuildVoxel {
    /// Block-local Morton index (< 2^18).
    pub morton: u32,
    /// Area-weighted sum of the normals of the triangles touching the voxel.
    pub normal_sum: [f32; 3],
    /// Area-weighted sum of linear RGB colours in [0, 1]; all zero when the input has none.
    pub color_sum: [f32; 3],
    /// Total area behind `color_sum`; 0 means "no colour".
    pub color_weight: f32,
    /// Exposed-face mask; filled in by the LOD stage.
    pub faces: u8,
}

impl BuildVoxel {
    pub const EMPTY: BuildVoxel =
        BuildVoxel { morton: 0, normal_sum: [0.0; 3], color_sum: [0.0; 3], color_weight: 0.0, faces: 0 };
}

/// One block's voxels in strictly increasing Morton order.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseBlock {
    pub key: BlockKey,
    pub voxels: Vec<BuildVoxel>,
}

#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct VoxelizeStats {
    pub triangles: u64,
    /// Degenerate (zero-area) or non-finite triangles.
    pub skipped: u64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum VoxelizeError {
    #[error("grid resolution {0} must be a power of two between 1 and {MAX_RESOLUTION}")]
    BadResolution(u32),
    #[error("the mesh has no valid triangle ({skipped} degenerate or non-finite)")]
    NoValidTriangle { skipped: u64 },
    #[error("{0}")]
    BadVoxelSize(String),
}

/// Largest grid we accept: 1024 blocks an edge, so block Morton codes take
/// 30 bits (the bin index packs them with segment ids into a u64).
pub const MAX_RESOLUTION: u32 = 65536;

pub fn check_resolution(resolution: u32) -> Result<(), VoxelizeError> {
    if resolution.is_power_of_two() && resolution <= MAX_RESOLUTION {
        Ok(())
    } else {
        Err(VoxelizeError::BadResolution(resolution))
    }
}

/// A triangle in grid units, or `None` when it is degenerate or non-finite.
pub(crate) fn to_grid(tri: [[f64; 3]; 3], frame: &GridFrame) -> Option<[[f64; 3]; 3]> {
    let t = to_grid_unchecked(tri, frame);
    valid_triangle(&t).then_some(t)
}

/// [`to_grid`] without the validity check, for triangles already checked by it.
///
/// A product with the voxel's reciprocal, not nine divisions: the divisions
/// were a tenth of the bin pass. The grid triangle is whatever this returns;
/// every pass and the in-memory reference call this one function, so they
/// agree bit for bit, and `p - origin` stays exact for shifted scans.
pub(crate) fn to_grid_unchecked(tri: [[f64; 3]; 3], frame: &GridFrame) -> [[f64; 3]; 3] {
    let per_voxel = 1.0 / frame.voxel_size;
    tri.map(|p| std::array::from_fn(|a| (p[a] - frame.origin[a]) * per_voxel))
}

pub fn valid_triangle(tri: &[[f64; 3]; 3]) -> bool {
    tri.iter().flatten().all(|c| c.is_finite()) && {
        let n = cross(sub(tri[1], tri[0]), sub(tri[2], tri[0]));
        dot(n, n) > 0.0
    }
}

/// Chooses the bounding cube of the mesh's valid triangles, split into
/// `resolution`³ voxels, with its corner at the bounds' minimum.
///
/// Translation invariance: the origin is an input coordinate itself, not a
/// computed one, so for a mesh moved by an exactly representable offset every
/// `p - origin` (and the extent) comes out bit-identical, and so does the voxel
/// set, however far from zero the scan sits (georeferenced scans at 1e7 units).
/// The cube is enlarged by a hair so that no vertex lands on its far faces.
pub fn choose_frame(mesh: &TriangleMesh, resolution: u32) -> Result<GridFrame, VoxelizeError> {
    check_resolution(resolution)?;
    let mut bounds = Bounds::EMPTY;
    let mut skipped = 0;
    for t in 0..mesh.triangles.len() {
        let tri = mesh.triangle(t);
        if !valid_triangle(&tri) {
            skipped += 1;
            continue;
        }
        bounds.add_triangle(&tri);
    }
    frame_from_bounds(&bounds, resolution, skipped)
}

/// [`choose_frame`] from the bounds of the valid triangles (as the chunked
/// stream's headers carry them); `skipped` only feeds the error.
pub fn frame_from_bounds(bounds: &Bounds, resolution: u32, skipped: u64) -> Result<GridFrame, VoxelizeError> {
    check_resolution(resolution)?;
    if bounds.is_empty() {
        return Err(VoxelizeError::NoValidTriangle { skipped });
    }
    let (lo, hi) = (bounds.min, bounds.max);
    // Positive: a valid triangle has non-zero area, so some axis has extent.
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let voxel_size = extent * (1.0 + 1e-6) / resolution as f64;
    Ok(GridFrame { origin: lo, voxel_size, resolution, units: None })
}

/// How the grid's resolution is chosen (`--resolution auto|N`, `--voxel-size`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Resolution {
    /// The power of two whose voxel edge is closest, in log2, to the scan's
    /// median triangle edge (its own sampling), within [64, 65536].
    #[default]
    Auto,
    /// Voxels of this edge in source units: the grid is the next power of two
    /// that covers the extent, and the cube grows beyond the bounds.
    VoxelSize(f64),
    /// This many voxels an edge (a power of two).
    Explicit(u32),
}

impl std::str::FromStr for Resolution {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(Resolution::Auto);
        }
        s.parse::<u32>()
            .map(Resolution::Explicit)
            .map_err(|_| format!("{s:?} is neither auto nor a power of two such as 1024"))
    }
}

impl std::fmt::Display for Resolution {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Resolution::Auto => f.write_str("auto"),
            Resolution::VoxelSize(v) => write!(f, "voxel size {v}"),
            Resolution::Explicit(r) => write!(f, "{r}"),
        }
    }
}

/// What resolution a build used and why (the manifest's, the report's and
/// the catalog's).
pub use voxstream_format::ResolutionChoice;

/// The smallest grid `auto` picks.
pub const MIN_AUTO_RESOLUTION: u32 = 64;

const EDGE_EXP_MIN: i64 = -256;
const EDGE_EXP_MAX: i64 = 255;
/// Mantissa bits of a squared length kept per bin: 32 bins per octave of the
/// square, 64 per octave of the length.
const EDGE_MANTISSA_BITS: u32 = 5;
const EDGE_BINS: usize = ((EDGE_EXP_MAX - EDGE_EXP_MIN + 1) as usize) << EDGE_MANTISSA_BITS;
const _: () = assert!(EDGE_BINS <= 1 << 16, "bins are u16");

/// A histogram of triangle edge lengths (bins of 1/32 to 1/64 octave, from
/// the bits of the squared length: no logarithm per edge), for the median
/// edge. Deterministic: counts do not depend on the order edges come in.
#[derive(Clone)]
pub struct EdgeHistogram {
    counts: Vec<u64>,
}

impl Default for EdgeHistogram {
    fn default() -> Self {
        Self { counts: vec![0; EDGE_BINS] }
    }
}

impl EdgeHistogram {
    fn bin(len2: f64) -> Option<usize> {
        if !(len2 > 0.0 && len2.is_finite()) {
            return None;
        }
        let bits = len2.to_bits();
        // Subnormals fall into the lowest bin.
        let exp = (((bits >> 52) & 0x7ff) as i64 - 1023).clamp(EDGE_EXP_MIN, EDGE_EXP_MAX);
        let mant = (bits >> (52 - EDGE_MANTISSA_BITS)) as usize & ((1 << EDGE_MANTISSA_BITS) - 1);
        Some(((exp - EDGE_EXP_MIN) as usize) << EDGE_MANTISSA_BITS | mant)
    }

    /// Counts the three edges of a triangle.
    pub fn add_triangle(&mut self, t: &[[f64; 3]; 3]) {
        let mut bins = Vec::with_capacity(3);
        Self::bins(t, &mut bins);
        self.count(&bins);
    }

    /// Appends the bins of a triangle's three edges (to count later, maybe on another thread).
    pub fn bins(t: &[[f64; 3]; 3], out: &mut Vec<u16>) {
        for (a, b) in [(0, 1), (1, 2), (2, 0)] {
            let d = sub(t[a], t[b]);
            if let Some(i) = Self::bin(dot(d, d)) {
                out.push(i as u16);
            }
        }
    }

    /// Counts bins from [`Self::bins`].
    pub fn count(&mut self, bins: &[u16]) {
        for &i in bins {
            self.counts[i as usize] += 1;
        }
    }

    pub fn merge(&mut self, other: &EdgeHistogram) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
    }

    pub fn edges(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// The median edge length (the middle of its bin), or `None` without edges.
    pub fn median(&self) -> Option<f64> {
        let total = self.edges();
        if total == 0 {
            return None;
        }
        let mut seen = 0;
        let i = self.counts.iter().position(|&c| {
            seen += c;
            2 * seen >= total
        })?;
        let exp = (i >> EDGE_MANTISSA_BITS) as i64 + EDGE_EXP_MIN;
        let mant = (i & ((1 << EDGE_MANTISSA_BITS) - 1)) as f64 + 0.5;
        let len2 = 2f64.powi(exp as i32) * (1.0 + mant / (1 << EDGE_MANTISSA_BITS) as f64);
        Some(len2.sqrt())
    }
}

/// The frame for `mode` over the bounds of the valid triangles: the
/// resolution, the grid and the reason. `max_auto` caps what `auto` picks
/// (the memory budget's or the server's limit); `median_edge` comes from an
/// [`EdgeHistogram`] of the same triangles.
pub fn choose_resolution(
    bounds: &Bounds,
    mode: Resolution,
    median_edge: Option<f64>,
    max_auto: u32,
    skipped: u64,
) -> Result<(GridFrame, ResolutionChoice), VoxelizeError> {
    if bounds.is_empty() {
        return Err(VoxelizeError::NoValidTriangle { skipped });
    }
    let extent = (0..3).map(|a| bounds.max[a] - bounds.min[a]).fold(0.0, f64::max);
    let median_note = |vs: f64| match median_edge {
        Some(m) => format!("; the scan's median triangle edge is {m:.4} units ({:.2} voxels)", m / vs),
        None => String::new(),
    };
    match mode {
        Resolution::Explicit(r) => {
            let frame = frame_from_bounds(bounds, r, skipped)?;
            let reason = format!(
                "resolution {r} was asked for: voxels of {:.4} units{}",
                frame.voxel_size,
                median_note(frame.voxel_size)
            );
            let choice = ResolutionChoice {
                mode: "explicit".into(),
                resolution: r,
                voxel_size: frame.voxel_size,
                median_edge,
                reason,
            };
            Ok((frame, choice))
        }
        Resolution::VoxelSize(len) => {
            if !(len > 0.0 && len.is_finite()) {
                return Err(VoxelizeError::BadVoxelSize(format!(
                    "voxel size {len} must be a positive number"
                )));
            }
            // The same hair as `frame_from_bounds`, so no vertex lands on the far faces.
            let cells = (extent * (1.0 + 1e-6) / len).ceil().max(1.0);
            if cells > MAX_RESOLUTION as f64 {
                return Err(VoxelizeError::BadVoxelSize(format!(
                    "voxel size {len} needs {cells} voxels across the {extent:.4}-unit extent, more than \
                     {MAX_RESOLUTION}: choose a voxel size of at least {:.6}",
                    extent * (1.0 + 1e-6) / MAX_RESOLUTION as f64
                )));
            }
            let r = (cells as u32).next_power_of_two();
            let frame = GridFrame { origin: bounds.min, voxel_size: len, resolution: r, units: None };
            let reason = format!(
                "voxel size {len} was asked for: {r} voxels an edge, the next power of two covering the \
                 {extent:.4}-unit extent{}",
                median_note(len)
            );
            let choice = ResolutionChoice {
                mode: "voxel-size".into(),
                resolution: r,
                voxel_size: len,
                median_edge,
                reason,
            };
            Ok((frame, choice))
        }
        Resolution::Auto => {
            let cube = extent * (1.0 + 1e-6);
            let max = max_auto.clamp(MIN_AUTO_RESOLUTION, MAX_RESOLUTION);
            let (r, why) = match median_edge {
                Some(m) if m > 0.0 => {
                    let k = (cube / m).log2().round().clamp(0.0, 31.0) as u32;
                    let ideal = 1u64 << k;
                    let r = ideal.clamp(MIN_AUTO_RESOLUTION as u64, max as u64) as u32;
                    let capped = if ideal > max as u64 {
                        format!(" (the closest, {ideal}, is above the limit {max})")
                    } else if ideal < MIN_AUTO_RESOLUTION as u64 {
                        format!(" (the closest, {ideal}, is below the smallest, {MIN_AUTO_RESOLUTION})")
                    } else {
                        String::new()
                    };
                    (
                        r,
                        format!(
                            "the power of two whose voxel is closest to the scan's median triangle edge{capped}"
                        ),
                    )
                }
                _ => (MIN_AUTO_RESOLUTION, "no edge lengths were measured".to_string()),
            };
            let frame = frame_from_bounds(bounds, r, skipped)?;
            let reason = format!(
                "auto: {r} voxels an edge, voxels of {:.4} units, {why}{}",
                frame.voxel_size,
                median_note(frame.voxel_size)
            );
            let choice = ResolutionChoice {
                mode: "auto".into(),
                resolution: r,
                voxel_size: frame.voxel_size,
                median_edge,
                reason,
            };
            Ok((frame, choice))
        }
    }
}

/// Voxelizes every valid triangle into level-0 blocks, sorted by key, all in
/// memory. The build goes through `pipeline::bin` instead (same per-block kernel,
/// bounded memory); this form is the reference the tests compare it with.
pub fn voxelize(
    mesh: &TriangleMesh,
    frame: &GridFrame,
) -> Result<(Vec<SparseBlock>, VoxelizeStats), VoxelizeError> {
    voxelize_reporting(mesh, frame, Topology::Conservative, &ProgressSink::new(&|_| {}))
}

/// [`voxelize`] with a chosen output topology, reporting each finished block to `progress`.
pub fn voxelize_reporting(
    mesh: &TriangleMesh,
    frame: &GridFrame,
    topology: Topology,
    progress: &ProgressSink,
) -> Result<(Vec<SparseBlock>, VoxelizeStats), VoxelizeError> {
    let res = frame.resolution as i64;
    let mut stats = VoxelizeStats::default();
    let mut tris: Vec<[[f64; 3]; 3]> = Vec::with_capacity(mesh.triangles.len());
    let mut colors: Vec<[f32; 3]> = Vec::new();
    let colored = !mesh.colors.is_empty() && mesh.colors.len() == mesh.positions.len();
    let mut bins: BTreeMap<[u32; 3], Vec<u32>> = BTreeMap::new();
    for t in 0..mesh.triangles.len() {
        let Some(g) = to_grid(mesh.triangle(t), frame) else {
            stats.skipped += 1;
            continue;
        };
        for_each_block(&g, res, |b| bins.entry(b).or_default().push(tris.len() as u32));
        tris.push(g);
        if colored {
            colors.push(mesh.triangle_color(t).unwrap_or_default());
        }
    }
    stats.triangles = tris.len() as u64;
    if tris.is_empty() {
        return Err(VoxelizeError::NoValidTriangle { skipped: stats.skipped });
    }
    let counter = StageCounter::new(progress, Stage::Voxelize, bins.len());
    let blocks: Vec<SparseBlock> = bins
        .into_par_iter()
        .map(|(coord, list)| {
            let key = BlockKey::new(0, coord[0], coord[1], coord[2]);
            let block = with_block_voxelizer(|vox| {
                for &t in &list {
                    let color = colored.then(|| colors[t as usize]);
                    vox.add(key, &tris[t as usize], color, res, topology);
                }
                vox.finish(key)
            });
            counter.tick();
            block
        })
        .filter_map(|b| b)
        .collect();
    Ok((blocks, stats))
}

/// The closed range of 64³ block coordinates a grid triangle's bounds overlap.
pub(crate) fn block_range(g: &[[f64; 3]; 3], res: i64) -> ([u32; 3], [u32; 3]) {
    let (lo, hi) = voxel_range(g, res);
    (lo.map(|v| (v / BLOCK_SIZE as i64) as u32), hi.map(|v| (v / BLOCK_SIZE as i64) as u32))
}

/// The part of the voxel box `[lo, hi]` (closed) inside the 64³ block whose
/// first voxel is `base`.
fn clip_to_block(lo: [i64; 3], hi: [i64; 3], base: [i64; 3]) -> ([i64; 3], [i64; 3]) {
    (
        std::array::from_fn(|a| lo[a].max(base[a])),
        std::array::from_fn(|a| hi[a].min(base[a] + BLOCK_SIZE as i64 - 1)),
    )
}

/// Calls `f` with the coordinate of every 64³ block a grid triangle's bounds overlap.
fn for_each_block(g: &[[f64; 3]; 3], res: i64, mut f: impl FnMut([u32; 3])) {
    let (blo, bhi) = block_range(g, res);
    for bz in blo[2]..=bhi[2] {
        for by in blo[1]..=bhi[1] {
            for bx in blo[0]..=bhi[0] {
                f([bx, by, bz]);
            }
        }
    }
}

/// Closed voxel index range of a grid-space triangle's bounds, clamped to the
/// grid. A bound on an integer plane also touches the voxel below it, hence
/// `ceil - 1` rather than `floor` at the low end.
fn voxel_range(t: &[[f64; 3]; 3], res: i64) -> ([i64; 3], [i64; 3]) {
    let lo = std::array::from_fn(|a| (-fast_floor(-t[0][a].min(t[1][a]).min(t[2][a])) - 1).clamp(0, res - 1));
    let hi = std::array::from_fn(|a| fast_floor(t[0][a].max(t[1][a]).max(t[2][a])).clamp(0, res - 1));
    (lo, hi)
}

/// A 64³ brick, indexed by local Morton code so that reading occupied
/// voxels in index order yields them already sorted. One per worker thread,
/// reused block after block: finishing a block clears only the voxels it set.
///
/// The occupancy bits are dense; the sums are kept per 4³ tile (64 voxels,
/// one word of `bits`), and a tile gets its slot in `sums` when its first
/// voxel is set. A surface fills a few percent of a block but a third or
/// more of the tiles it crosses, so the sums a block touches lie together
/// (a few hundred KiB that stay in L2) instead of scattered over 3 MiB,
/// where every hit was a cache miss. Each voxel's sums, and the order they
/// are added in, are the same either way.
pub(crate) struct BlockVoxelizer {
    bits: Vec<u64>,
    /// Each tile's slot in `sums` plus one; 0 while the tile has no voxel.
    tiles: Vec<u16>,
    /// Slots handed out in this block.
    used: usize,
    /// Per slot, its tile's voxels in Morton order, each voxel's sums side
    /// by side (one cache line serves a hit): the area-weighted normal sum,
    /// then, once a coloured triangle came, the area-weighted colour sum and
    /// the area behind it. `stride` floats a voxel. Zero outside the voxels
    /// set; grows to the most slots a block has needed, never past a full block.
    sums: Vec<f32>,
    /// 3 (normals) or 7 (normals and colours).
    stride: usize,
}

/// Floats a voxel takes in [`BlockVoxelizer::sums`] without and with colour.
const NORMAL_STRIDE: usize = 3;
const COLOR_STRIDE: usize = 7;

/// Voxels a tile of [`BlockVoxelizer::sums`] (a 4³ Morton cell: one word of the bits).
const TILE_VOXELS: usize = 64;
const TILES: usize = BLOCK_VOXELS / TILE_VOXELS;
const _: () = assert!(TILES <= u16::MAX as usize, "slots + 1 fit a u16");

/// Heap bytes of one [`BlockVoxelizer`] with colours: what an in-flight block costs
/// (the sums of every tile at most).
pub(crate) const BLOCK_VOXELIZER_BYTES: usize =
    BLOCK_VOXELS / 8 + TILES * 2 + BLOCK_VOXELS * COLOR_STRIDE * 4;

/// `morton3(c, 0, 0)` for every block-local coordinate: a voxel's Morton code
/// is three lookups (`SPREAD[x] | SPREAD[y] << 1 | SPREAD[z] << 2`).
const SPREAD: [u32; BLOCK_SIZE as usize] = {
    let mut t = [0u32; BLOCK_SIZE as usize];
    let mut c = 0;
    while c < t.len() {
        let mut bit = 0;
        while bit < 6 {
            t[c] |= ((c as u32 >> bit) & 1) << (3 * bit);
            bit += 1;
        }
        c += 1;
    }
    t
};

/// Block-local Morton code of a voxel whose local coordinates are below 64.
#[inline]
fn local_morton(l: [i64; 3]) -> usize {
    // The masks only spare the bounds checks: callers pass coordinates inside the block.
    (SPREAD[(l[0] & 63) as usize] | SPREAD[(l[1] & 63) as usize] << 1 | SPREAD[(l[2] & 63) as usize] << 2)
        as usize
}

thread_local! {
    /// Each worker thread's brick, allocated once (rayon's `map_init` would
    /// allocate one per work split).
    static BRICK: std::cell::RefCell<Option<BlockVoxelizer>> = const { std::cell::RefCell::new(None) };
}

/// Runs `f` with this thread's [`BlockVoxelizer`] (clear on entry, and left clear by `finish`).
pub(crate) fn with_block_voxelizer<T>(f: impl FnOnce(&mut BlockVoxelizer) -> T) -> T {
    BRICK.with(|cell| {
        let mut slot = cell.borrow_mut();
        let vox = slot.get_or_insert_with(BlockVoxelizer::new);
        vox.clear();
        f(vox)
    })
}

/// One triangle's part of a block, as [`BlockVoxelizer::add`] hands it on.
struct Hits<'t> {
    tri: &'t [[f64; 3]; 3],
    /// The triangle's (unnormalised) normal.
    n: [f64; 3],
    /// The block's first voxel in grid units.
    base: [i64; 3],
    /// The block's part of the triangle's bounds, closed.
    lo: [i64; 3],
    hi: [i64; 3],
    /// Every voxel of `[lo, hi]` is touched (see `add`); only the topology's targets are left to test.
    one_row: bool,
    topology: Topology,
}

impl BlockVoxelizer {
    /// Drops whatever an interrupted block left behind (cheap when already clear).
    fn clear(&mut self) {
        if self.bits.iter().any(|&w| w != 0) {
            self.finish(BlockKey::new(0, 0, 0, 0));
        }
    }

    pub(crate) fn new() -> Self {
        Self { bits: vec![0; TILES], tiles: vec![0; TILES], used: 0, sums: Vec::new(), stride: NORMAL_STRIDE }
    }

    /// Widens the sums to hold colours (on the first coloured triangle), keeping the normal sums.
    fn add_color_sums(&mut self) {
        let voxels = self.sums.len() / NORMAL_STRIDE;
        let mut sums = Vec::new();
        sums.reserve_exact(voxels * COLOR_STRIDE);
        sums.resize(voxels * COLOR_STRIDE, 0.0);
        for (wide, narrow) in sums.chunks_exact_mut(COLOR_STRIDE).zip(self.sums.chunks_exact(NORMAL_STRIDE)) {
            wide[..NORMAL_STRIDE].copy_from_slice(narrow);
        }
        self.sums = sums;
        self.stride = COLOR_STRIDE;
    }

    /// A slot for a tile that has none: the next one, the sums grown (zeroed) when it is new.
    #[cold]
    fn new_slot<const STRIDE: usize>(
        tiles: &mut [u16],
        used: &mut usize,
        sums: &mut Vec<f32>,
        tile: usize,
    ) -> usize {
        let slot = *used;
        *used += 1;
        tiles[tile] = *used as u16;
        let need = *used * TILE_VOXELS * STRIDE;
        if sums.len() < need {
            // Doubling, capped at a full block so the budget's figure holds.
            let len = need.max(2 * sums.len()).min(BLOCK_VOXELS * STRIDE);
            sums.reserve_exact(len - sums.len());
            sums.resize(len, 0.0);
        }
        slot
    }

    /// Adds a valid grid-space triangle (see [`to_grid`]) to block `key`.
    pub(crate) fn add(
        &mut self,
        key: BlockKey,
        tri: &[[f64; 3]; 3],
        color: Option<[f32; 3]>,
        res: i64,
        topology: Topology,
    ) {
        let base = key.coord().map(|c| c as i64 * BLOCK_SIZE as i64);
        let n = cross(sub(tri[1], tri[0]), sub(tri[2], tri[0]));
        // What a hit adds to the voxel's sums: the normal, then (colour) the
        // colour weighted by the triangle's area in voxel units, and that area.
        let mut add = [0.0f32; COLOR_STRIDE];
        for a in 0..3 {
            add[a] = n[a] as f32;
        }
        if let Some(c) = color {
            let area = (0.5 * norm(n)) as f32;
            add[3..].copy_from_slice(&[c[0] * area, c[1] * area, c[2] * area, area]);
            if self.stride != COLOR_STRIDE {
                self.add_color_sums();
            }
        }
        let (full_lo, full_hi) = voxel_range(tri, res);
        let (lo, hi) = clip_to_block(full_lo, full_hi, base);
        // The triangle's whole bounds (not the block's part) lie inside one
        // voxel, or one row of voxels, open in the other two axes: it is
        // connected and spans the row from end to end, so it touches every
        // voxel of the row (the SAT would say the same, at many times the cost).
        let one_row = (0..3).filter(|&a| full_hi[a] > full_lo[a]).count() <= 1;
        let hits = Hits { tri, n, base, lo, hi, one_row, topology };
        // Uncoloured triangles add nothing past the normal, even to a coloured brick.
        match (self.stride, color.is_some()) {
            (COLOR_STRIDE, true) => self.add_hits::<COLOR_STRIDE, COLOR_STRIDE>(&hits, &add),
            (COLOR_STRIDE, false) => self.add_hits::<COLOR_STRIDE, NORMAL_STRIDE>(&hits, &add),
            _ => self.add_hits::<NORMAL_STRIDE, NORMAL_STRIDE>(&hits, &add),
        }
    }

    /// Sets every voxel of `hits` that the triangle meets, adding the first
    /// `WIDTH` floats of `add` to its sums (`STRIDE` floats a voxel: constants,
    /// so the update is a few fixed adds).
    #[inline]
    fn add_hits<const STRIDE: usize, const WIDTH: usize>(&mut self, h: &Hits, add: &[f32; COLOR_STRIDE]) {
        debug_assert_eq!(self.stride, STRIDE);
        let (bits, tiles, used, sums, base) =
            (&mut self.bits, &mut self.tiles, &mut self.used, &mut self.sums, h.base);
        let mut set = |v: [i64; 3]| {
            let m = local_morton([v[0] - base[0], v[1] - base[1], v[2] - base[2]]);
            let tile = m / TILE_VOXELS;
            bits[tile] |= 1 << (m % TILE_VOXELS);
            let slot = match tiles[tile] {
                0 => Self::new_slot::<STRIDE>(tiles, used, sums, tile),
                s => s as usize - 1,
            };
            let at = slot * TILE_VOXELS + m % TILE_VOXELS;
            let s: &mut [f32; STRIDE] =
                (&mut sums[at * STRIDE..(at + 1) * STRIDE]).try_into().expect("STRIDE floats");
            for a in 0..WIDTH {
                s[a] += add[a];
            }
        };
        let (lo, hi) = (h.lo, h.hi);
        if h.one_row {
            for x in lo[0]..=hi[0] {
                for y in lo[1]..=hi[1] {
                    for z in lo[2]..=hi[2] {
                        if meets_segments(h.tri, [x, y, z], h.topology) {
                            set([x, y, z]);
                        }
                    }
                }
            }
            return;
        }
        for_each_touched_voxel(h.tri, h.n, lo, hi, h.topology, set);
    }

    /// The block's voxels in Morton order (`None` when empty); leaves the brick clear.
    pub(crate) fn finish(&mut self, key: BlockKey) -> Option<SparseBlock> {
        let voxels = self.finish_map(|v| v);
        (!voxels.is_empty()).then_some(SparseBlock { key, voxels })
    }

    /// The block's voxels in Morton order, each passed through `f`, in a vector
    /// of exact capacity (the build counts its bytes); leaves the brick clear.
    pub(crate) fn finish_map<T>(&mut self, f: impl Fn(BuildVoxel) -> T) -> Vec<T> {
        if self.stride == COLOR_STRIDE {
            self.drain_voxels::<COLOR_STRIDE, T>(f)
        } else {
            self.drain_voxels::<NORMAL_STRIDE, T>(f)
        }
    }

    /// [`Self::finish_map`] for a brick of `STRIDE` floats a voxel.
    fn drain_voxels<const STRIDE: usize, T>(&mut self, f: impl Fn(BuildVoxel) -> T) -> Vec<T> {
        debug_assert_eq!(self.stride, STRIDE);
        let count = self.bits.iter().map(|w| w.count_ones() as usize).sum();
        let mut out = Vec::with_capacity(count);
        for w in 0..self.bits.len() {
            let mut bits = std::mem::take(&mut self.bits[w]);
            if bits == 0 {
                continue;
            }
            // A tile with a voxel set has a slot (`add_hits` gives it one first).
            let slot = std::mem::take(&mut self.tiles[w]) as usize - 1;
            while bits != 0 {
                let bit = bits.trailing_zeros();
                let m = (w * TILE_VOXELS) as u32 + bit;
                bits &= bits - 1;
                let at = (slot * TILE_VOXELS + bit as usize) * STRIDE;
                let s: &mut [f32; STRIDE] =
                    (&mut self.sums[at..at + STRIDE]).try_into().expect("STRIDE floats");
                let mut sum = [0.0f32; COLOR_STRIDE];
                sum[..STRIDE].copy_from_slice(s);
                *s = [0.0; STRIDE];
                out.push(f(BuildVoxel {
                    morton: m,
                    normal_sum: [sum[0], sum[1], sum[2]],
                    color_sum: [sum[3], sum[4], sum[5]],
                    color_weight: sum[6],
                    faces: 0,
                }));
            }
        }
        self.used = 0;
        out
    }
}

/// Which voxels a triangle sets (Laine, "A topological approach to
/// voxelization", via seed 003 §3.1.2). Each voxel has a *target* inside its
/// closed cube; the voxel is set iff the triangle meets the target.
///
/// - `Conservative`: the whole cube. Every voxel the surface touches.
/// - `Separating26`: the 13 segments through the centre to the 26 neighbours'
///   directions. A 26-connected path of unset voxels steps between centres
///   along exactly those segments, so it cannot cross a closed surface.
/// - `Separating6`: the 3 axis segments through the centre; blocks 6-paths.
///
/// Targets nest, so 6-separating ⊆ 26-separating ⊆ conservative.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Topology {
    #[default]
    Conservative,
    Separating26,
    Separating6,
}

impl Topology {
    pub fn name(self) -> &'static str {
        match self {
            Topology::Conservative => "conservative",
            Topology::Separating26 => "26-separating",
            Topology::Separating6 => "6-separating",
        }
    }
}

/// Half-extents (in voxels) of the target segments through a voxel centre:
/// 3 axes, then 6 face diagonals, then 4 body diagonals.
const TARGET_SEGMENTS: [[f64; 3]; 13] = [
    [0.5, 0.0, 0.0],
    [0.0, 0.5, 0.0],
    [0.0, 0.0, 0.5],
    [0.5, 0.5, 0.0],
    [0.5, -0.5, 0.0],
    [0.5, 0.0, 0.5],
    [0.5, 0.0, -0.5],
    [0.0, 0.5, 0.5],
    [0.0, 0.5, -0.5],
    [0.5, 0.5, 0.5],
    [0.5, 0.5, -0.5],
    [0.5, -0.5, 0.5],
    [0.5, -0.5, -0.5],
];

fn orient(a: [f64; 3], b: [f64; 3], c: [f64; 3], d: [f64; 3]) -> f64 {
    dot(cross(sub(b, a), sub(c, a)), sub(d, a))
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Closed segment–triangle test by signed volumes, with a tolerance that only
/// ever adds hits. A segment lying in the triangle's plane counts as a hit:
/// keeping such a voxel can only thicken the surface, never open a hole.
pub fn segment_meets_triangle(p0: [f64; 3], p1: [f64; 3], t: &[[f64; 3]; 3]) -> bool {
    const REL: f64 = 1e-10;
    let n = norm(cross(sub(t[1], t[0]), sub(t[2], t[0])));
    let seg = norm(sub(p1, p0));
    let (d0, d1) = (orient(t[0], t[1], t[2], p0), orient(t[0], t[1], t[2], p1));
    let eps_d = REL * n * (1.0 + seg);
    if (d0 > eps_d && d1 > eps_d) || (d0 < -eps_d && d1 < -eps_d) {
        return false;
    }
    if d0.abs() <= eps_d && d1.abs() <= eps_d {
        return true;
    }
    let r = t.iter().map(|&q| norm(sub(q, p0))).fold(0.0, f64::max);
    let eps_s = REL * seg * r * r;
    let s = [orient(p0, p1, t[0], t[1]), orient(p0, p1, t[1], t[2]), orient(p0, p1, t[2], t[0])];
    let any_neg = s.iter().any(|&v| v < -eps_s);
    let any_pos = s.iter().any(|&v| v > eps_s);
    !(any_neg && any_pos)
}

/// Whether the triangle meets voxel `c`'s target for `topology`.
pub fn triangle_meets_target(tri: &[[f64; 3]; 3], c: [i64; 3], topology: Topology) -> bool {
    triangle_touches_voxel(tri, c) && meets_segments(tri, c, topology)
}

/// The segment part of [`triangle_meets_target`], for a voxel the triangle touches.
fn meets_segments(tri: &[[f64; 3]; 3], c: [i64; 3], topology: Topology) -> bool {
    let segments = match topology {
        Topology::Conservative => return true, // every target lies inside the closed cube
        Topology::Separating26 => &TARGET_SEGMENTS[..],
        Topology::Separating6 => &TARGET_SEGMENTS[..3],
    };
    let m = c.map(|v| v as f64 + 0.5);
    segments.iter().any(|h| {
        let p0 = [m[0] - h[0], m[1] - h[1], m[2] - h[2]];
        let p1 = [m[0] + h[0], m[1] + h[1], m[2] + h[2]];
        segment_meets_triangle(p0, p1, tri)
    })
}

/// Calls `hit` for every voxel in the closed index box `[lo, hi]` whose
/// `topology` target the triangle meets. Columns along the dominant normal axis are narrowed
/// to the slab the triangle's plane crosses, so large triangles cost their
/// area, not their bounding volume. The box must lie within one 64³ block.
pub fn for_each_touched_voxel(
    tri: &[[f64; 3]; 3],
    n: [f64; 3],
    lo: [i64; 3],
    hi: [i64; 3],
    topology: Topology,
    mut hit: impl FnMut([i64; 3]),
) {
    debug_assert!((0..3).all(|a| hi[a] - lo[a] < BLOCK_SIZE as i64));
    if (0..3).any(|a| hi[a] < lo[a]) {
        return; // the triangle's bounds miss the block
    }
    let sat = TriangleSat::new(tri, lo);
    let plane = PlaneSlab::new(tri, n);
    let [u, v, w] = plane.axes;
    let slab = |cu: i64, cv: i64| plane.range(cu, cv, lo[w], hi[w]);
    // The SAT's edge axes cross(unit_a, edge) have no a component, so each
    // tests a point of one coordinate plane: a = w the column (u, v), a = u
    // the pair (v, w), a = v the pair (u, w). Each such test passes on an
    // interval of w (see `w_interval`), found once per v (or u) rather than
    // per column; the plane normal is left for each column's slab.
    let column = [w, 3 + w, 6 + w];
    if (0..3).all(|a| hi[a] - lo[a] < SMALL as i64) {
        let hits = sat.small_box_hits([u, v, w], lo, hi, slab);
        for_each_bit(hits, |bit| {
            let mut p = [0i64; 3];
            p[u] = lo[u] + (bit / (SMALL * SMALL)) as i64;
            p[v] = lo[v] + (bit / SMALL % SMALL) as i64;
            p[w] = lo[w] + (bit % SMALL) as i64;
            if meets_segments(tri, p, topology) {
                hit(p);
            }
        });
        return;
    }
    let centre = |c: i64, a: usize| (c - lo[a]) as f64 + 0.5;
    let len_w = (hi[w] - lo[w] + 1) as usize;
    let mut by_v = [(0usize, 0usize); BLOCK_SIZE as usize];
    for cv in lo[v]..=hi[v] {
        by_v[(cv - lo[v]) as usize] = sat.w_interval([u, 3 + u, 6 + u], v, w, centre(cv, v), len_w);
    }
    let k = 9; // the plane normal
    let len_v = (hi[v] - lo[v] + 1) as usize;
    for cu in lo[u]..=hi[u] {
        let mu = centre(cu, u);
        let (u_first, u_last) = sat.w_interval([v, 3 + v, 6 + v], u, w, mu, len_w);
        if u_first > u_last {
            continue;
        }
        // The column axes' `d` is monotone in cv as the others are in cw: the
        // columns that pass are one run, found from its ends.
        let (v_lo, v_hi) = passing_run(len_v, |iv| sat.column_passes(column, u, v, mu, iv as f64 + 0.5));
        for cv in lo[v] + v_lo as i64..=lo[v] + v_hi as i64 {
            let mv = centre(cv, v);
            let (v_first, v_last) = by_v[(cv - lo[v]) as usize];
            let (w0, w1) = slab(cu, cv);
            // In `lo[w]`-relative indices, where both intervals live.
            let mut first = ((w0 - lo[w]).max(0) as usize).max(u_first).max(v_first);
            let mut last = ((w1 - lo[w]).min(len_w as i64 - 1)).max(-1);
            if last < 0 {
                continue;
            }
            last = (last as usize).min(u_last).min(v_last) as i64;
            let part = sat.axes[k][u] * mu + sat.axes[k][v] * mv;
            let touches = |j: usize| sat.passes(k, part + sat.axes[k][w] * (j as f64 + 0.5));
            // The normal's `d` is monotone in cw too: only the ends need finding.
            while first as i64 <= last && !touches(first) {
                first += 1;
            }
            while last > first as i64 && !touches(last as usize) {
                last -= 1;
            }
            for j in first as i64..=last {
                let mut p = [0i64; 3];
                p[u] = cu;
                p[v] = cv;
                p[w] = lo[w] + j;
                if meets_segments(tri, p, topology) {
                    hit(p);
                }
            }
        }
    }
}

/// A triangle's plane over the columns along its dominant normal axis: the
/// voxels of a column it can meet, which the SAT then decides one by one.
struct PlaneSlab {
    /// `[u, v, w]`: w the normal's dominant axis, u and v the next two cyclically.
    axes: [usize; 3],
    /// The plane as w = a - b·u - c·v.
    a: f64,
    b: f64,
    c: f64,
    /// Over a column's closed square [cu, cu+1] × [cv, cv+1] the plane spans
    /// [base - lo_off, base - hi_off], base its w at the corner (cu, cv).
    lo_off: f64,
    hi_off: f64,
}

impl PlaneSlab {
    fn new(tri: &[[f64; 3]; 3], n: [f64; 3]) -> Self {
        let w = (0..3).max_by(|&a, &b| n[a].abs().total_cmp(&n[b].abs())).unwrap_or(2);
        let (u, v) = ((w + 1) % 3, (w + 2) % 3);
        let (b, c) = (n[u] / n[w], n[v] / n[w]);
        Self {
            axes: [u, v, w],
            a: dot(n, tri[0]) / n[w],
            b,
            c,
            lo_off: b.max(0.0) + c.max(0.0),
            hi_off: b.min(0.0) + c.min(0.0),
        }
    }

    /// The closed range of cw, clamped to `[lo_w, hi_w]`, whose voxels in
    /// column (cu, cv) the plane can meet (empty when first > last).
    #[inline]
    fn range(&self, cu: i64, cv: i64, lo_w: i64, hi_w: i64) -> (i64, i64) {
        // Voxel cw's cube spans [cw, cw+1] in w, so it can meet the plane iff
        // cw ∈ [ceil(wmin) - 1, floor(wmax)], i.e. [floor(wmin - slack), floor(wmax + slack)]:
        // the slack also covers rounding and the SAT's grown cube (≤ 3e-9 voxels).
        const SLACK: f64 = 1e-7;
        let base = self.a - self.b * cu as f64 - self.c * cv as f64;
        (fast_floor(base - self.lo_off - SLACK).max(lo_w), fast_floor(base - self.hi_off + SLACK).min(hi_w))
    }
}

/// Voxels an edge of the boxes [`TriangleSat::small_box_hits`] takes: their
/// voxels fit one u64, and nearly every triangle's box at a scan's own
/// resolution is one.
const SMALL: usize = 4;
const _: () = assert!(SMALL * SMALL * SMALL <= 64, "a small box's voxels fit a u64");

/// The closed run of indices below `len` where `passes` holds, given that it
/// holds on one run (or nowhere: then first > last), found from both ends.
/// Always inlined: called per row with a closure of a few multiplies, a call
/// per test would cost more than the test.
#[inline(always)]
fn passing_run(len: usize, passes: impl Fn(usize) -> bool) -> (usize, usize) {
    let mut first = 0;
    while first < len && !passes(first) {
        first += 1;
    }
    if first == len {
        return (1, 0);
    }
    let mut last = len - 1;
    while last > first && !passes(last) {
        last -= 1;
    }
    (first, last)
}

/// Calls `f` with the index of every set bit of `bits`, lowest first.
#[inline]
fn for_each_bit(mut bits: u64, mut f: impl FnMut(usize)) {
    while bits != 0 {
        f(bits.trailing_zeros() as usize);
        bits &= bits - 1;
    }
}

/// `floor` without a libm call (the default x86-64 target has no SSE4.1 round)
/// and, on the grid's range, without the saturating float-to-int conversion's
/// checks: adding 1.5·2^52 leaves round(x) in the low bits of the sum's
/// representation (|x| < 2^51, where one ulp of the sum is 1). Outside that
/// it saturates, where the callers' clamps take over. The correction is a 0 or 1,
/// not a branch: its sign is a coin toss.
#[inline]
fn fast_floor(x: f64) -> i64 {
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    if x.abs() < (1u64 << 51) as f64 {
        let r = (x + MAGIC).to_bits() as i64 - MAGIC.to_bits() as i64;
        return r - i64::from((r as f64) > x);
    }
    // NaN too (to 0, as `as` does).
    let i = x as i64;
    i.saturating_sub(i64::from((i as f64) > x))
}

/// Separating-axis test (Akenine-Möller) of a triangle against the closed unit
/// cube at integer corner `c`. The cube is grown by a relative hair so that
/// touching contacts lost to rounding still count: conservative by design.
pub fn triangle_touches_voxel(tri: &[[f64; 3]; 3], c: [i64; 3]) -> bool {
    const H: f64 = 0.5 + 1e-9;
    let centre = c.map(|v| v as f64 + 0.5);
    let p = tri.map(|q| sub(q, centre));
    // 3 box face normals.
    for a in 0..3 {
        let (mn, mx) = project(&p, std::array::from_fn(|k| if k == a { 1.0 } else { 0.0 }));
        if mn > H || mx < -H {
            return false;
        }
    }
    TriangleSat::new(tri, c).touches(c)
}

/// The triangle's side of the separating-axis test, computed once: for the
/// 9 edge × box-axis directions and the plane normal, the interval the
/// triangle projects to, widened by the grown cube's radius. A voxel then
/// costs one dot product per axis. The box face axes are not tested: callers
/// only ask about voxels in the triangle's closed bounding box, whose cubes
/// always overlap it on those axes.
struct TriangleSat {
    /// An integer corner near the triangle; coordinates are taken relative to
    /// it so that products stay small and precise far from the grid origin.
    origin: [i64; 3],
    axes: [[f64; 3]; 10],
    lo: [f64; 10],
    hi: [f64; 10],
}

impl TriangleSat {
    fn new(tri: &[[f64; 3]; 3], origin: [i64; 3]) -> Self {
        const H: f64 = 0.5 + 1e-9;
        let o = origin.map(|v| v as f64);
        let p = tri.map(|q| sub(q, o));
        let e = [sub(p[1], p[0]), sub(p[2], p[1]), sub(p[0], p[2])];
        let mut axes = [[0.0; 3]; 10];
        let mut lo = [0.0; 10];
        let mut hi = [0.0; 10];
        // cross(unit_a, e) is (-e[a2], e[a1]) at (a1, a2) = (a+1, a+2) and zero at a:
        // equal in value (up to the sign of zero, which no comparison sees) to
        // the full cross product, and its projections are the full dot
        // products less their zero term (x + ±0 = x, and a sum of two commutes).
        for (i, ei) in e.iter().enumerate() {
            for a in 0..3 {
                let (a1, a2) = ((a + 1) % 3, (a + 2) % 3);
                let k = 3 * i + a;
                axes[k][a1] = -ei[a2];
                axes[k][a2] = ei[a1];
                let r = H * (ei[a2].abs() + ei[a1].abs());
                let d = p.map(|q| q[a1] * axes[k][a1] + q[a2] * axes[k][a2]);
                let (mn, mx) = min_max3(d);
                lo[k] = mn - r;
                hi[k] = mx + r;
            }
        }
        axes[9] = cross(e[0], e[1]);
        let ax = axes[9];
        let r = H * (ax[0].abs() + ax[1].abs() + ax[2].abs());
        let (mn, mx) = min_max3(p.map(|q| dot(q, ax)));
        lo[9] = mn - r;
        hi[9] = mx + r;
        Self { origin, axes, lo, hi }
    }

    /// Whether `d`, a point's projection on axis `k`, lies in the axis's interval.
    /// `&`, not `&&`: the tests are cheap and their outcomes unpredictable, so
    /// evaluating both (and, in the callers, every axis) beats branching on each.
    #[inline]
    fn passes(&self, k: usize, d: f64) -> bool {
        (d >= self.lo[k]) & (d <= self.hi[k])
    }

    /// Whether the column (centres `mu`, `mv`) passes the three edge axes
    /// `column`, which have no component along the column.
    #[inline]
    fn column_passes(&self, column: [usize; 3], u: usize, v: usize, mu: f64, mv: f64) -> bool {
        column.iter().fold(true, |ok, &k| ok & self.passes(k, self.axes[k][u] * mu + self.axes[k][v] * mv))
    }

    /// Whether centre `mw` along `w` passes the three edge axes `ks`, given
    /// `part`, each axis's product with the point's other coordinate.
    #[inline]
    fn edge_axes_pass(&self, ks: [usize; 3], part: [f64; 3], w: usize, mw: f64) -> bool {
        (0..3).fold(true, |ok, i| ok & self.passes(ks[i], part[i] + self.axes[ks[i]][w] * mw))
    }

    /// Bit j: centre j + 0.5 along w (j < [`SMALL`]) passes the edge axes
    /// `ks`, which have no component along their plane's third axis, at
    /// centre `m` along `a`: [`Self::edge_axes_pass`]'s floats, lane by lane.
    #[inline(always)]
    fn run_mask(&self, ks: [usize; 3], a: usize, m: f64, w: usize) -> u64 {
        self.mask_of(ks.map(|k| (self.axes[k][a] * m, k)), w)
    }

    /// Bit j: for every `(part, k)`, `part + axis_k[w]·(j + 0.5)` passes axis k.
    /// Fixed-length arrays, so the lanes are straight-line code.
    #[inline(always)]
    fn mask_of<const N: usize>(&self, tests: [(f64, usize); N], w: usize) -> u64 {
        const CENTRES: [f64; SMALL] = [0.5, 1.5, 2.5, 3.5];
        let mut pass = [true; SMALL];
        for (part, k) in tests {
            let slope = self.axes[k][w];
            for (p, x) in pass.iter_mut().zip(CENTRES) {
                *p &= self.passes(k, part + slope * x);
            }
        }
        pass.iter().enumerate().fold(0, |bits, (j, &p)| bits | u64::from(p) << j)
    }

    /// [`for_each_touched_voxel`]'s voxels for a box `[lo, hi]` (the
    /// SAT's origin) under [`SMALL`] voxels an edge, as bits
    /// `(SMALL·iu + iv)·SMALL + iw` of the `lo`-relative indices along
    /// `[u, v, w]`; `slab(cu, cv)` is the closed range of cw the plane
    /// can reach in that column. Float for float the sweep's tests, without
    /// its branches: each plane's tests as a mask over a fixed run of w
    /// (beyond the box is masked off), ANDed per column.
    #[inline]
    fn small_box_hits(
        &self,
        [u, v, w]: [usize; 3],
        lo: [i64; 3],
        hi: [i64; 3],
        slab: impl Fn(i64, i64) -> (i64, i64),
    ) -> u64 {
        let (nu, nv, nw) = ((hi[u] - lo[u] + 1) as usize, (hi[v] - lo[v] + 1) as usize, hi[w] - lo[w] + 1);
        let mut by_v = [0u64; SMALL];
        for (iv, bits) in by_v.iter_mut().enumerate().take(nv) {
            *bits = self.run_mask([u, 3 + u, 6 + u], v, iv as f64 + 0.5, w);
        }
        let (column, k) = ([w, 3 + w, 6 + w], 9);
        let mut hits = 0u64;
        for iu in 0..nu {
            let mu = iu as f64 + 0.5;
            let cu = lo[u] + iu as i64;
            let by_u = self.run_mask([v, 3 + v, 6 + v], u, mu, w) & ((1 << nw) - 1);
            for (iv, &by_v) in by_v.iter().enumerate().take(nv) {
                let mv = iv as f64 + 0.5;
                let in_column = self.column_passes(column, u, v, mu, mv);
                let (w0, w1) = slab(cu, lo[v] + iv as i64);
                // [w0, w1] as bits of lo[w]-relative indices: w0 ≥ lo[w], w1 ≤ hi[w].
                let below = (1u64 << (w0 - lo[w]).min(SMALL as i64)) - 1;
                let through = (1u64 << (w1 - lo[w] + 1).clamp(0, SMALL as i64)) - 1;
                let part = self.axes[k][u] * mu + self.axes[k][v] * mv;
                let normal = self.mask_of([(part, k)], w);
                let bits = by_u & by_v & through & !below & normal & 0u64.wrapping_sub(u64::from(in_column));
                hits |= bits << ((SMALL * iu + iv) * SMALL);
            }
        }
        hits
    }

    /// The `origin[w]`-relative closed interval (empty when first > last) of
    /// indices j < `len` whose cube centre j + 0.5 passes the three edge axes
    /// `ks`, which have no component along the plane's third axis, at centre
    /// coordinate `m` along `a`. Each axis's `d = axis[a]·m + axis[w]·(j + 0.5)`
    /// is monotone in j (a fixed product plus the product of an exact,
    /// increasing centre, and rounding is monotone), so each test passes on an
    /// interval and all three on the intersection: only its ends need finding.
    #[inline]
    fn w_interval(&self, ks: [usize; 3], a: usize, w: usize, m: f64, len: usize) -> (usize, usize) {
        let part = ks.map(|k| self.axes[k][a] * m);
        passing_run(len, |j| self.edge_axes_pass(ks, part, w, j as f64 + 0.5))
    }

    /// Whether the closed (grown) cube at integer corner `c` meets the triangle.
    #[inline]
    fn touches(&self, c: [i64; 3]) -> bool {
        let centre: [f64; 3] = std::array::from_fn(|a| (c[a] - self.origin[a]) as f64 + 0.5);
        (0..10).all(|k| {
            let d = dot(centre, self.axes[k]);
            d >= self.lo[k] && d <= self.hi[k]
        })
    }
}

/// The least and greatest of three numbers, none NaN: `f64::min`'s values
/// (but maybe not its sign of a zero, which no comparison sees), without its NaN handling.
#[inline]
fn min_max3(d: [f64; 3]) -> (f64, f64) {
    let pick = |take_first: bool, x: f64, y: f64| if take_first { x } else { y };
    let (mn, mx) = (pick(d[0] < d[1], d[0], d[1]), pick(d[0] > d[1], d[0], d[1]));
    (pick(mn < d[2], mn, d[2]), pick(mx > d[2], mx, d[2]))
}

fn project(p: &[[f64; 3]; 3], ax: [f64; 3]) -> (f64, f64) {
    let d = p.map(|q| dot(q, ax));
    (d[0].min(d[1]).min(d[2]), d[0].max(d[1]).max(d[2]))
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};
    use voxstream_format::morton3;

    /// Fails if `fast_floor` differs from `f64::floor` at integers, half-way
    /// points, a hair either side of them, random values over the grid and
    /// far beyond it (the saturating path), and at infinities.
    #[test]
    fn fast_floor_is_floor() {
        let mut rng = StdRng::seed_from_u64(7);
        let mut xs =
            vec![0.0, -0.0, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300, 2f64.powi(51), -(2f64.powi(51))];
        for i in -70_000i64..70_000 {
            let x = i as f64;
            xs.extend([x, x + 0.5, x.next_up(), x.next_down(), (x + 0.5).next_up(), (x + 0.5).next_down()]);
        }
        for _ in 0..200_000 {
            xs.push(rng.random_range(-1e6..1e6));
            xs.push(rng.random_range(-1e18..1e18));
        }
        for x in xs {
            assert_eq!(fast_floor(x), x.floor() as i64, "floor({x:e})");
        }
    }

    /// Fails if the table lookup differs from `morton3` anywhere in a block.
    #[test]
    fn local_morton_is_morton3() {
        for z in 0..64 {
            for y in 0..64 {
                for x in 0..64 {
                    assert_eq!(local_morton([x, y, z]), morton3(x as u32, y as u32, z as u32) as usize);
                }
            }
        }
    }

    /// The sweep as it was before its setup and tests were factored by
    /// coordinate plane (float for float the same tests, fewer of them): the
    /// voxel sets must not change.
    #[allow(clippy::needless_range_loop)]
    fn reference_sat(tri: &[[f64; 3]; 3], origin: [i64; 3]) -> TriangleSat {
        const H: f64 = 0.5 + 1e-9;
        let o = origin.map(|v| v as f64);
        let p = tri.map(|q| sub(q, o));
        let e = [sub(p[1], p[0]), sub(p[2], p[1]), sub(p[0], p[2])];
        let mut axes = [[0.0; 3]; 10];
        let mut lo = [0.0; 10];
        let mut hi = [0.0; 10];
        let mut k = 0;
        for ei in e {
            for a in 0..3 {
                let mut unit = [0.0; 3];
                unit[a] = 1.0;
                axes[k] = cross(unit, ei);
                k += 1;
            }
        }
        axes[9] = cross(e[0], e[1]);
        for k in 0..10 {
            let ax = axes[k];
            let r = H * (ax[0].abs() + ax[1].abs() + ax[2].abs());
            let (mn, mx) = project(&p, ax);
            lo[k] = mn - r;
            hi[k] = mx + r;
        }
        TriangleSat { origin, axes, lo, hi }
    }

    fn reference_sweep(
        tri: &[[f64; 3]; 3],
        n: [f64; 3],
        lo: [i64; 3],
        hi: [i64; 3],
        topology: Topology,
        mut hit: impl FnMut([i64; 3]),
    ) {
        let sat = reference_sat(tri, lo);
        // The plane's slab is not what the factoring changed: both sweeps share it.
        let plane = PlaneSlab::new(tri, n);
        let [u, v, w] = plane.axes;
        // SAT axes cross(unit_w, edge) (k = 3·edge + w) have no w component: their
        // test is the same for a whole column, so it runs once per column. The
        // other axes cost one multiply-add per voxel on top of the column's part.
        let column_axes = [w, 3 + w, 6 + w];
        let voxel_axes: [usize; 7] = {
            let mut out = [9; 7];
            for (i, k) in (0..9).filter(|k| k % 3 != w).enumerate() {
                out[i] = k;
            }
            out
        };
        let centre = |c: i64, a: usize| (c - sat.origin[a]) as f64 + 0.5;
        for cu in lo[u]..=hi[u] {
            let mu = centre(cu, u);
            for cv in lo[v]..=hi[v] {
                let mv = centre(cv, v);
                // `&`, not `&&` or `all`: the tests are cheap and their outcomes
                // unpredictable, so evaluating all beats branching on each.
                let in_column = column_axes.iter().fold(true, |ok, &k| {
                    let d = sat.axes[k][u] * mu + sat.axes[k][v] * mv;
                    ok & (d >= sat.lo[k]) & (d <= sat.hi[k])
                });
                if !in_column {
                    continue;
                }
                let part = voxel_axes.map(|k| sat.axes[k][u] * mu + sat.axes[k][v] * mv);
                let (w0, w1) = plane.range(cu, cv, lo[w], hi[w]);
                let touches = |cw: i64| {
                    let mw = centre(cw, w);
                    (0..7).fold(true, |ok, i| {
                        let k = voxel_axes[i];
                        let d = part[i] + sat.axes[k][w] * mw;
                        ok & (d >= sat.lo[k]) & (d <= sat.hi[k])
                    })
                };
                // Each axis's `d` is monotone in cw (a fixed product and sum of an
                // increasing exact centre, and rounding is monotone), so each test
                // passes on an interval of the column and all of them on the
                // intersection: only its ends need finding, from both sides.
                let mut first = w0;
                while first <= w1 && !touches(first) {
                    first += 1;
                }
                let mut last = w1;
                while last > first && !touches(last) {
                    last -= 1;
                }
                for cw in first..=last {
                    let mut p = [0i64; 3];
                    p[u] = cu;
                    p[v] = cv;
                    p[w] = cw;
                    if meets_segments(tri, p, topology) {
                        hit(p);
                    }
                }
            }
        }
    }

    /// Calls `f` with the triangle's voxel box clipped to each block its bounds
    /// overlap, as `BlockVoxelizer::add` clips it.
    fn for_block_box(tri: &[[f64; 3]; 3], res: i64, mut f: impl FnMut([i64; 3], [i64; 3])) {
        let (full_lo, full_hi) = voxel_range(tri, res);
        for_each_block(tri, res, |b| {
            let (lo, hi) = clip_to_block(full_lo, full_hi, b.map(|c| c as i64 * BLOCK_SIZE as i64));
            f(lo, hi);
        });
    }

    /// Both sweeps' voxels for `tri` in every block its bounds overlap; false on any difference.
    fn sweeps_agree(tri: &[[f64; 3]; 3], res: i64) -> bool {
        let n = cross(sub(tri[1], tri[0]), sub(tri[2], tri[0]));
        let mut ok = true;
        for_block_box(tri, res, |lo, hi| {
            let (mut got, mut want) = (Vec::new(), Vec::new());
            for_each_touched_voxel(tri, n, lo, hi, Topology::Conservative, |p| got.push(p));
            reference_sweep(tri, n, lo, hi, Topology::Conservative, |p| want.push(p));
            ok &= got == want;
        });
        ok
    }

    /// The factored sweep sets the same voxels as the reference, float for
    /// float, on triangles made to hit edge cases: vertices and edges on
    /// integer planes, axis-parallel edges, slivers, and sizes from a hair
    /// to a block, across block boundaries.
    #[test]
    fn sweep_matches_the_reference() {
        let mut rng = StdRng::seed_from_u64(8);
        let mut checked = 0;
        for i in 0..40000 {
            let size = [0.01, 0.4, 1.0, 2.5, 7.0, 40.0][i % 6];
            let c: [f64; 3] = std::array::from_fn(|_| rng.random_range(50.0..78.0));
            let mut tri: [[f64; 3]; 3] =
                std::array::from_fn(|_| std::array::from_fn(|a| c[a] + rng.random_range(-size..size)));
            match i % 5 {
                // Snapped to quarter voxels: touching contacts on every axis.
                0 => tri = tri.map(|p| p.map(|x| (x * 4.0).round() / 4.0)),
                // One axis-parallel edge.
                1 => tri[1][i % 3] = tri[0][i % 3],
                // Flat on an integer plane.
                2 => {
                    for p in &mut tri {
                        p[i % 3] = c[i % 3].floor();
                    }
                }
                _ => {}
            }
            if !valid_triangle(&tri) {
                continue;
            }
            assert!(sweeps_agree(&tri, 256), "triangle {i} {tri:?}");
            checked += 1;
        }
        assert!(checked > 35000, "only {checked} valid triangles");
    }

    /// Times both sweeps over a mesh's grid triangles, alternating.
    fn bench_sweeps(mesh: &crate::pipeline::read::TriangleMesh, frame: &GridFrame) {
        let res = frame.resolution as i64;
        let mut jobs = Vec::new();
        for t in 0..mesh.triangles.len() {
            if let Some(g) = to_grid(mesh.triangle(t), frame) {
                let n = cross(sub(g[1], g[0]), sub(g[2], g[0]));
                for_block_box(&g, res, |lo, hi| jobs.push((g, n, lo, hi)));
            }
        }
        let (mut new, mut old) = (std::time::Duration::ZERO, std::time::Duration::ZERO);
        for _ in 0..5 {
            let t = std::time::Instant::now();
            let mut hits = 0u64;
            for (g, n, lo, hi) in &jobs {
                for_each_touched_voxel(g, *n, *lo, *hi, Topology::Conservative, |p| hits += p[0] as u64);
            }
            std::hint::black_box(hits);
            new += t.elapsed();
            let t = std::time::Instant::now();
            let mut hits = 0u64;
            for (g, n, lo, hi) in &jobs {
                reference_sweep(g, *n, *lo, *hi, Topology::Conservative, |p| hits += p[0] as u64);
            }
            std::hint::black_box(hits);
            old += t.elapsed();
        }
        eprintln!("  {} jobs: sweep {:?}, reference {:?}", jobs.len(), new / 5, old / 5);
    }

    /// [`sweep_matches_the_reference`] on real scans: `VOXSTREAM_SWEEP_MESHES`
    /// lists `path[:resolution]` items, comma-separated (auto when no resolution).
    #[test]
    #[ignore = "needs meshes; run with VOXSTREAM_SWEEP_MESHES"]
    fn sweep_matches_the_reference_on_meshes() {
        let list = std::env::var("VOXSTREAM_SWEEP_MESHES").expect("VOXSTREAM_SWEEP_MESHES");
        for item in list.split(',') {
            let (path, res) = match item.rsplit_once(':') {
                Some((p, r)) => (p, Resolution::Explicit(r.parse().expect("resolution"))),
                None => (item, Resolution::Auto),
            };
            let (mesh, _) = crate::pipeline::read::read_mesh(std::path::Path::new(path)).expect("mesh");
            let mut bounds = Bounds::EMPTY;
            let mut edges = EdgeHistogram::default();
            for t in 0..mesh.triangles.len() {
                let tri = mesh.triangle(t);
                if valid_triangle(&tri) {
                    bounds.add_triangle(&tri);
                    edges.add_triangle(&tri);
                }
            }
            let (frame, _) = choose_resolution(&bounds, res, edges.median(), MAX_RESOLUTION, 0).unwrap();
            let res = frame.resolution as i64;
            let mut checked = 0u64;
            for t in 0..mesh.triangles.len() {
                if let Some(g) = to_grid(mesh.triangle(t), &frame) {
                    assert!(sweeps_agree(&g, res), "{path}: triangle {t} {g:?}");
                    checked += 1;
                }
            }
            eprintln!("{path} at {res}: {checked} triangles, the same voxels");
            if std::env::var_os("VOXSTREAM_SWEEP_BENCH").is_some() {
                bench_sweeps(&mesh, &frame);
            }
        }
    }

    /// Every voxel of the block the SAT says the triangle touches (the reference),
    /// searched over the triangle's bounds grown by two voxels.
    fn by_sat(tri: &[[f64; 3]; 3], key: BlockKey) -> Vec<u32> {
        let base = key.coord().map(|c| (c * BLOCK_SIZE) as i64);
        let range = |a: usize| {
            let lo = tri.iter().map(|p| p[a]).fold(f64::INFINITY, f64::min).floor() as i64 - 2;
            let hi = tri.iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max).floor() as i64 + 2;
            lo.max(base[a])..=hi.min(base[a] + BLOCK_SIZE as i64 - 1)
        };
        let mut out = Vec::new();
        for z in range(2) {
            for y in range(1) {
                for x in range(0) {
                    if triangle_touches_voxel(tri, [x, y, z]) {
                        let l = [x - base[0], y - base[1], z - base[2]].map(|c| c as u32);
                        out.push(morton3(l[0], l[1], l[2]));
                    }
                }
            }
        }
        out.sort();
        out
    }

    /// Small and thin triangles take the one-voxel and one-row shortcuts and
    /// larger ones the column sweep; all must agree with the plain SAT, also
    /// where a block boundary cuts the triangle.
    #[test]
    fn shortcuts_and_sweep_agree_with_the_sat() {
        let mut rng = StdRng::seed_from_u64(3);
        let mut vox = BlockVoxelizer::new();
        let mut rows = 0;
        for i in 0..3000 {
            let size = [0.05, 0.3, 0.9, 3.0][i % 4];
            let c: [f64; 3] = std::array::from_fn(|_| rng.random_range(60.0..68.0));
            let mut tri: [[f64; 3]; 3] =
                std::array::from_fn(|_| std::array::from_fn(|a| c[a] + rng.random_range(-size..size)));
            if i % 7 == 0 {
                // Flat in z on an integer plane: touching contacts.
                for p in &mut tri {
                    p[2] = c[2].floor();
                }
            }
            if !valid_triangle(&tri) {
                continue;
            }
            let (lo, hi) = voxel_range(&tri, 128);
            rows += usize::from((0..3).filter(|&a| hi[a] > lo[a]).count() == 1);
            for key in [BlockKey::new(0, 0, 0, 0), BlockKey::new(0, 1, 0, 0), BlockKey::new(0, 1, 1, 1)] {
                vox.add(key, &tri, None, 128, Topology::Conservative);
                let got: Vec<u32> =
                    vox.finish(key).map(|b| b.voxels.iter().map(|v| v.morton).collect()).unwrap_or_default();
                assert_eq!(got, by_sat(&tri, key), "triangle {i} {tri:?} in block {key}");
            }
        }
        assert!(rows > 300, "only {rows} one-row triangles");
    }
}
