//! Native rendering for tests: the browser's code paths (selection, decode,
//! GPU expansion, draw, AO) fed from a store's scene directory instead of HTTP,
//! rendered on Vulkan (lavapipe in CI) into an Rgba8Unorm texture and read back.

use std::path::Path;
use std::time::Instant;

use voxstream_format::{Block, BlockKey, Manifest, ManifestError};

use crate::camera::OrbitCamera;
use crate::fetch::{BlockSource, FetchError};
use crate::pass_timer::PassTime;
use crate::render::Renderer;
use crate::request::Request;
use crate::scene::Scene;
use crate::stats::Stats;

#[derive(Debug, thiserror::Error)]
pub enum OffscreenError {
    #[error(
        "no GPU adapter found ({0}). Native rendering needs Vulkan: install mesa-vulkan-drivers \
         (lavapipe, a CPU Vulkan driver) or run on a machine with a GPU driver"
    )]
    NoAdapter(String),
    #[error("could not open the GPU device: {0}")]
    Device(String),
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error(transparent)]
    Manifest(#[from] ManifestError),
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}

/// One rendered frame and everything needed to check it.
#[derive(Debug, Clone)]
pub struct OffscreenFrame {
    pub width: u32,
    pub height: u32,
    /// RGBA8, rows top to bottom, `width * 4` bytes each.
    pub pixels: Vec<u8>,
    /// Grid units → clip space, column-major, as `window.voxstream.view().viewProj`.
    pub view_proj: [f32; 16],
    /// Keys of the drawn blocks, sorted.
    pub drawn_blocks: Vec<BlockKey>,
    /// The decoded drawn blocks, in the order of `drawn_blocks`.
    pub blocks: Vec<Block>,
    /// Blocks that failed to fetch or decode, with why.
    pub failures: Vec<(BlockKey, String)>,
    /// The frame counts as complete (what sets the browser's ready marker).
    pub complete: bool,
    pub stats: Stats,
    /// The first draw, from encoding to the GPU finishing it (includes any lazy pipeline work).
    pub first_frame_ms: f64,
    /// The same frame drawn again: the steady-state cost.
    pub frame_ms: f64,
    /// The adapter that rendered it, e.g. "llvmpipe (LLVM 19.1.7, 256 bits) (Vulkan)".
    pub adapter: String,
}

/// A frame with its G-buffer: the shaded image plus, per pixel (rows top to
/// bottom), what the AO was computed for and the visibility it got.
#[derive(Debug, Clone)]
pub struct GBufferFrame {
    pub frame: OffscreenFrame,
    /// xyz: grid-unit position on the drawn voxel face, w: the visibility V.
    pub position_ao: Vec<[f32; 4]>,
    /// xyz: the AO hemisphere's unit normal (f16 precision), w: 1 on a surface, 0 on the background.
    pub normal: Vec<[f32; 4]>,
    /// With temporal accumulation, the frames each pixel's history holds (0 on
    /// the background, 1 where the history was dropped).
    pub history_frames: Option<Vec<f32>>,
    /// Surface pixels whose voxel carries the precomputed AO field (G-buffer position.w ≥ 1.5).
    pub field_pixels: usize,
}

/// A view's frame times (see [`Offscreen::time_frames`]).
#[derive(Debug, Clone)]
pub struct FrameTiming {
    /// Median wall time of a frame, encoding to GPU idle (ms).
    pub cpu_ms: f64,
    /// Median GPU time of each pass (`None` where the device has no timestamps).
    pub gpu_passes: Option<Vec<PassTime>>,
}

/// A native device and queue.
#[derive(Clone)]
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter_info: wgpu::AdapterInfo,
}

