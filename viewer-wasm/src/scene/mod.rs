//! The thin driver both the browser loop and the native offscreen loop call,
//! one frame at a time, through the viewer's stages, a file each:
//!
//! - [`plan`], traverse ([`crate::traverse`]: what the view wants, within the budget) →
//!   request ([`crate::request`]: what to fetch next, what to abort);
//! - [`intake`], decode ([`crate::decode`], fed by the caller: pages into the index,
//!   blocks into the decoded cache);
//! - [`upload`], upload (one staging write per frame, capped, [`crate::expand::UploadBatch`])
//!   → expand (compute), into the face arena ([`crate::face_arena`]) under the hard byte
//!   budget ([`crate::residency`]);
//! - this file: draw ([`Scene::draw`], [`crate::render`]), the order of a frame;
//! - [`feedback`], what was visible (occlusion), which steers the next traversal;
//! - [`ao_sources`], the AO structure's sources, beside draw.
//!
//! It never fetches by itself; the caller feeds it fetched bytes, so the same
//! code runs under the browser's event loop and a blocking native loop.

mod ao_sources;
mod feedback;
mod intake;
mod plan;
mod upload;

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use glam::{Mat4, Vec3};
use voxstream_format::{Block, BlockKey, Manifest, SceneIndex};

use crate::camera::OrbitCamera;
use crate::crossfade::{Crossfade, Fade};
use crate::expand::{GpuBlock, UPLOAD_BYTES_PER_FRAME, UploadBatch, UploadPacer};
use crate::occlusion::{Occlusion, OccupiedCells, occlusion_gpu_bytes};
use crate::render::{FrameParams, Renderer};
use crate::request::{DEFAULT_MAX_IN_FLIGHT, NeededBlocks, RequestQueue};
use crate::residency::{DEFAULT_BUDGET_BYTES, Residency};
use crate::select::{SelectParams, resolve_draw_set_in, scene_bounds};
use crate::stats::Stats;
use crate::traverse::Traversal;

/// Most of the GPU budget the frame's own targets may take; the rest holds blocks.
pub const FRAME_SHARE_OF_BUDGET: f64 = 0.5;

/// GPU bytes a `width`×`height` frame's own targets take: colour and depth,
/// the G-buffer and AO targets (AO traced at 1/`ao_downscale` resolution), the
/// occlusion readbacks.
pub fn frame_target_bytes(width: u32, height: u32, ao_downscale: u32) -> u64 {
    width as u64 * height as u64 * 4 * 2
        + crate::ao_passes::target_bytes(width, height, ao_downscale)
        + occlusion_gpu_bytes(width, height)
}

/// The drawing-buffer size for a canvas of `size` device pixels under a GPU
/// byte budget: `size` itself while its targets take at most
/// [`FRAME_SHARE_OF_BUDGET`] of the budget, else scaled down, aspect kept,
/// until they do. Why: at 3840×2160 (a 4K display, or 1920×1080 CSS pixels at
/// device-pixel ratio 2) the targets alone take about 1 GB, and the default
/// 512 MiB budget would hold no block at all: nothing would be drawn.
pub fn drawing_size_within(size: (u32, u32), budget: u64) -> (u32, u32) {
    let limit = (budget as f64 * FRAME_SHARE_OF_BUDGET) as u64;
    let (w, h) = (size.0.max(1), size.1.max(1));
    // Traced at full resolution: the most the targets take.
    let full = frame_target_bytes(w, h, 1);
    if full <= limit {
        return (w, h);
    }
    let mut scale = (limit as f64 / full as f64).sqrt();
    loop {
        let fit = (((w as f64 * scale) as u32).max(1), ((h as f64 * scale) as u32).max(1));
        if fit == (1, 1) || frame_target_bytes(fit.0, fit.1, 1) <= limit {
            return fit;
        }
        scale *= 0.99;
    }
}

/// A view given by matrices instead of the orbit camera (native `voxstream
/// render` with a camera.json); when set it replaces `Scene::camera`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixedView {
    /// Grid units → clip space (wgpu depth 0..1).
    pub view_proj: Mat4,
    /// Eye in grid units.
    pub eye: Vec3,
    /// Pixels per grid unit at distance 1 for this viewport.
    pub focal_pixels: f32,
}

/// What a call to [`Scene::draw`] drew.
#[derive(Debug, Clone, PartialEq)]
pub struct DrawnFrame {
    pub view_proj: Mat4,
    pub drawn: Vec<BlockKey>,
    /// Every needed block and page is settled (loaded, or failed for good and
    /// drawn as its ancestor): nothing more will change this view.
    pub complete: bool,
}

/// The state the traversal was computed for.
type TraversedFor = (OrbitCamera, (u32, u32), usize, SelectParams, u64, usize, u64, Option<FixedView>);

