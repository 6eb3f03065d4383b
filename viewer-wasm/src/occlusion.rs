//! Occlusion culling from GPU feedback (seed 003 §4): the frame's depth
//! buffer is copied into one of two readback buffers and mapped without
//! waiting; a frame or two later a max-depth pyramid (hierarchical Z) is built
//! from it and the bounding box of each block the traversal wanted to refine
//! in that frame is tested against it with that frame's matrix. A box whose
//! nearest point lies behind the farthest depth over its screen rectangle is
//! hidden, and so is everything below it: the traversal stops there (a parent
//! is a conservative proxy for its children).
//!
//! Why this and not occlusion queries: wgpu 30's WebGPU backend drops
//! `RenderPassDescriptor::occlusion_query_set` (backend/webgpu.rs never sets
//! it), so any `begin_occlusion_query` invalidates the whole frame in the
//! browser; queries worked natively (lavapipe) in our first version, but the
//! product runs in the browser. One compute pass (shaders/depth_reduce.wgsl)
//! first reduces the depth to the farthest value of each 4×4 tile, so the
//! main thread maps and scans a sixteenth of it: mapping the whole depth
//! buffer and building its pyramid was the viewer's longest main-thread work
//! (17 ms at 640×456 in Chromium). The coarser pyramid tests boxes smaller
//! than a tile against a tile's farthest depth, which is still conservative.
//! A pending pick reads that frame's depth whole instead (one pixel's exact
//! depth is what a pick needs).

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use rustc_hash::FxHashSet as HashSet;

use glam::{Mat4, Vec3, Vec4};
use voxstream_format::{BLOCK_SIZE, Block, BlockKey};

use crate::select::Aabb;

const IDLE: u8 = 0;
const MAPPING: u8 = 1;
const MAPPED: u8 = 2;
const FAILED: u8 = 3;

/// Pixels a side of the tiles the depth is reduced to before it is read back.
pub const DEPTH_TILE: u32 = 4;

/// What a readback buffer holds: the whole depth, or its reduced tiles.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct ReadbackLayout {
    texels: (u32, u32),
    row_bytes: u32,
    /// Pixels a side of one texel: 1 for the whole depth, [`DEPTH_TILE`] reduced.
    scale: u32,
}

impl ReadbackLayout {
    fn whole(size: (u32, u32)) -> Self {
        Self { texels: size, row_bytes: padded_row(size.0), scale: 1 }
    }

    fn reduced(size: (u32, u32)) -> Self {
        let texels = reduced_size(size);
        Self { texels, row_bytes: texels.0 * 4, scale: DEPTH_TILE }
    }

    fn bytes(&self) -> u64 {
        self.row_bytes as u64 * self.texels.1 as u64
    }
}

fn reduced_size(size: (u32, u32)) -> (u32, u32) {
    (size.0.div_ceil(DEPTH_TILE), size.1.div_ceil(DEPTH_TILE))
}

struct Readback {
    /// Big enough for the whole depth; a reduced copy uses its start.
    buffer: Option<wgpu::Buffer>,
    state: Arc<AtomicU8>,
    size: (u32, u32),
    layout: ReadbackLayout,
    view_proj: Mat4,
    tests: Vec<(BlockKey, Aabb)>,
    frame: u64,
}

/// The reduction pass and its buffers for one depth size.
struct DepthReduce {
    pipeline: wgpu::ComputePipeline,
    bind_layout: wgpu::BindGroupLayout,
    target: Option<ReduceTarget>,
}

struct ReduceTarget {
    size: (u32, u32),
    farthest: wgpu::Buffer,
    params: wgpu::Buffer,
}

impl DepthReduce {
    fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("depth_reduce.wgsl"),
            source: wgpu::ShaderSource::Wgsl(crate::shaders::DEPTH_REDUCE_WGSL.into()),
        });
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        };
        let bind_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("depth reduce"),
            entries: &[
                entry(
                    0,
                    wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Depth,
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                ),
                entry(
                    1,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: false },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                entry(
                    2,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("depth reduce"),
            bind_group_layouts: &[Some(&bind_layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("depth reduce"),
            layout: Some(&layout),
            module: &module,
            entry_point: Some("reduce_depth"),
            compilation_options: Default::default(),
            cache: None,
        });
        Self { pipeline, bind_layout, target: None }
    }

    fn target(&mut self, device: &wgpu::Device, size: (u32, u32)) -> &ReduceTarget {
        if self.target.as_ref().is_none_or(|t| t.size != size) {
            if let Some(t) = self.target.take() {
                t.farthest.destroy();
                t.params.destroy();
            }
            let out = reduced_size(size);
            let farthest = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("reduced depth"),
                size: out.0 as u64 * out.1 as u64 * 4,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let words: [u32; 8] = [size.0, size.1, out.0, out.1, DEPTH_TILE, 0, 0, 0];
            let params = wgpu::util::DeviceExt::create_buffer_init(
                device,
                &wgpu::util::BufferInitDescriptor {
                    label: Some("depth reduce params"),
                    contents: bytemuck::cast_slice(&words),
                    usage: wgpu::BufferUsages::UNIFORM,
                },
            );
            self.target = Some(ReduceTarget { size, farthest, params });
        }
        self.target.as_ref().expect("just made")
    }
}