impl Gpu {
    /// Opens the default adapter; WGPU_ADAPTER_NAME / WGPU_BACKEND and friends are honoured.
    pub fn new() -> Result<Self, OffscreenError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(wgpu::util::initialize_adapter_from_env_or_default(&instance, None))
            .map_err(|e| OffscreenError::NoAdapter(e.to_string()))?;
        let adapter_info = adapter.get_info();
        // Timestamps, where the adapter has them, time each pass (crate::pass_timer).
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("voxstream offscreen"),
            required_features: adapter.features() & wgpu::Features::TIMESTAMP_QUERY,
            required_limits: wgpu::Limits::default(),
            ..Default::default()
        }))
        .map_err(|e| OffscreenError::Device(e.to_string()))?;
        Ok(Self { device, queue, adapter_info })
    }

    pub fn adapter_name(&self) -> String {
        format!("{} ({:?})", self.adapter_info.name, self.adapter_info.backend)
    }

    /// One device for the whole process, opened on first use. Why: a sweep
    /// renders hundreds of views, and opening a device for each made the
    /// NVIDIA driver refuse one after about 25 in a process ("no GPU adapter
    /// found"). Resources are per [`Offscreen`] and freed with it.
    pub fn shared() -> Result<Self, OffscreenError> {
        static SHARED: std::sync::Mutex<Option<Gpu>> = std::sync::Mutex::new(None);
        let mut shared = SHARED.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(gpu) = shared.as_ref() {
            return Ok(gpu.clone());
        }
        let gpu = Gpu::new()?;
        *shared = Some(gpu.clone());
        Ok(gpu)
    }
}

/// Options for [`Offscreen::open`].
#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    pub width: u32,
    pub height: u32,
    /// `None`: the default camera the browser starts with.
    pub camera: Option<OrbitCamera>,
    pub ao_strength: f32,
}

impl RenderOptions {
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, camera: None, ao_strength: 1.0 }
    }
}

/// A scene loaded for native rendering.
pub struct Offscreen {
    pub renderer: Renderer,
    pub scene: Scene,
    source: BlockSource,
    adapter: String,
    target: wgpu::Texture,
}

impl Offscreen {
    /// Opens the GPU and the scene in `scene_dir` (`<store>/<scene-id>`).
    pub fn open(scene_dir: &Path, options: &RenderOptions) -> Result<Self, OffscreenError> {
        let source = BlockSource::SceneDir(scene_dir.to_path_buf());
        let manifest = Manifest::from_json(&pollster::block_on(source.manifest_bytes())?)?;
        let gpu = Gpu::shared()?;
        let adapter = gpu.adapter_name();
        let (width, height) = (options.width.max(1), options.height.max(1));
        let renderer = Renderer::new(gpu.device, gpu.queue, crate::COLOR_FORMAT, manifest.grid.resolution);
        let mut scene = Scene::new(manifest, (width, height));
        if let Some(camera) = options.camera {
            scene.camera = camera;
        }
        scene.ao_strength = options.ao_strength;
        // An image is asked for at its size: the budget grows to hold its targets
        // (in the browser the drawing buffer shrinks instead, `drawing_size_within`).
        let need = (crate::scene::frame_target_bytes(width, height, 1) as f64
            / crate::scene::FRAME_SHARE_OF_BUDGET) as u64;
        if scene.budget_bytes() < need {
            scene.set_budget_bytes(need);
        }
        let target = renderer.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("offscreen target"),
            size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: crate::COLOR_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        Ok(Self { renderer, scene, source, adapter, target })
    }

    /// Fetches, decodes and expands every block the current view wants (and
    /// their ancestors, as the browser does).
    pub fn load_wanted(&mut self) {
        loop {
            let requests = self.scene.start_requests();
            if requests.is_empty() {
                break;
            }
            self.fetch(&requests);
        }
        self.scene.upload_all(&self.renderer);
    }

    /// Fetches `requests` and hands the results to the scene.
    pub fn fetch(&mut self, requests: &[Request]) {
        let mut blocks = Vec::new();
        for r in requests {
            match r {
                Request::Page(page) => {
                    let range = self.scene.index.page_range(&page.root);
                    let result = pollster::block_on(self.source.page_bytes(page, range.as_ref()));
                    self.scene.insert_page(page, result);
                }
                Request::Block(key) => {
                    let range = self.scene.index.pack_range(key);
                    blocks
                        .push((*key, pollster::block_on(self.source.block_bytes(*key, None, range.as_ref()))))
                }
            }
        }
        self.scene.insert_fetched(blocks);
    }