/// A decoded block kept on the CPU: its voxels, the faces they expand to, its
/// occlusion proxies, and the frame it was last needed (the least recently
/// needed go first).
struct CachedBlock {
    block: Block,
    faces: u32,
    cells: OccupiedCells,
    needed_frame: u64,
}

pub struct Scene {
    pub manifest: Manifest,
    /// The hierarchy as far as its pages have loaded.
    pub index: SceneIndex,
    pub camera: OrbitCamera,
    /// Overrides `camera` when set.
    pub fixed_view: Option<FixedView>,
    pub select_params: SelectParams,
    /// 0 disables ambient occlusion; 1 is full strength.
    pub ao_strength: f32,
    /// Occlusion culling from GPU feedback (on by default).
    pub occlusion_culling: bool,
    pub stats: Stats,
    viewport: (u32, u32),
    traversed_for: Option<TraversedFor>,
    traversal: Traversal,
    requests: RequestQueue,
    /// What the traversal needs loaded ([`Scene::needed`]).
    needed: NeededBlocks,
    failed_pages: HashMap<BlockKey, String>,
    residency: Residency,
    /// Blocks on the GPU.
    gpu: HashMap<BlockKey, GpuBlock>,
    /// Decoded blocks without faces: ready, nothing to put on the GPU.
    empty: HashSet<BlockKey>,
    /// Decoded blocks on the CPU.
    decoded: HashMap<BlockKey, CachedBlock>,
    decoded_bytes: u64,
    failed: HashMap<BlockKey, String>,
    upload: Option<wgpu::Buffer>,
    /// The frame's upload batch, kept so its buffer is allocated once.
    batch: UploadBatch,
    pacer: Option<UploadPacer>,
    occlusion: Option<Occlusion>,
    /// Bumped whenever `hidden` changes (the traversal depends on it).
    hidden_generation: u64,
    feedback_changed_frame: u64,
    /// Blocks the newest feedback found hidden.
    hidden: HashSet<BlockKey>,
    drawn: Vec<BlockKey>,
    occupancy_for: Option<Vec<BlockKey>>,
    occupancy_built_ms: f64,
    frame_counter: u64,
    picked: Option<Option<Vec3>>,
    /// Set where a worker builds the occupancy volume (the browser); native builds inline.
    pub occupancy_offload: bool,
    /// Level changes fade over `crossfade.duration_ms` (0: they pop, as native renders want).
    pub crossfade: Crossfade,
    /// A payload waiting to be sent to the worker, and whether an answer is outstanding.
    occupancy_job: Option<Vec<u8>>,
    occupancy_job_in_flight: bool,
    /// Milliseconds from any fixed origin: splits WebGPU calls off the main
    /// thread's tasks in the stats (the page sets `performance.now`).
    pub clock: fn() -> f64,
}

/// A clock that never moves: natively nobody reads the main-thread split.
fn no_clock() -> f64 {
    0.0
}

impl Scene {
    /// A scene framed by the default camera for a `viewport`-sized view.
    pub fn new(manifest: Manifest, viewport: (u32, u32)) -> Self {
        let camera = default_camera(&manifest, viewport.0.max(1) as f32 / viewport.1.max(1) as f32);
        Self {
            index: SceneIndex::new(&manifest),
            manifest,
            camera,
            fixed_view: None,
            select_params: SelectParams::default(),
            ao_strength: 1.0,
            occlusion_culling: true,
            stats: Stats { budget_bytes: DEFAULT_BUDGET_BYTES, ..Default::default() },
            viewport: (viewport.0.max(1), viewport.1.max(1)),
            traversed_for: None,
            traversal: Traversal::default(),
            requests: RequestQueue::new(DEFAULT_MAX_IN_FLIGHT),
            needed: NeededBlocks::default(),
            failed_pages: HashMap::default(),
            residency: Residency::new(DEFAULT_BUDGET_BYTES),
            gpu: HashMap::default(),
            empty: HashSet::default(),
            decoded: HashMap::default(),
            decoded_bytes: 0,
            failed: HashMap::default(),
            upload: None,
            batch: UploadBatch::new(),
            pacer: None,
            occlusion: None,
            hidden_generation: 0,
            feedback_changed_frame: 0,
            hidden: HashSet::default(),
            drawn: Vec::new(),
            occupancy_for: None,
            occupancy_built_ms: f64::NEG_INFINITY,
            frame_counter: 0,
            picked: None,
            occupancy_offload: false,
            crossfade: Crossfade::default(),
            occupancy_job: None,
            occupancy_job_in_flight: false,
            clock: no_clock,
        }
    }

    pub fn viewport(&self) -> (u32, u32) {
        self.viewport
    }