/// What the depth of one frame says about the blocks tested in it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Visibility {
    pub frame: u64,
    pub hidden: HashSet<BlockKey>,
}

pub struct Occlusion {
    readbacks: [Readback; 2],
    reduce: Option<DepthReduce>,
    current: Option<usize>,
    /// A double-click waiting for a depth readback: the pixel and the frame it came in.
    pick: Option<((f32, f32), u64)>,
    /// The surface point under the last answered pick; `Some(None)` when it hit nothing.
    picked: Option<Option<Vec3>>,
}

impl Default for Occlusion {
    fn default() -> Self {
        let readback = || Readback {
            buffer: None,
            state: Arc::new(AtomicU8::new(IDLE)),
            size: (0, 0),
            layout: ReadbackLayout::default(),
            view_proj: Mat4::IDENTITY,
            tests: Vec::new(),
            frame: 0,
        };
        Self { readbacks: [readback(), readback()], reduce: None, current: None, pick: None, picked: None }
    }
}

/// GPU bytes of the two depth readbacks for a `width`×`height` view, the
/// reduced depth and its parameters.
pub fn occlusion_gpu_bytes(width: u32, height: u32) -> u64 {
    let (rw, rh) = reduced_size((width, height));
    2 * padded_row(width) as u64 * height as u64 + rw as u64 * rh as u64 * 4 + 32
}