    /// Loads the hierarchy pages the current view wants (and those they lead
    /// to), no blocks; returns how many were fetched.
    pub fn load_pages(&mut self) -> usize {
        let mut n = 0;
        loop {
            let pages = self.scene.start_page_requests();
            if pages.is_empty() {
                return n;
            }
            n += pages.len();
            self.fetch(&pages);
        }
    }

    /// Fetches, decodes and expands `keys` whatever the view wants.
    pub fn load(&mut self, keys: &[BlockKey]) {
        let results: Vec<_> = keys
            .iter()
            .map(|&k| {
                let range = self.scene.index.pack_range(&k);
                (k, pollster::block_on(self.source.block_bytes(k, None, range.as_ref())))
            })
            .collect();
        self.scene.insert_fetched(results);
        self.scene.upload_all(&self.renderer);
    }

    /// The adapter rendering this scene.
    pub fn adapter_name(&self) -> &str {
        &self.adapter
    }

    /// One streaming frame as the browser runs it: whatever was fetched is
    /// uploaded (within the per-frame cap), the view drawn, and the GPU
    /// waited for (so occlusion feedback is ready for the next frame).
    pub fn draw_frame(&mut self) -> Result<crate::scene::DrawnFrame, OffscreenError> {
        self.draw_frame_at(0.0)
    }

    /// [`Offscreen::draw_frame`] at a given clock (cross-fades and AO rebuilds are timed by it).
    pub fn draw_frame_at(&mut self, now_ms: f64) -> Result<crate::scene::DrawnFrame, OffscreenError> {
        let view = self.target.create_view(&Default::default());
        let frame = self.scene.draw(&mut self.renderer, &view, now_ms);
        wait_idle(&self.renderer.device)?;
        Ok(frame)
    }

    /// The pixels of the last frame drawn (RGBA8, rows top to bottom).
    pub fn read_pixels(&self) -> Result<Vec<u8>, OffscreenError> {
        read_texture(&self.renderer, &self.target)
    }

    /// Loads what the view wants, draws it, reads it back.
    pub fn render(&mut self) -> Result<OffscreenFrame, OffscreenError> {
        self.load_wanted();
        wait_idle(&self.renderer.device)?;
        let view = self.target.create_view(&Default::default());
        let mut times = [0.0; 2];
        let mut frame = None;
        for t in &mut times {
            let start = Instant::now();
            frame = Some(self.scene.draw(&mut self.renderer, &view, 0.0));
            wait_idle(&self.renderer.device)?;
            *t = start.elapsed().as_secs_f64() * 1e3;
        }
        let frame = frame.expect("drawn twice");
        self.scene.stats.frame_ms = times[1];
        let pixels = read_texture(&self.renderer, &self.target)?;
        let blocks = frame.drawn.iter().filter_map(|k| self.scene.block(k).cloned()).collect();
        let mut failures: Vec<(BlockKey, String)> =
            self.scene.failures().map(|(k, e)| (*k, e.clone())).collect();
        failures.sort();
        Ok(OffscreenFrame {
            width: self.target.width(),
            height: self.target.height(),
            pixels,
            view_proj: frame.view_proj.to_cols_array(),
            drawn_blocks: frame.drawn,
            blocks,
            failures,
            complete: frame.complete,
            stats: self.scene.stats.clone(),
            first_frame_ms: times[0],
            frame_ms: times[1],
            adapter: self.adapter.clone(),
        })
    }

    /// Loads what the view wants, draws it, then draws `ao_frames` frames of
    /// the still view from a fresh AO history (jittered frames accumulate when
    /// the settings ask for it) and reads back the last one: the image, the
    /// G-buffer's positions and normals and the final visibilities.
    pub fn render_gbuffer(&mut self, ao_frames: u32) -> Result<GBufferFrame, OffscreenError> {
        let frame = self.render()?;
        self.renderer.ao_passes.reset_history();
        self.draw_frames(ao_frames.max(1))?;
        self.read_gbuffer(frame)
    }