    /// Sets the drawing size (the caller keeps it within the budget: [`drawing_size_within`]).
    pub fn set_viewport(&mut self, width: u32, height: u32) {
        self.viewport = (width.max(1), height.max(1));
    }

    pub fn aspect(&self) -> f32 {
        self.viewport.0 as f32 / self.viewport.1 as f32
    }

    pub fn view_proj(&self) -> Mat4 {
        match &self.fixed_view {
            Some(v) => v.view_proj,
            None => self.camera.view_proj(self.aspect()),
        }
    }

    /// The eye in grid units (of the fixed view when set).
    pub fn eye(&self) -> Vec3 {
        self.fixed_view.map_or_else(|| self.camera.eye(), |v| v.eye)
    }

    /// The hard GPU byte budget for everything the viewer holds.
    pub fn budget_bytes(&self) -> u64 {
        self.residency.budget()
    }

    pub fn set_budget_bytes(&mut self, bytes: u64) {
        self.residency.set_budget(bytes);
        self.stats.budget_bytes = bytes;
    }

    /// The GPU memory bookkeeping.
    pub fn residency(&self) -> &Residency {
        &self.residency
    }

    /// The last traversal.
    pub fn traversal(&mut self) -> &Traversal {
        self.update_traversal();
        &self.traversal
    }

    /// Most requests in flight at once.
    pub fn set_max_in_flight(&mut self, n: usize) {
        self.requests.max_in_flight = n.max(1);
    }

    fn is_ready(&self, key: &BlockKey) -> bool {
        self.gpu.contains_key(key) || self.empty.contains(key)
    }

    /// Whether another frame would change something without new input:
    /// blocks wait for the per-frame upload cap, or the feedback changed
    /// lately (the next frames' queries settle it).
    pub fn needs_another_frame(&mut self) -> bool {
        self.has_pending_uploads()
            || self.frame_counter <= self.feedback_changed_frame + 2
            || self.occlusion.as_ref().is_some_and(Occlusion::pick_pending)
            || self.crossfade.is_active()
    }

    /// Every needed block and page is settled (on the GPU, empty or failed for
    /// good), nothing waits for the GPU and nothing is in flight.
    pub fn is_settled(&mut self) -> bool {
        self.update_traversal();
        self.requests.in_flight() == 0
            && self.needed().keys().all(|k| self.is_ready(k) || self.failed.contains_key(k))
            && self.traversal.pages.iter().all(|p| self.failed_pages.contains_key(&p.root))
    }

    pub fn is_cached(&self, key: &BlockKey) -> bool {
        self.is_ready(key)
    }

    /// The decoded block, if kept.
    pub fn block(&self, key: &BlockKey) -> Option<&Block> {
        self.decoded.get(key).map(|c| &c.block)
    }

    pub fn gpu_block(&self, key: &BlockKey) -> Option<&GpuBlock> {
        self.gpu.get(key)
    }

    /// Where the resident blocks' faces live.
    pub fn face_arena(&self) -> &crate::face_arena::FaceArena {
        self.residency.arena()
    }

    /// Keys drawn by the last [`Scene::draw`].
    pub fn drawn(&self) -> &[BlockKey] {
        &self.drawn
    }