fn padded_row(width: u32) -> u32 {
    (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT
}

impl Occlusion {
    /// Takes this frame's tests (blocks and their bounds); skipped while both
    /// readbacks are still in use.
    pub fn prepare(
        &mut self,
        device: &wgpu::Device,
        size: (u32, u32),
        view_proj: Mat4,
        tests: Vec<(BlockKey, Aabb)>,
        frame: u64,
    ) {
        self.current = None;
        if tests.is_empty() && self.pick.is_none() {
            return;
        }
        let Some(slot) = self.readbacks.iter().position(|r| r.state.load(Ordering::Acquire) == IDLE) else {
            return;
        };
        let r = &mut self.readbacks[slot];
        if r.size != size || r.buffer.is_none() {
            if let Some(b) = r.buffer.take() {
                b.destroy();
            }
            r.buffer = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("depth readback"),
                size: ReadbackLayout::whole(size).bytes(),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
            r.size = size;
        }
        r.layout = if self.pick.is_some() {
            ReadbackLayout::whole(size)
        } else {
            self.reduce.get_or_insert_with(|| DepthReduce::new(device)).target(device, size);
            ReadbackLayout::reduced(size)
        };
        r.view_proj = view_proj;
        r.tests = tests;
        r.frame = frame;
        self.current = Some(slot);
    }

    /// Copies the frame's depth, reduced or whole, into the readback (after
    /// the render pass). Without a copy nothing is mapped: stale bytes must
    /// never read as depth.
    pub fn encode_copy(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        depth: &wgpu::Texture,
        timer: Option<&crate::pass_timer::PassTimer>,
    ) {
        let Some(slot) = self.current else { return };
        let r = &self.readbacks[slot];
        let Some(buffer) = &r.buffer else { return };
        if (depth.width(), depth.height()) != r.size {
            self.current = None;
            return;
        }
        if r.layout.scale != 1 {
            let Some(target) = self.reduce.as_ref().and_then(|d| d.target.as_ref().map(|t| (d, t))) else {
                self.current = None;
                return;
            };
            let (reduce, target) = target;
            let view = depth.create_view(&wgpu::TextureViewDescriptor {
                aspect: wgpu::TextureAspect::DepthOnly,
                ..Default::default()
            });
            let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("depth reduce"),
                layout: &reduce.bind_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
                    wgpu::BindGroupEntry { binding: 1, resource: target.farthest.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: target.params.as_entire_binding() },
                ],
            });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("depth reduce"),
                    timestamp_writes: timer.and_then(|t| t.compute_writes("depth reduce")),
                });
                pass.set_pipeline(&reduce.pipeline);
                pass.set_bind_group(0, &bind, &[]);
                pass.dispatch_workgroups(r.layout.texels.0.div_ceil(8), r.layout.texels.1.div_ceil(8), 1);
            }
            encoder.copy_buffer_to_buffer(&target.farthest, 0, buffer, 0, r.layout.bytes());
            return;
        }
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: depth,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::DepthOnly,
            },
            wgpu::TexelCopyBufferInfo {
                buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(r.layout.row_bytes),
                    rows_per_image: Some(r.size.1),
                },
            },
            wgpu::Extent3d { width: r.size.0, height: r.size.1, depth_or_array_layers: 1 },
        );
    }

    /// Starts mapping this frame's readback (after the submit).
    pub fn after_submit(&mut self) {
        let Some(slot) = self.current.take() else { return };
        let r = &self.readbacks[slot];
        let Some(buffer) = &r.buffer else { return };
        r.state.store(MAPPING, Ordering::Release);
        let state = r.state.clone();
        buffer.map_async(wgpu::MapMode::Read, ..r.layout.bytes(), move |result| {
            state.store(if result.is_ok() { MAPPED } else { FAILED }, Ordering::Release);
        });
    }

    /// The newest finished test, if one finished since the last call.
    pub fn take_results(&mut self) -> Option<Visibility> {
        let mut newest: Option<Visibility> = None;
        for r in &mut self.readbacks {
            match r.state.load(Ordering::Acquire) {
                MAPPED => {
                    let Some(buffer) = &r.buffer else { continue };
                    let l = r.layout;
                    let answers_pick = self
                        .pick
                        .filter(|(_, since)| r.frame >= *since && l.scale == 1)
                        .map(|(pixel, _)| pixel);
                    let hidden = match buffer.get_mapped_range(..l.bytes()) {
                        Ok(view) => {
                            if let Some(pixel) = answers_pick {
                                let depth = depth_at(&view, r.size, l.row_bytes, pixel);
                                self.picked =
                                    Some(depth.and_then(|d| unproject(d, pixel, r.size, &r.view_proj)));
                                self.pick = None;
                            }
                            let depth = DepthPyramid::from_rows(&view, l.texels, l.row_bytes)
                                .with_pixel_scale(l.scale, r.size);
                            // A block with several boxes is hidden only if all of them are.
                            let mut visible = HashSet::default();
                            for (k, b) in &r.tests {
                                if !visible.contains(k) && !depth.hides(b, &r.view_proj) {
                                    visible.insert(*k);
                                }
                            }
                            r.tests.iter().map(|(k, _)| *k).filter(|k| !visible.contains(k)).collect()
                        }
                        Err(_) => HashSet::default(),
                    };
                    buffer.unmap();
                    r.state.store(IDLE, Ordering::Release);
                    // A readback taken only for a pick tested nothing: it says nothing about visibility.
                    if !r.tests.is_empty() && newest.as_ref().is_none_or(|v| v.frame < r.frame) {
                        newest = Some(Visibility { frame: r.frame, hidden });
                    }
                }
                FAILED => r.state.store(IDLE, Ordering::Release),
                _ => {}
            }
        }
        newest
    }
}

impl Occlusion {
    /// Asks for the surface under `pixel` (viewport pixels, row 0 at the top);
    /// answered by the first depth readback of frame `frame` or later.
    pub fn request_pick(&mut self, pixel: (f32, f32), frame: u64) {
        self.pick = Some((pixel, frame));
    }

    pub fn pick_pending(&self) -> bool {
        self.pick.is_some()
    }

    /// The answer to the last pick, once: `Some(None)` when the pixel showed no surface.
    pub fn take_picked(&mut self) -> Option<Option<Vec3>> {
        self.picked.take()
    }
}