    /// Draws the current view `frames` times (the AO history carries over
    /// from frame to frame and from earlier calls), waiting for each.
    pub fn draw_frames(&mut self, frames: u32) -> Result<(), OffscreenError> {
        let view = self.target.create_view(&Default::default());
        for _ in 0..frames {
            self.scene.draw(&mut self.renderer, &view, 0.0);
            wait_idle(&self.renderer.device)?;
        }
        Ok(())
    }

    /// The last frame drawn with its G-buffer and final visibilities; `frame`
    /// gives the rest (its pixels are replaced by the last frame's).
    pub fn read_gbuffer(&self, mut frame: OffscreenFrame) -> Result<GBufferFrame, OffscreenError> {
        frame.pixels = read_texture(&self.renderer, &self.target)?;
        frame.view_proj = self.scene.view_proj().to_cols_array();
        let crate::ao_passes::LastFrame { position, normal, visibility } = self
            .renderer
            .ao_passes
            .last_frame()
            .ok_or_else(|| OffscreenError::Readback("no frame was drawn".into()))?;
        let positions: Vec<[f32; 4]> = read_texture_bytes(&self.renderer, position, 16)?
            .chunks_exact(16)
            .map(bytemuck::pod_read_unaligned)
            .collect();
        let normal = read_texture_bytes(&self.renderer, normal, 8)?
            .chunks_exact(8)
            .map(|t| std::array::from_fn(|i| f16_to_f32(u16::from_le_bytes([t[2 * i], t[2 * i + 1]]))))
            .collect();
        // V in the first f32 of each texel (and, in the history, the frames in the second).
        let (visibility, history_frames) = match visibility {
            Some((texture, texel)) => {
                let bytes = read_texture_bytes(&self.renderer, texture, texel)?;
                let first = |k: usize| -> Vec<f32> {
                    bytes
                        .chunks_exact(texel as usize)
                        .map(|t| f32::from_le_bytes(t[4 * k..4 * k + 4].try_into().expect("4")))
                        .collect()
                };
                (first(0), (texel == 16).then(|| first(1)))
            }
            None => (vec![1.0; positions.len()], None),
        };
        let field_pixels = positions.iter().filter(|p| p[3] >= 1.5).count();
        let position_ao = positions.iter().zip(&visibility).map(|(p, v)| [p[0], p[1], p[2], *v]).collect();
        Ok(GBufferFrame { position_ao, normal, history_frames, frame, field_pixels })
    }

    /// `runs` frames of the loaded view at `ao_strength` (0: no AO), each timed
    /// from encoding until the GPU is idle, and by the GPU per pass where the
    /// device has timestamps: medians of each.
    pub fn time_frames(&mut self, ao_strength: f32, runs: usize) -> Result<FrameTiming, OffscreenError> {
        self.load_wanted();
        let saved = self.scene.ao_strength;
        self.scene.ao_strength = ao_strength;
        let view = self.target.create_view(&Default::default());
        let mut times = Vec::new();
        let mut passes = Vec::new();
        // One untimed frame first: it rebuilds the occupancy volume when AO was off.
        for i in 0..=runs.max(1) {
            let start = Instant::now();
            self.scene.draw(&mut self.renderer, &view, 0.0);
            wait_idle(&self.renderer.device)?;
            if i > 0 {
                times.push(start.elapsed().as_secs_f64() * 1e3);
                if let Some(frame) = self.last_pass_times()? {
                    passes.push(frame);
                }
            }
        }
        self.scene.ao_strength = saved;
        times.sort_by(f64::total_cmp);
        Ok(FrameTiming {
            cpu_ms: times[times.len() / 2],
            gpu_passes: (!passes.is_empty()).then(|| crate::pass_timer::median_by_label(&passes)),
        })
    }

    /// The passes of the last frame drawn, timed by the GPU (`None` without timestamps).
    pub fn last_pass_times(&self) -> Result<Option<Vec<PassTime>>, OffscreenError> {
        self.renderer.pass_timer.as_ref().map(|t| t.read(&self.renderer.device)).transpose()
    }