    /// Uploads this frame's share, draws the current view into `target` and
    /// submits it. `now_ms` paces occupancy rebuilds while streaming.
    pub fn draw(&mut self, renderer: &mut Renderer, target: &wgpu::TextureView, now_ms: f64) -> DrawnFrame {
        self.frame_counter += 1;
        self.stats.frames_drawn = self.frame_counter;
        if let Some(timer) = &renderer.pass_timer {
            // The upload's expansion and the clipmap's update, recorded
            // before the frame's passes, are timed with it.
            timer.begin_frame(self.frame_counter);
        }
        let mut step = (self.clock)();
        self.take_feedback();
        self.stats.note_phase("feedback", &mut step, (self.clock)());
        // One command buffer and one submit a frame: the upload's expansion,
        // the clipmap's splats and the frame's passes. In a browser each
        // encoder and submit is a call across to the GPU process, and a
        // streaming frame made three.
        let mut encoder =
            renderer.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        let cap = self.pacer.as_ref().map_or(UPLOAD_BYTES_PER_FRAME, UploadPacer::cap_bytes);
        self.upload_into(renderer, &mut encoder, cap);
        self.stats.note_phase("upload", &mut step, (self.clock)());
        let settled = self.is_settled();
        let max_level = self.manifest.coarsest_level();
        let drawn =
            resolve_draw_set_in(self.select_params.refinement, &self.drawable_wanted(), max_level, |k| {
                self.is_ready(k)
            });
        self.stats.note_phase("draw set", &mut step, (self.clock)());

        self.update_occupancy(renderer, &mut encoder, &drawn, settled, now_ms);
        self.stats.note_phase("AO occupancy", &mut step, (self.clock)());

        let gpu = &self.gpu;
        let draw_list = self.crossfade.update(&drawn, max_level, now_ms, |k| gpu.contains_key(k));
        for (key, _) in &draw_list {
            self.residency.mark_visible(key, self.frame_counter);
        }
        let mut faces = 0u64;
        for key in &drawn {
            if let Some(g) = self.gpu.get(key) {
                faces += g.faces as u64;
            }
        }
        for key in self.traversal.priority.keys() {
            if let Some(entry) = self.decoded.get_mut(key) {
                entry.needed_frame = self.frame_counter;
            }
        }
        let gpu_blocks: Vec<(&GpuBlock, Option<Fade>)> =
            draw_list.iter().filter_map(|(k, fade)| Some((self.gpu.get(k)?, *fade))).collect();
        let params = FrameParams {
            view_proj: self.view_proj(),
            eye: self.eye(),
            grid_resolution: self.manifest.grid.resolution as f32,
            ao_strength: self.ao_strength,
        };
        self.stats.note_phase("draw list", &mut step, (self.clock)());
        let tests = if self.occlusion_culling { self.occlusion_tests() } else { Vec::new() };
        self.stats.note_phase("occlusion tests", &mut step, (self.clock)());
        let webgpu_from = (self.clock)();
        renderer.encode_frame(
            &mut encoder,
            target,
            self.viewport,
            &params,
            self.residency.arena(),
            &gpu_blocks,
        );
        let occlusion = self.occlusion.get_or_insert_with(Occlusion::default);
        occlusion.prepare(&renderer.device, self.viewport, params.view_proj, tests, self.frame_counter);
        if let Some(depth) = renderer.depth_texture() {
            occlusion.encode_copy(&renderer.device, &mut encoder, depth, renderer.pass_timer.as_ref());
        }
        if let Some(timer) = &renderer.pass_timer {
            timer.resolve(&mut encoder);
        }
        renderer.queue.submit([encoder.finish()]);
        occlusion.after_submit();
        if let Some(timer) = &renderer.pass_timer {
            timer.after_submit();
        }
        self.stats.note_webgpu((self.clock)() - webgpu_from);

        self.stats.blocks_drawn = drawn.len() as u32;
        self.stats.faces_drawn = faces;
        self.drawn = drawn.clone();
        self.stats.note_phase("encode", &mut step, (self.clock)());
        self.enforce_budget();
        self.trim_decoded();
        self.note_residency();
        self.stats.note_phase("budget", &mut step, (self.clock)());
        // The picture is complete once the AO volume the worker builds is in it too.
        DrawnFrame {
            view_proj: params.view_proj,
            drawn,
            complete: settled && !self.occupancy_job_in_flight && !self.crossfade.is_active(),
        }
    }
}

/// The default view: the scene's voxels framed from the front, slightly
/// above, filling a view of `aspect` (width / height).
pub fn default_camera(manifest: &Manifest, aspect: f32) -> OrbitCamera {
    let (min, max) = match scene_bounds(manifest) {
        Some(b) => (b.min, b.max),
        None => (Vec3::ZERO, Vec3::splat(manifest.grid.resolution as f32)),
    };
    let mut camera = OrbitCamera::framing(min, max);
    camera.fit_box(min, max, aspect);
    camera
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_drawing_buffer_shrinks_until_its_targets_fit_half_the_budget() {
        let budget = DEFAULT_BUDGET_BYTES;
        let half = (budget as f64 * FRAME_SHARE_OF_BUDGET) as u64;
        // 1920×1080 fits the default budget as it is.
        assert_eq!(drawing_size_within((1920, 1080), budget), (1920, 1080));
        // 3840×2160 does not (its targets alone are over the whole budget):
        // scaled down, aspect kept, within half the budget but not far below it.
        assert!(frame_target_bytes(3840, 2160, 1) > budget);
        let (w, h) = drawing_size_within((3840, 2160), budget);
        assert!(frame_target_bytes(w, h, 1) <= half, "{w}x{h}: {} > {half}", frame_target_bytes(w, h, 1));
        assert!(frame_target_bytes(w, h, 1) as f64 >= 0.95 * half as f64, "{w}x{h} is needlessly small");
        assert!(((w as f64 / h as f64) - 16.0 / 9.0).abs() < 0.01, "{w}x{h}");
        // A budget that grows lets the full size back in (the control).
        assert_eq!(drawing_size_within((3840, 2160), 4 * budget), (3840, 2160));
        // Nothing fits a budget of a byte: one pixel, never zero.
        assert_eq!(drawing_size_within((3840, 2160), 1), (1, 1));
        assert_eq!(drawing_size_within((0, 0), budget), (1, 1));
    }
}