/// The depth at `pixel` of row-padded f32 depth rows; `None` outside the image.
fn depth_at(bytes: &[u8], size: (u32, u32), row_bytes: u32, pixel: (f32, f32)) -> Option<f32> {
    let (x, y) = (pixel.0.floor(), pixel.1.floor());
    if !(x >= 0.0 && y >= 0.0 && x < size.0 as f32 && y < size.1 as f32) {
        return None;
    }
    let at = y as usize * row_bytes as usize + x as usize * 4;
    let b = bytes.get(at..at + 4)?;
    Some(f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// The grid-unit point a depth-buffer sample stands for, or `None` where the
/// depth is the clear value (nothing drawn) or the matrix is singular.
/// Invariant: projecting the result with `view_proj` gives back `pixel`'s centre and `depth`.
pub fn unproject(depth: f32, pixel: (f32, f32), size: (u32, u32), view_proj: &Mat4) -> Option<Vec3> {
    if !(depth.is_finite() && (0.0..1.0).contains(&depth)) {
        return None;
    }
    let ndc = Vec3::new(
        ((pixel.0.floor() + 0.5) / size.0 as f32) * 2.0 - 1.0,
        1.0 - ((pixel.1.floor() + 0.5) / size.1 as f32) * 2.0,
        depth,
    );
    let inverse = view_proj.inverse();
    let p = inverse * ndc.extend(1.0);
    (p.w.abs() > 1e-12 && p.is_finite()).then(|| p.truncate() / p.w)
}

/// Max-depth mips of a depth image: `mips[0]` is the image, each next level
/// holds the farthest depth of 2×2 texels of the one before. A texel of
/// `mips[0]` covers `scale`×`scale` pixels of a `size` image.
pub struct DepthPyramid {
    mips: Vec<(u32, u32, Vec<f32>)>,
    scale: u32,
    size: (u32, u32),
}

impl DepthPyramid {
    /// From tightly packed or row-padded f32 depth rows.
    pub fn from_rows(bytes: &[u8], size: (u32, u32), row_bytes: u32) -> Self {
        let (w, h) = size;
        let mut base = Vec::with_capacity((w * h) as usize);
        for y in 0..h as usize {
            let row = &bytes[y * row_bytes as usize..][..w as usize * 4];
            base.extend(row.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])));
        }
        Self::new(w, h, base)
    }

    pub fn new(width: u32, height: u32, depth: Vec<f32>) -> Self {
        let mut mips = vec![(width, height, depth)];
        while let Some((w, h, d)) = mips.last().filter(|(w, h, _)| *w > 1 || *h > 1) {
            let (nw, nh) = (w.div_ceil(2), h.div_ceil(2));
            let (w, h, cols) = (*w as usize, *h as usize, nw as usize);
            let mut next = Vec::with_capacity(cols * nh as usize);
            // Row by row, so the inner loop indexes two rows without clamping y
            // (this runs on the browser's main thread every feedback frame).
            for y in 0..nh as usize {
                let row = |r: usize| &d[r.min(h - 1) * w..][..w];
                let (r0, r1) = (row(2 * y), row(2 * y + 1));
                next.extend((0..cols).map(|x| {
                    let (x0, x1) = (2 * x, (2 * x + 1).min(w - 1));
                    0f32.max(r0[x0]).max(r0[x1]).max(r1[x0]).max(r1[x1])
                }));
            }
            mips.push((nw, nh, next));
        }
        Self { mips, scale: 1, size: (width, height) }
    }

    /// Declares the base level's texels to stand for `scale`×`scale` pixels of
    /// a `size` image (a reduced depth buffer).
    pub fn with_pixel_scale(mut self, scale: u32, size: (u32, u32)) -> Self {
        self.scale = scale.max(1);
        self.size = size;
        self
    }

    /// Whether the box lies wholly behind the depth over its screen
    /// rectangle. Conservative: a box crossing the near plane or the screen
    /// edge counts as visible.
    pub fn hides(&self, b: &Aabb, view_proj: &Mat4) -> bool {
        let (w, h) = (&self.size.0, &self.size.1);
        let (mut lo, mut hi, mut near) = (glam::Vec2::splat(f32::MAX), glam::Vec2::splat(f32::MIN), f32::MAX);
        for i in 0..8 {
            let p = Vec3::select(glam::BVec3::new(i & 1 != 0, i & 2 != 0, i & 4 != 0), b.max, b.min);
            let c: Vec4 = *view_proj * p.extend(1.0);
            if c.w <= 1e-6 || c.z < 0.0 {
                return false;
            }
            let ndc = c.truncate() / c.w;
            // NDC y up, pixel rows down.
            let px = glam::Vec2::new((ndc.x * 0.5 + 0.5) * *w as f32, (0.5 - ndc.y * 0.5) * *h as f32);
            lo = lo.min(px);
            hi = hi.max(px);
            near = near.min(ndc.z);
        }
        // One pixel of slack on each side for rasterisation rules.
        let (x0, y0) = ((lo.x - 1.0).floor().max(0.0) as u32, (lo.y - 1.0).floor().max(0.0) as u32);
        let (x1, y1) = ((hi.x + 1.0).ceil().min(*w as f32) as u32, (hi.y + 1.0).ceil().min(*h as f32) as u32);
        if x0 >= x1 || y0 >= y1 {
            // Off screen: the frustum test decides, not this one.
            return false;
        }
        // Pixels to base texels: the tiles that touch the rectangle.
        let (x0, y0, x1, y1) =
            (x0 / self.scale, y0 / self.scale, x1.div_ceil(self.scale), y1.div_ceil(self.scale));
        // The mip where the rectangle spans at most about 16 texels a side.
        let span = (x1 - x0).max(y1 - y0);
        let level = (span.div_ceil(16).max(1).ilog2() as usize).min(self.mips.len() - 1);
        let (mw, mh, d) = &self.mips[level];
        let (mx0, my0) = (x0 >> level, y0 >> level);
        let (mx1, my1) = ((x1 - 1) >> level, (y1 - 1) >> level);
        let mut farthest = 0f32;
        for y in my0..=my1.min(mh - 1) {
            for x in mx0..=mx1.min(mw - 1) {
                farthest = farthest.max(d[(y * mw + x) as usize]);
            }
        }
        near > farthest
    }
}