    /// The indirect draw args the compute pass wrote for a cached block:
    /// (vertex_count, instance_count, first_vertex, first_instance).
    pub fn draw_args(&self, key: &BlockKey) -> Result<Option<[u32; 4]>, OffscreenError> {
        let Some((gpu, chunk)) = self.arena_block(key) else { return Ok(None) };
        let bytes = read_buffer(&self.renderer, &chunk.args)?;
        let at = gpu.slot.args_offset() as usize;
        Ok(Some(bytemuck::pod_read_unaligned(&bytes[at..at + 16])))
    }

    /// The face records the compute pass wrote for a cached block, as
    /// (x | y << 6 | z << 12 | face << 18, normal, colour) records in GPU order.
    pub fn face_records(&self, key: &BlockKey) -> Result<Vec<[u32; 3]>, OffscreenError> {
        let Some((gpu, chunk)) = self.arena_block(key) else { return Ok(Vec::new()) };
        let bytes = read_buffer(&self.renderer, &chunk.faces)?;
        let record = crate::expand::FACE_RECORD_BYTES as usize;
        // The block's run of pages is longer than its faces: only its own records count.
        Ok(bytes[gpu.slot.first_face() as usize * record..]
            .chunks_exact(record)
            .take(gpu.faces as usize)
            .map(bytemuck::pod_read_unaligned)
            .collect())
    }

    /// The page-table entries of a cached block's run of pages.
    pub fn page_infos(&self, key: &BlockKey) -> Result<Vec<crate::expand::PageInfo>, OffscreenError> {
        let Some((gpu, chunk)) = self.arena_block(key) else { return Ok(Vec::new()) };
        let bytes = read_buffer(&self.renderer, &chunk.page_table)?;
        let entry = crate::face_arena::PAGE_INFO_BYTES as usize;
        Ok(bytes[gpu.slot.first_page as usize * entry..]
            .chunks_exact(entry)
            .take(gpu.slot.pages as usize)
            .map(bytemuck::pod_read_unaligned)
            .collect())
    }

    fn arena_block(
        &self,
        key: &BlockKey,
    ) -> Option<(&crate::expand::GpuBlock, &crate::face_arena::FaceChunk)> {
        let gpu = self.scene.gpu_block(key)?;
        Some((gpu, self.scene.face_arena().chunk(gpu.slot.chunk)?))
    }
}

/// Renders the scene in `scene_dir` (`<store>/<scene-id>`) with the default
/// camera at `width`×`height`, exactly as the browser would draw it once every
/// selected block is loaded.
pub fn render_scene(scene_dir: &Path, width: u32, height: u32) -> Result<OffscreenFrame, OffscreenError> {
    Offscreen::open(scene_dir, &RenderOptions::new(width, height))?.render()
}

/// IEEE half → f32 (the G-buffer's normal target).
fn f16_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f32;
    match exp {
        0 => sign * frac * 2f32.powi(-24),
        31 if frac == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        _ => sign * (1.0 + frac / 1024.0) * 2f32.powi(exp - 15),
    }
}

fn wait_idle(device: &wgpu::Device) -> Result<(), OffscreenError> {
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map(|_| ())
        .map_err(|e| OffscreenError::Readback(e.to_string()))
}

fn map_and_read(renderer: &Renderer, staging: &wgpu::Buffer) -> Result<Vec<u8>, OffscreenError> {
    map_and_read_on(&renderer.device, staging)
}

/// Maps a whole MAP_READ buffer once the GPU is idle and copies it out.
pub(crate) fn map_and_read_on(
    device: &wgpu::Device,
    staging: &wgpu::Buffer,
) -> Result<Vec<u8>, OffscreenError> {
    let (tx, rx) = std::sync::mpsc::channel();
    staging.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    wait_idle(device)?;
    rx.recv()
        .map_err(|e| OffscreenError::Readback(e.to_string()))?
        .map_err(|e| OffscreenError::Readback(e.to_string()))?;
    let bytes =
        staging.get_mapped_range(..).map_err(|e| OffscreenError::Readback(format!("{e:?}")))?.to_vec();
    staging.unmap();
    Ok(bytes)
}

/// Copies a whole buffer (COPY_SRC) back to the CPU.
pub fn read_buffer(renderer: &Renderer, buffer: &wgpu::Buffer) -> Result<Vec<u8>, OffscreenError> {
    read_buffer_on(&renderer.device, &renderer.queue, buffer)
}