/// Cells a side of the split a block's region gets in [`OccupiedCells`]: two
/// per child octant, so a child's proxy is 2×2×2 cells of its parent.
const CELLS: u32 = 4;

/// The tight grid-unit bounds of a decoded block's voxels in each cell of a
/// 4×4×4 split of its region. They give occlusion tests much tighter proxies
/// than one box around a curved surface (whose box pokes past the silhouettes
/// in front of it): the block itself is tested as its 8 octants' boxes, a child
/// not yet loaded as the 8 cells of its octant. Conservative: a parent voxel is
/// occupied wherever a child voxel is, so the cells hold the child's surface.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupiedCells {
    key: BlockKey,
    cells: [Option<Aabb>; (CELLS * CELLS * CELLS) as usize],
    /// Each octant's union of its 8 cells: the block's own test boxes, asked
    /// for every frame, so worked out once.
    octants: [Option<Aabb>; 8],
}

impl OccupiedCells {
    pub fn new(block: &Block) -> Self {
        let key = block.key;
        let voxel = (1u64 << key.level) as f32;
        let origin = Vec3::new(key.x as f32, key.y as f32, key.z as f32) * (BLOCK_SIZE as f32 * voxel);
        let per_cell = BLOCK_SIZE / CELLS;
        let mut cells = [None; (CELLS * CELLS * CELLS) as usize];
        for v in &block.voxels {
            let [x, y, z] = v.local();
            let cell = (x / per_cell + CELLS * (y / per_cell + CELLS * (z / per_cell))) as usize;
            let min = origin + Vec3::new(x as f32, y as f32, z as f32) * voxel;
            let b = Aabb { min, max: min + Vec3::splat(voxel) };
            let slot: &mut Option<Aabb> = &mut cells[cell];
            *slot = Some(slot.map_or(b, |c| c.union(&b)));
        }
        Self::with_cells(key, cells)
    }

    fn with_cells(key: BlockKey, cells: [Option<Aabb>; (CELLS * CELLS * CELLS) as usize]) -> Self {
        let octants = std::array::from_fn(|o| {
            let o = o as u32;
            octant_cells(&cells, [o & 1, o >> 1 & 1, o >> 2]).reduce(|a, b| a.union(&b))
        });
        Self { key, cells, octants }
    }

    /// Bytes of [`OccupiedCells::to_bytes`]: each cell's min and max as f32 LE.
    pub const BYTES: usize = (CELLS * CELLS * CELLS) as usize * 6 * 4;

    /// The cells as bytes (an empty cell as NaNs), for a worker to send.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(Self::BYTES);
        for cell in &self.cells {
            let (min, max) = cell.map_or((Vec3::NAN, Vec3::NAN), |b| (b.min, b.max));
            for v in min.to_array().into_iter().chain(max.to_array()) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// The cells of block `key` from [`OccupiedCells::to_bytes`]; `None` unless exactly
    /// [`OccupiedCells::BYTES`] bytes.
    pub fn from_bytes(key: BlockKey, bytes: &[u8]) -> Option<Self> {
        if bytes.len() != Self::BYTES {
            return None;
        }
        let mut cells = [None; (CELLS * CELLS * CELLS) as usize];
        for (cell, b) in cells.iter_mut().zip(bytes.chunks_exact(24)) {
            let f: [f32; 6] =
                std::array::from_fn(|i| f32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap()));
            if !f[0].is_nan() {
                *cell = Some(Aabb { min: Vec3::new(f[0], f[1], f[2]), max: Vec3::new(f[3], f[4], f[5]) });
            }
        }
        Some(Self::with_cells(key, cells))
    }

    /// Boxes that together hold `key`'s surface: for the block itself its 8
    /// octants', for one of its children the cells of that child's octant;
    /// `None` for any other key. Empty octants are left out.
    pub fn boxes_for(&self, key: &BlockKey) -> Option<Vec<Aabb>> {
        let mut boxes = Vec::with_capacity(8);
        if *key == self.key {
            boxes.extend(self.octants.iter().flatten());
        } else if key.level + 1 == self.key.level && key.parent() == self.key {
            boxes.extend(octant_cells(&self.cells, [key.x & 1, key.y & 1, key.z & 1]));
        } else {
            return None;
        }
        Some(boxes)
    }
}

/// The occupied cells of octant `o` (each coordinate 0 or 1) of a block's 4×4×4 cells.
fn octant_cells(
    cells: &[Option<Aabb>; (CELLS * CELLS * CELLS) as usize],
    o: [u32; 3],
) -> impl Iterator<Item = Aabb> + '_ {
    let [ox, oy, oz] = o.map(|c| 2 * c);
    (0..8u32).filter_map(move |i| {
        cells[(ox + (i & 1) + CELLS * (oy + (i >> 1 & 1) + CELLS * (oz + (i >> 2)))) as usize]
    })
}

/// A block's test box: its tight bounds grown by one voxel of `drawn_level`,
/// the level drawn in its place (itself or a coarser stand-in), so the drawn
/// voxels of the block's own surface never hide it.
pub fn proxy_bounds(bounds: &Aabb, drawn_level: u8) -> Aabb {
    let grow = Vec3::splat((1u64 << drawn_level) as f32);
    Aabb { min: bounds.min - grow, max: bounds.max + grow }
}