/// [`read_buffer`] on any device and queue.
pub fn read_buffer_on(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    buffer: &wgpu::Buffer,
) -> Result<Vec<u8>, OffscreenError> {
    let staging = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: buffer.size(),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&Default::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, buffer.size());
    queue.submit([encoder.finish()]);
    map_and_read_on(device, &staging)
}

/// The clipmap's cells as the GPU holds them: per level, cells³ × [`crate::clipmap::CELL_WORDS`] u32 in storage (toroidal) order.
pub fn read_clipmap_cells(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    clipmap: &crate::clipmap::OccupancyClipmap,
) -> Result<Vec<Vec<u32>>, OffscreenError> {
    let Some(layout) = clipmap.layout() else { return Ok(Vec::new()) };
    let bytes = read_buffer_on(device, queue, &clipmap.cells_buffer)?;
    let words: Vec<u32> =
        bytes.chunks_exact(4).map(|b| u32::from_le_bytes(b.try_into().expect("4"))).collect();
    let n = layout.level_words() as usize;
    Ok((0..layout.levels as usize).map(|k| words[k * n..(k + 1) * n].to_vec()).collect())
}

/// The clipmap's texels as the GPU holds them: per level of the layout, its
/// block of (cells + 1)³ texels (x: opacity along x, y, z, w: their bound),
/// x fastest; texel i of the block holds the cell in slot i mod cells.
pub fn read_clipmap_texels(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    clipmap: &crate::clipmap::OccupancyClipmap,
) -> Result<Vec<Vec<[f32; 4]>>, OffscreenError> {
    let Some(layout) = clipmap.layout() else { return Ok(Vec::new()) };
    let texture = clipmap.texels();
    let (edge, depth) = (texture.width(), texture.depth_or_array_layers());
    let row = edge * crate::clipmap::TEXEL_BYTES as u32;
    let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let staging = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("clipmap texels readback"),
        size: padded as u64 * edge as u64 * depth as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &staging,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(edge),
            },
        },
        wgpu::Extent3d { width: edge, height: edge, depth_or_array_layers: depth },
    );
    queue.submit([encoder.finish()]);
    let bytes = map_and_read_on(device, &staging)?;
    let texels: Vec<[f32; 4]> = bytes
        .chunks_exact(padded as usize)
        .flat_map(|r| r[..row as usize].chunks_exact(4))
        .map(|t| std::array::from_fn(|c| t[c] as f32 / 255.0))
        .collect();
    let block = (layout.cells as usize + 1).pow(3);
    Ok(texels.chunks_exact(block).take(layout.levels as usize).map(<[_]>::to_vec).collect())
}

/// Copies an Rgba8 texture back, dropping the row padding wgpu requires.
fn read_texture(renderer: &Renderer, texture: &wgpu::Texture) -> Result<Vec<u8>, OffscreenError> {
    read_texture_bytes(renderer, texture, 4)
}

/// Copies a texture of `texel_bytes` per texel back, rows top to bottom, unpadded.
fn read_texture_bytes(
    renderer: &Renderer,
    texture: &wgpu::Texture,
    texel_bytes: u32,
) -> Result<Vec<u8>, OffscreenError> {
    let (width, height) = (texture.width(), texture.height());
    let row = width * texel_bytes;
    let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let staging = renderer.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("frame readback"),
        size: padded as u64 * height as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = renderer.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &staging,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(height),
            },
        },
        wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
    );
    renderer.queue.submit([encoder.finish()]);
    let bytes = map_and_read(renderer, &staging)?;
    Ok(bytes.chunks_exact(padded as usize).flat_map(|r| &r[..row as usize]).copied().collect())
}

#[cfg(test)]
mod tests {
    #[test]
    fn half_floats_decode() {
        use super::f16_to_f32;
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xbc00), -1.0);
        assert_eq!(f16_to_f32(0x3800), 0.5);
        assert_eq!(f16_to_f32(0x0000), 0.0);
        assert_eq!(f16_to_f32(0x3555), 0.333_251_95);
        assert!(f16_to_f32(0x7e00).is_nan());
    }
}