/// Whether the eye is inside `bounds`: such a block is always visible.
pub fn contains_eye(bounds: &Aabb, eye: Vec3) -> bool {
    bounds.distance_to(eye) <= 0.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::OrbitCamera;
    use voxstream_format::PackedVoxel;

    /// A slanted sheet through a level-1 block and its pyramid child voxels: the
    /// parent's cells hold every voxel of each child, and are far tighter than
    /// the child's box.
    #[test]
    fn occupied_cells_hold_each_childs_voxels_and_are_tighter_than_its_box() {
        let parent = BlockKey { level: 1, x: 3, y: 0, z: 2 };
        let on_sheet = |x: u32, y: u32, z: u32| x.abs_diff(y) <= 1 && z < 64;
        // Child voxels (level 0, 128³ over the parent's region), and the parent's OR of them.
        let mut children: std::collections::HashMap<BlockKey, Vec<[u32; 3]>> = Default::default();
        let mut parent_voxels = std::collections::BTreeSet::new();
        for z in 0..128u32 {
            for y in 0..128u32 {
                for x in 0..128u32 {
                    if on_sheet(x, y, z) {
                        let child = BlockKey {
                            level: 0,
                            x: 2 * parent.x + x / 64,
                            y: 2 * parent.y + y / 64,
                            z: 2 * parent.z + z / 64,
                        };
                        children.entry(child).or_default().push([x % 64, y % 64, z % 64]);
                        parent_voxels.insert([x / 2, y / 2, z / 2]);
                    }
                }
            }
        }
        let block = Block {
            key: parent,
            voxels: parent_voxels.iter().map(|&l| PackedVoxel::new(l, 0x3f, 0)).collect(),
        };
        let cells = OccupiedCells::new(&block);
        assert!(children.len() >= 2);
        for (child, voxels) in &children {
            let boxes = cells.boxes_for(child).expect("a child of the block");
            let origin = Vec3::new(child.x as f32, child.y as f32, child.z as f32) * 64.0;
            for v in voxels {
                let (lo, hi) = (
                    origin + Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32),
                    origin + Vec3::new(v[0] as f32 + 1.0, v[1] as f32 + 1.0, v[2] as f32 + 1.0),
                );
                assert!(
                    boxes.iter().any(|b| b.min.cmple(lo).all() && b.max.cmpge(hi).all()),
                    "{child:?} voxel {v:?} lies outside its proxies"
                );
            }
            if child.x % 2 != child.y % 2 {
                continue; // a child the sheet only grazes at an edge
            }
            // The diagonal sheet fills its box poorly; the cells leave most of it out.
            let volume = |b: &Aabb| (b.max - b.min).element_product();
            let whole = boxes.iter().copied().reduce(|a, b| a.union(&b)).unwrap();
            let cells_volume: f32 = boxes.iter().map(volume).sum();
            assert!(cells_volume < 0.6 * volume(&whole), "{child:?}: {cells_volume} of {}", volume(&whole));
        }
        // The block itself: its octants hold all its voxels too, and come back the same from bytes.
        let own = cells.boxes_for(&parent).unwrap();
        assert!(!own.is_empty() && own.len() <= 8);
        let origin = Vec3::new(parent.x as f32, parent.y as f32, parent.z as f32) * 128.0;
        for v in &parent_voxels {
            let lo = origin + Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32) * 2.0;
            assert!(
                own.iter().any(|b| b.min.cmple(lo).all() && b.max.cmpge(lo + 2.0).all()),
                "parent voxel {v:?} lies outside its octants"
            );
        }
        let again = OccupiedCells::from_bytes(parent, &cells.to_bytes()).unwrap();
        assert_eq!(again, cells);
        assert_eq!(again.boxes_for(&parent), Some(own));
        // Control: keys that are neither the block nor a child get no proxies.
        assert!(cells.boxes_for(&BlockKey { level: 0, x: 0, y: 0, z: 0 }).is_none());
        assert!(cells.boxes_for(&BlockKey { level: 2, x: 1, y: 0, z: 1 }).is_none());
    }

    #[test]
    fn a_picked_pixel_unprojects_onto_the_drawn_surface_and_the_clear_depth_onto_nothing() {
        let cam = OrbitCamera {
            target: Vec3::new(3.0, -2.0, 7.0),
            yaw: 0.4,
            pitch: 0.3,
            distance: 50.0,
            fov_y: 0.8,
            scene_radius: 30.0,
        };
        let (w, h) = (64u32, 48u32);
        let vp = cam.view_proj(w as f32 / h as f32);
        // A point on some surface, its pixel and its depth as the rasteriser would store them.
        let surface = cam.target + Vec3::new(4.0, 1.5, -2.0);
        let c = vp * surface.extend(1.0);
        let ndc = c.truncate() / c.w;
        let pixel = ((ndc.x * 0.5 + 0.5) * w as f32, (0.5 - ndc.y * 0.5) * h as f32);
        let mut rows = vec![0u8; (256 * h) as usize];
        let at = pixel.1 as usize * 256 + pixel.0 as usize * 4;
        rows[at..at + 4].copy_from_slice(&ndc.z.to_le_bytes());
        let depth = depth_at(&rows, (w, h), 256, pixel).expect("inside the image");
        assert_eq!(depth, ndc.z);
        let p = unproject(depth, pixel, (w, h), &vp).expect("a surface");
        // Within the half pixel the sample centre moves it: well under a grid unit at this range.
        let pixel_size = 2.0 * cam.distance * (cam.fov_y * 0.5).tan() / h as f32;
        assert!((p - surface).length() < pixel_size, "{p} vs {surface}");
        // Controls: the cleared depth and a pixel outside the image give nothing.
        assert_eq!(unproject(1.0, pixel, (w, h), &vp), None);
        assert_eq!(depth_at(&rows, (w, h), 256, (w as f32 + 1.0, 0.0)), None);
        assert_eq!(depth_at(&rows, (w, h), 256, (-1.0, 0.0)), None);
    }

    /// Looking down -Z from z = 100 at the origin.
    fn head_on_camera() -> OrbitCamera {
        OrbitCamera {
            target: Vec3::ZERO,
            yaw: 0.0,
            pitch: 0.0,
            distance: 100.0,
            fov_y: 0.8,
            scene_radius: 60.0,
        }
    }

    /// The depth buffer value of a wall facing the camera at height `z`.
    fn depth_of(vp: &Mat4, z: f32) -> f32 {
        let c = *vp * Vec4::new(0.0, 0.0, z, 1.0);
        c.z / c.w
    }

    #[test]
    fn each_mip_texel_is_the_farthest_of_the_texels_it_covers() {
        // Odd sizes: the last column and row of a level are their own pair.
        let (w, h) = (13u32, 7u32);
        let depth: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 101) as f32 / 100.0).collect();
        let p = DepthPyramid::new(w, h, depth.clone());
        let base = |x: u32, y: u32| depth[(y.min(h - 1) * w + x.min(w - 1)) as usize];
        for (level, (lw, lh, texels)) in p.mips.iter().enumerate() {
            let span = 1u32 << level;
            for y in 0..*lh {
                for x in 0..*lw {
                    let mut far = 0f32;
                    for sy in y * span..(y + 1) * span {
                        for sx in x * span..(x + 1) * span {
                            far = far.max(base(sx, sy));
                        }
                    }
                    assert_eq!(texels[(y * lw + x) as usize], far, "level {level} texel ({x}, {y})");
                }
            }
        }
        assert_eq!(p.mips.last().map(|m| (m.0, m.1)), Some((1, 1)));
        // Control: a texel set farther than any other reaches the top.
        let mut far = depth;
        far[(6 * w + 12) as usize] = 2.0;
        assert_eq!(DepthPyramid::new(w, h, far).mips.last().unwrap().2, vec![2.0]);
    }

    #[test]
    fn a_box_behind_a_near_wall_is_hidden_and_one_in_front_is_not() {
        // Looking down -Z from z = 100 at the origin; a wall fills the view at depth d.
        let cam = head_on_camera();
        let vp = cam.view_proj(1.0);
        let wall_depth = depth_of(&vp, 10.0);
        let pyramid = DepthPyramid::new(64, 64, vec![wall_depth; 64 * 64]);
        let behind = Aabb { min: Vec3::new(-5.0, -5.0, -20.0), max: Vec3::new(5.0, 5.0, -10.0) };
        let in_front = Aabb { min: Vec3::new(-5.0, -5.0, 15.0), max: Vec3::new(5.0, 5.0, 25.0) };
        let straddling = Aabb { min: Vec3::new(-5.0, -5.0, 0.0), max: Vec3::new(5.0, 5.0, 12.0) };
        assert!(pyramid.hides(&behind, &vp));
        assert!(!pyramid.hides(&in_front, &vp));
        assert!(!pyramid.hides(&straddling, &vp));
        // Control: a hole in the wall where the box projects makes it visible.
        let mut holed = vec![wall_depth; 64 * 64];
        holed[32 * 64 + 32] = 1.0;
        assert!(!DepthPyramid::new(64, 64, holed).hides(&behind, &vp));
        // An empty (cleared) depth buffer hides nothing.
        assert!(!DepthPyramid::new(64, 64, vec![1.0; 64 * 64]).hides(&behind, &vp));
    }

    #[test]
    fn a_reduced_depth_tests_boxes_in_pixels_not_in_tiles() {
        // A 66×50 view (not a multiple of the tile) reduced to 17×13 tiles.
        let cam = head_on_camera();
        let size = (66u32, 50u32);
        let vp = cam.view_proj(size.0 as f32 / size.1 as f32);
        let wall = depth_of(&vp, 10.0);
        let (tw, th) = reduced_size(size);
        assert_eq!((tw, th), (17, 13));
        let reduced = |depth: Vec<f32>| DepthPyramid::new(tw, th, depth).with_pixel_scale(DEPTH_TILE, size);
        let behind = Aabb { min: Vec3::new(-2.0, -2.0, -20.0), max: Vec3::new(2.0, 2.0, -10.0) };
        assert!(reduced(vec![wall; (tw * th) as usize]).hides(&behind, &vp));
        // Control: one tile under the box left empty (a hole somewhere in its 4×4 pixels) shows it.
        let centre = |px: f32, n: u32| ((px / DEPTH_TILE as f32) as u32).min(n - 1);
        let (cx, cy) = (centre(size.0 as f32 / 2.0, tw), centre(size.1 as f32 / 2.0, th));
        let mut holed = vec![wall; (tw * th) as usize];
        holed[(cy * tw + cx) as usize] = 1.0;
        assert!(!reduced(holed.clone()).hides(&behind, &vp));
        // A hole in a tile far from the box changes nothing.
        let mut far = vec![wall; (tw * th) as usize];
        far[0] = 1.0;
        assert!(reduced(far).hides(&behind, &vp));
    }
}
