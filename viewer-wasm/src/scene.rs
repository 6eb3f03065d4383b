//! The thin driver both the browser loop and the native offscreen loop call,
//! one frame at a time, through the viewer's stages:
//!
//! traverse ([`crate::traverse`]: what the view wants, within the budget) →
//! request ([`crate::request`]: what to fetch next, what to abort) →
//! decode ([`crate::decode`], fed by the caller) → upload (one staging write
//! per frame, capped, [`crate::expand::UploadBatch`]) → expand (compute) →
//! draw ([`crate::render`]) → feedback (what was visible).
//! GPU memory goes through [`crate::residency`] under a hard byte budget.
//! It never fetches by itself; the caller feeds it fetched bytes, so the same
//! code runs under the browser's event loop and a blocking native loop.

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use glam::{Mat4, Vec3};
use voxstream_format::{Block, BlockKey, HierarchyPage, Manifest, PageRef, SceneIndex};

use crate::ao::{AoStructure, OccupancyVolume, encode_sources};
use crate::camera::OrbitCamera;
use crate::clipmap::{CLIP_CELLS, ClipmapLayout, view_forward};
use crate::crossfade::{Crossfade, Fade};
use crate::decode::{DecodedBlock, decode_fetched};
use crate::expand::{GpuBlock, UPLOAD_BYTES_PER_FRAME, UploadBatch, UploadPacer, upload_buffer};
use crate::fetch::FetchError;
use crate::occlusion::{Occlusion, OccupiedCells, contains_eye, occlusion_gpu_bytes, proxy_bounds};
use crate::render::{FADE_BUFFER_BYTES, FrameParams, Renderer};
use crate::request::{DEFAULT_MAX_IN_FLIGHT, Request, RequestQueue};
use crate::residency::{DEFAULT_BUDGET_BYTES, Residency, block_gpu_bytes};
use crate::select::{SelectParams, ViewParams, block_bounds, resolve_draw_set_in, scene_bounds};
use crate::stats::Stats;
use crate::traverse::{Traversal, TraverseParams, traverse};

/// While streaming, rebuild the occupancy volume at most this often.
const OCCUPANCY_REBUILD_MS: f64 = 400.0;
/// Share of the block budget the needed set (wanted blocks and their
/// ancestors, counted with the pools' rounding) may take; the rest leaves
/// room for the free list and the last frame's blocks while the view changes.
const WANTED_SHARE_OF_BUDGET: f64 = 0.8;
/// Decoded blocks kept on the CPU (voxel bytes), so a block evicted from the
/// GPU comes back without a refetch.
const DECODED_CACHE_BYTES: u64 = 256 << 20;

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

    /// GPU bytes of the frame's own targets: colour and depth at the viewport
    /// size, the G-buffer and AO targets, the occupancy volume with its mips,
    /// the clipmap (cells and source voxels), uniforms, the upload buffer.
    fn fixed_gpu_bytes(&self, occupancy_cells: u32, ao_downscale: u32, clipmap_bytes: u64) -> u64 {
        let occupancy: u64 =
            (0..=occupancy_cells.max(1).ilog2()).map(|m| ((occupancy_cells >> m) as u64).pow(3)).sum();
        frame_target_bytes(self.viewport.0, self.viewport.1, ao_downscale)
            + occupancy
            + clipmap_bytes
            + 512
            + UPLOAD_BYTES_PER_FRAME
            + FADE_BUFFER_BYTES
    }

    fn traverse_params(&self) -> TraverseParams {
        TraverseParams {
            max_error_pixels: self.select_params.max_error_pixels,
            max_blocks: self.select_params.max_blocks,
            max_bytes: (self.residency.block_budget() as f64 * WANTED_SHARE_OF_BUDGET) as u64,
            ..Default::default()
        }
    }

    /// Runs the traversal when the camera, viewport, loaded pages, parameters
    /// or budget changed, and replans the requests.
    fn update_traversal(&mut self) {
        let now = (
            self.camera,
            self.viewport,
            self.index.pages_loaded(),
            self.select_params,
            // The block budget, not the budget: the fixed targets are counted after the first
            // traversal, whose byte cap must then shrink.
            self.residency.block_budget(),
            self.failed_pages.len(),
            self.hidden_generation,
            self.fixed_view,
        );
        if self.traversed_for.as_ref() == Some(&now) {
            return;
        }
        let view = ViewParams {
            view_proj: self.view_proj(),
            eye: self.eye(),
            focal_pixels: self
                .fixed_view
                .map_or_else(|| self.camera.focal_pixels(self.viewport.1 as f32), |v| v.focal_pixels),
        };
        let started = (self.clock)();
        let no_feedback = HashSet::default();
        let occluded = if self.occlusion_culling { &self.hidden } else { &no_feedback };
        self.traversal =
            traverse(&self.index, &self.manifest.root.key, &view, &self.traverse_params(), occluded);
        self.stats.culled_frustum = self.traversal.culled_frustum;
        self.stats.culled_occlusion = self.traversal.culled_occlusion;
        self.traversed_for = Some(now);
        self.plan_requests();
        self.stats.longest_traversal_ms = self.stats.longest_traversal_ms.max((self.clock)() - started);
    }

    fn plan_requests(&mut self) {
        let pages: Vec<PageRef> = self
            .traversal
            .pages
            .iter()
            .filter(|p| !self.failed_pages.contains_key(&p.root))
            .cloned()
            .collect();
        let (decoded, failed, empty) = (&self.decoded, &self.failed, &self.empty);
        let present = |k: &BlockKey| decoded.contains_key(k) || failed.contains_key(k) || empty.contains(k);
        let needed = self.needed();
        let failed_pages = &self.failed_pages;
        self.requests.plan(&pages, &needed, |k| failed_pages.contains_key(k), present);
    }

    /// What must be loaded, with its projected error: the wanted blocks but
    /// the hidden ones, and all their ancestors (stand-ins while they load).
    fn needed(&self) -> HashMap<BlockKey, f32> {
        let hidden: HashSet<&BlockKey> = self.traversal.hidden.iter().collect();
        let max_level = self.manifest.coarsest_level();
        let mut needed = HashMap::default();
        for key in self.traversal.blocks.iter().filter(|k| !hidden.contains(k)) {
            let mut k = *key;
            loop {
                if needed.contains_key(&k) {
                    break;
                }
                if self.index.block(&k).is_some() {
                    needed.insert(k, self.traversal.priority.get(&k).copied().unwrap_or(f32::INFINITY));
                }
                if k.level >= max_level {
                    break;
                }
                k = k.parent();
            }
        }
        needed
    }

    /// The blocks to resolve the draw set from: the wanted ones, a hidden
    /// block only if it is loaded (it is invisible; its ancestor must not
    /// stand in for it and cover its visible siblings).
    fn drawable_wanted(&self) -> Vec<BlockKey> {
        let hidden: HashSet<&BlockKey> = self.traversal.hidden.iter().collect();
        self.traversal.blocks.iter().filter(|k| !hidden.contains(k) || self.is_ready(k)).copied().collect()
    }

    /// The blocks this view wants (sorted by key).
    pub fn wanted(&mut self) -> &[BlockKey] {
        self.update_traversal();
        &self.traversal.blocks
    }

    /// The next requests to start (pages first, then blocks by projected
    /// error), within the in-flight cap; they are marked in flight.
    pub fn start_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let started = self.requests.start();
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        started
    }

    /// Like [`Scene::start_requests`], hierarchy pages only.
    pub fn start_page_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let started = self.requests.start_where(|r| matches!(r, Request::Page(_)));
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        started
    }

    /// In-flight requests this view no longer needs: abort them.
    pub fn take_stale_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let stale = self.requests.take_stale();
        self.stats.requests_aborted += stale.len() as u32;
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        stale
    }

    /// Takes a fetched page. A page that fails is not asked for again; the
    /// blocks above it stay drawn as they are.
    pub fn insert_page(&mut self, page: &PageRef, result: Result<Vec<u8>, FetchError>) {
        self.requests.finished(&Request::Page(page.clone()));
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        // An answer for a page loaded meanwhile (or aborted and answered anyway).
        if !self.index.missing_pages().any(|p| p.root == page.root) {
            return;
        }
        let outcome = result.map_err(|e| e.to_string()).and_then(|bytes| {
            self.stats.bytes_fetched += bytes.len() as u64;
            let decoded = HierarchyPage::decode(&bytes, page).map_err(|e| e.to_string())?;
            self.index.insert_page(decoded).map_err(|e| e.to_string())
        });
        match outcome {
            Ok(()) => self.stats.pages_loaded += 1,
            Err(e) => {
                self.stats.record_error(format!("hierarchy page {}: {e}", page.root));
                self.failed_pages.insert(page.root, e);
            }
        }
        self.plan_requests();
    }

    pub fn in_flight(&self) -> usize {
        self.requests.in_flight()
    }

    pub fn record_bytes_fetched(&mut self, bytes: u64) {
        self.stats.bytes_fetched += bytes;
    }

    /// Takes fetched block bytes: decodes them and keeps them for upload.
    /// Failures are recorded (stats) and the block is not asked for again;
    /// its ancestor keeps standing in for it.
    pub fn insert_fetched(
        &mut self,
        results: impl IntoIterator<Item = (BlockKey, Result<Vec<u8>, FetchError>)>,
    ) {
        for (key, result) in results {
            self.requests.finished(&Request::Block(key));
            let bytes = match result {
                Ok(bytes) => bytes,
                Err(e) => {
                    self.fail(key, e.to_string());
                    continue;
                }
            };
            self.stats.bytes_fetched += bytes.len() as u64;
            match decode_fetched(key, self.index.block(&key), &bytes) {
                Ok(block) => self.insert_decoded(DecodedBlock::new(block)),
                Err(e) => self.fail(key, e.to_string()),
            }
        }
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        self.plan_requests();
    }

    /// Takes a worker's answer for block `key`: `fetched` response bytes and
    /// the decoded block, or why it failed for good.
    pub fn insert_worker_result(&mut self, key: BlockKey, fetched: u64, block: Result<DecodedBlock, String>) {
        self.requests.finished(&Request::Block(key));
        self.stats.bytes_fetched += fetched;
        match block {
            Ok(decoded) if decoded.block.key == key => self.insert_decoded(decoded),
            Ok(decoded) => self.fail(key, format!("asked for block {key}, got block {}", decoded.block.key)),
            Err(e) => self.fail(key, e),
        }
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        self.plan_requests();
    }

    /// Takes a decoded block.
    pub fn insert_decoded(&mut self, decoded: DecodedBlock) {
        let DecodedBlock { block, faces, cells } = decoded;
        let key = block.key;
        self.stats.blocks_loaded += 1;
        if faces == 0 {
            self.empty.insert(key);
            return;
        }
        self.decoded_bytes += std::mem::size_of_val(block.voxels.as_slice()) as u64;
        let cached = CachedBlock { block, faces, cells, needed_frame: self.frame_counter };
        if let Some(old) = self.decoded.insert(key, cached) {
            self.decoded_bytes -= std::mem::size_of_val(old.block.voxels.as_slice()) as u64;
        }
    }

    fn fail(&mut self, key: BlockKey, message: String) {
        self.stats.record_error(message);
        self.stats.blocks_failed += 1;
        self.failed.insert(key, self.stats.last_error.clone().unwrap_or_default());
    }

    pub fn failures(&self) -> impl Iterator<Item = (&BlockKey, &String)> {
        self.failed.iter()
    }

    fn is_ready(&self, key: &BlockKey) -> bool {
        self.gpu.contains_key(key) || self.empty.contains(key)
    }

    /// Decoded needed blocks not on the GPU yet, most needed first.
    fn awaiting_upload(&self) -> Vec<BlockKey> {
        let mut keys: Vec<(f32, BlockKey)> = self
            .needed()
            .into_iter()
            .filter(|(k, _)| self.decoded.contains_key(k) && !self.gpu.contains_key(k))
            .map(|(k, p)| (p, k))
            .collect();
        keys.sort_by(|a, b| b.0.total_cmp(&a.0).then(b.1.level.cmp(&a.1.level)).then(a.1.cmp(&b.1)));
        keys.into_iter().map(|(_, k)| k).collect()
    }

    /// Whether decoded blocks wait for the GPU.
    pub fn has_pending_uploads(&mut self) -> bool {
        self.update_traversal();
        !self.awaiting_upload().is_empty()
    }

    /// One frame's upload: needed decoded blocks, most needed first, up to
    /// `cap` bytes, in one staging write and one compute pass recorded into
    /// `encoder`, each into pooled buffers the residency grants within the
    /// budget. The caller submits `encoder` before the upload buffer is written
    /// again. Returns how many blocks went up.
    fn upload_into(&mut self, renderer: &Renderer, encoder: &mut wgpu::CommandEncoder, cap: u64) -> usize {
        // Fixed targets first: they shrink the block budget the traversal plans within.
        self.residency.set_fixed_bytes(self.fixed_gpu_bytes(
            renderer.occupancy_cells(),
            renderer.ao.downscale(),
            if renderer.ao.structure == AoStructure::Clipmap {
                renderer.clipmap.budget_bytes(self.manifest.grid.resolution)
            } else {
                renderer.clipmap.gpu_bytes()
            },
        ));
        self.update_traversal();
        let todo = self.awaiting_upload();
        if todo.is_empty() {
            return 0;
        }
        // What this frame can draw: the needed blocks and hidden ones already
        // loaded. Last frame's other blocks will not be drawn again, so they may go.
        let mut protected: HashSet<BlockKey> = self.needed().into_keys().collect();
        protected.extend(self.traversal.hidden.iter().filter(|k| self.gpu.contains_key(k)).copied());
        // The pacer times what the bytes cost: packing, the write, the expansion (not the traversal).
        let packing_from = (self.clock)();
        let mut batch = std::mem::take(&mut self.batch);
        for key in todo {
            let Some(cached) = self.decoded.get(&key) else { continue };
            if !batch.fits(&cached.block, cap) {
                break;
            }
            let faces = cached.faces;
            let room = self.residency.make_room(block_gpu_bytes(faces), &protected);
            for victim in &room.evict {
                if let Some(g) = self.gpu.remove(victim) {
                    self.residency.release(victim, g.buffers);
                }
            }
            if !room.fits {
                self.stats.uploads_refused += 1;
                break;
            }
            let allocate_from = (self.clock)();
            let buffers = self.residency.allocate(&renderer.device, key, faces, self.frame_counter);
            self.stats.note_webgpu((self.clock)() - allocate_from);
            let Some(buffers) = buffers else {
                self.stats.uploads_refused += 1;
                break;
            };
            let Some(cached) = self.decoded.get(&key) else { continue };
            batch.push(&cached.block, cached.faces, buffers);
        }
        if batch.is_empty() {
            self.batch = batch;
            return 0;
        }
        let webgpu_from = (self.clock)();
        let upload = self.upload.get_or_insert_with(|| upload_buffer(&renderer.device));
        batch.write(&renderer.queue, upload);
        let uploaded_bytes = batch.byte_len();
        self.stats.bytes_uploaded += uploaded_bytes;
        let blocks = renderer.expander.expand_batch(
            &renderer.device,
            encoder,
            &mut batch,
            &renderer.block_layout,
            upload,
            renderer.pass_timer.as_ref(),
        );
        self.batch = batch;
        let now = (self.clock)();
        self.stats.note_webgpu(now - webgpu_from);
        if let Some(pacer) = &mut self.pacer {
            pacer.record(uploaded_bytes, now - packing_from);
        }
        let n = blocks.len();
        for g in blocks {
            self.gpu.insert(g.key, g);
        }
        self.note_residency();
        n
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

    /// Double-click at `pixel` (viewport pixels, row 0 at the top): a frame or
    /// two later the orbit centres on the surface there (none: nothing changes).
    pub fn pick(&mut self, pixel: (f32, f32)) {
        let frame = self.frame_counter + 1;
        self.occlusion.get_or_insert_with(Occlusion::default).request_pick(pixel, frame);
    }

    /// The answer to the last [`Scene::pick`], once; it has already been applied to the camera.
    pub fn take_picked(&mut self) -> Option<Option<Vec3>> {
        self.picked.take()
    }

    /// Uploads until nothing needed waits (native loops; the browser uploads once per frame).
    pub fn upload_all(&mut self, renderer: &Renderer) {
        // Each batch rewrites the upload buffer, so each is submitted before the next.
        loop {
            let mut encoder = renderer
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("upload blocks") });
            if self.upload_into(renderer, &mut encoder, UPLOAD_BYTES_PER_FRAME) == 0 {
                return;
            }
            renderer.queue.submit([encoder.finish()]);
        }
    }

    /// Paces each frame's upload to `budget_ms` of main thread ([`UploadPacer`]);
    /// without it a frame uploads up to the whole upload buffer.
    pub fn pace_uploads(&mut self, budget_ms: f64) {
        self.pacer = Some(UploadPacer::new(budget_ms));
    }

    fn note_residency(&mut self) {
        self.stats.resident_bytes = self.residency.used_bytes();
        self.stats.peak_resident_bytes = self.residency.peak_bytes();
        self.stats.budget_bytes = self.residency.budget();
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
        renderer.encode_frame(&mut encoder, target, self.viewport, &params, &gpu_blocks);
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

    /// Blocks whose visibility decides what is fetched: every visited block
    /// (coarsest first, they prune most), those that meet the error too, but
    /// those around the eye, which are always visible. Each box is grown by a
    /// voxel of the level drawn for it last frame: a coarse stand-in's voxels
    /// stick out of the finer block's bounds by up to one of their edges, and
    /// must not hide the block they stand in for.
    fn occlusion_tests(&self) -> Vec<(BlockKey, crate::select::Aabb)> {
        let eye = self.eye();
        let drawn: HashSet<&BlockKey> = self.drawn.iter().collect();
        let max_level = self.manifest.coarsest_level();
        // Nothing drawn over it (its region is drawn by finer blocks, or not at all): its own.
        let drawn_level = |key: &BlockKey| {
            let mut k = *key;
            loop {
                if drawn.contains(&k) {
                    return k.level;
                }
                if k.level >= max_level {
                    return key.level;
                }
                k = k.parent();
            }
        };
        let mut tests: Vec<(BlockKey, crate::select::Aabb)> = Vec::new();
        for k in self.traversal.priority.keys() {
            let Some(tight) = block_bounds(&self.index, k) else { continue };
            let level = drawn_level(k);
            let grown = |b: &crate::select::Aabb| proxy_bounds(b, level);
            if contains_eye(&grown(&tight), eye) {
                continue;
            }
            // The tightest boxes the loaded data gives: the block's own cells, else its parent's.
            let cells_of = |k: &BlockKey| self.decoded.get(k).map(|c| &c.cells);
            let cells =
                cells_of(k).or_else(|| (k.level < max_level).then(|| k.parent()).and_then(|p| cells_of(&p)));
            match cells.and_then(|c| c.boxes_for(k)).filter(|b| !b.is_empty()) {
                Some(boxes) => {
                    tests.extend(boxes.iter().filter_map(|b| b.intersection(&tight)).map(|b| (*k, grown(&b))))
                }
                None => tests.push((*k, grown(&tight))),
            }
        }
        tests.sort_by(|a, b| b.0.level.cmp(&a.0.level).then(a.0.cmp(&b.0)));
        tests
    }

    /// Takes the newest occlusion feedback, if any arrived.
    fn take_feedback(&mut self) {
        let Some(v) = self.occlusion.as_mut().and_then(Occlusion::take_results) else {
            self.take_pick_answer();
            return;
        };
        self.take_pick_answer();
        if v.hidden != self.hidden {
            self.hidden = v.hidden;
            self.hidden_generation += 1;
            self.feedback_changed_frame = self.frame_counter;
        }
    }

    fn take_pick_answer(&mut self) {
        if let Some(answer) = self.occlusion.as_mut().and_then(Occlusion::take_picked) {
            if let Some(point) = answer.filter(|_| self.fixed_view.is_none()) {
                self.camera.recentre(point);
            }
            self.picked = Some(answer);
        }
    }

    /// After a budget change: evicts until within it, never what was just drawn.
    fn enforce_budget(&mut self) {
        let protected: HashSet<BlockKey> = self.drawn.iter().copied().collect();
        let room = self.residency.make_room(0, &protected);
        for victim in &room.evict {
            if let Some(g) = self.gpu.remove(victim) {
                self.residency.release(victim, g.buffers);
            }
        }
    }

    /// The occupancy payload ([`encode_sources`]) to hand to the worker, once.
    pub fn take_occupancy_job(&mut self) -> Option<Vec<u8>> {
        self.occupancy_job.take()
    }

    /// The worker's answer to the last job: the volume's mips, uploaded; an
    /// error is reported and the volume is built on the main thread from then on.
    pub fn finish_occupancy_job(&mut self, renderer: &Renderer, mips: Result<Vec<u8>, String>) {
        self.occupancy_job_in_flight = false;
        match mips.and_then(|b| OccupancyVolume::from_bytes(self.manifest.grid.resolution, &b)) {
            Ok(volume) if volume.cells == renderer.occupancy_cells() => {
                let webgpu_from = (self.clock)();
                renderer.upload_occupancy(&volume);
                self.stats.note_webgpu((self.clock)() - webgpu_from);
                self.stats.ao_volumes += 1;
                self.stats.ao_volumes_from_worker += 1;
            }
            Ok(_) => {}
            Err(e) => {
                self.stats.record_error(format!("AO volume worker: {e}; building on the main thread"));
                self.occupancy_offload = false;
                self.occupancy_for = None;
            }
        }
    }

    /// Drops decoded CPU copies beyond [`DECODED_CACHE_BYTES`], least recently
    /// needed first, never one on the GPU or needed now.
    fn trim_decoded(&mut self) {
        if self.decoded_bytes <= DECODED_CACHE_BYTES {
            return;
        }
        let mut victims: Vec<(u64, BlockKey)> = self
            .decoded
            .iter()
            .filter(|(k, _)| !self.gpu.contains_key(k) && !self.traversal.priority.contains_key(k))
            .map(|(k, c)| (c.needed_frame, *k))
            .collect();
        victims.sort();
        for (_, key) in victims {
            if self.decoded_bytes <= DECODED_CACHE_BYTES {
                break;
            }
            if let Some(c) = self.decoded.remove(&key) {
                self.decoded_bytes -= std::mem::size_of_val(c.block.voxels.as_slice()) as u64;
            }
        }
    }

    /// The blocks the occupancy volume is splatted from: the drawn blocks, each
    /// finer than an occupancy cell replaced by its cached ancestor whose voxels
    /// are one cell wide. Those ancestors are few, cheap to splat, and mostly
    /// independent of the view, so orbiting and refining rarely rebuild the
    /// volume and the AO does not change with the LOD.
    fn occupancy_sources(&self, drawn: &[BlockKey], cells: u32) -> Vec<BlockKey> {
        let cell_level = (self.manifest.grid.resolution / cells.max(1)).max(1).ilog2() as u8;
        self.sources_at_level(drawn, cell_level)
    }

    /// The drawn blocks, each finer than `cell_level` replaced by its decoded
    /// ancestor at that level (a cut of the hierarchy: no two overlap).
    fn sources_at_level(&self, drawn: &[BlockKey], cell_level: u8) -> Vec<BlockKey> {
        let mut sources: Vec<BlockKey> = drawn
            .iter()
            .map(|key| {
                let mut a = *key;
                while a.level < cell_level {
                    a = a.parent();
                }
                if self.decoded.contains_key(&a) { a } else { *key }
            })
            .collect();
        sources.sort();
        sources.dedup();
        sources
    }

    /// Rebuilds and uploads the occupancy volume when its sources changed; at
    /// most every [`OCCUPANCY_REBUILD_MS`] while blocks are still streaming in.
    fn update_occupancy(
        &mut self,
        renderer: &mut Renderer,
        encoder: &mut wgpu::CommandEncoder,
        drawn: &[BlockKey],
        settled: bool,
        now_ms: f64,
    ) {
        if self.ao_strength <= 0.0 {
            return;
        }
        if renderer.ao.structure == AoStructure::Clipmap {
            self.update_clipmap(renderer, encoder, drawn);
            return;
        }
        let sources = self.occupancy_sources(drawn, renderer.occupancy_cells());
        if self.occupancy_for.as_ref() == Some(&sources)
            || !(settled || now_ms - self.occupancy_built_ms >= OCCUPANCY_REBUILD_MS)
        {
            return;
        }
        if self.occupancy_offload && self.occupancy_job_in_flight {
            // One build at a time; the sources are compared again after its answer.
            return;
        }
        // Nothing drawn yet: the texture starts out empty, no need to splat nothing.
        if self.occupancy_offload && (!sources.is_empty() || self.occupancy_for.is_some()) {
            self.occupancy_job = Some(encode_sources(sources.iter().filter_map(|k| self.block(k))));
            self.occupancy_job_in_flight = true;
        } else if !sources.is_empty() || self.occupancy_for.is_some() {
            let volume = OccupancyVolume::build(
                self.manifest.grid.resolution,
                sources.iter().filter_map(|k| self.block(k)),
            );
            if volume.cells == renderer.occupancy_cells() {
                renderer.upload_occupancy(&volume);
                self.stats.ao_volumes += 1;
            }
        }
        self.occupancy_for = Some(sources);
        self.occupancy_built_ms = now_ms;
    }
}

impl Scene {
    /// Brings the clipmap to this frame's camera and drawn blocks, every
    /// frame (incremental: only scrolled-in slabs and blocks that arrived or
    /// left are splatted, on the GPU). Level k splats the drawn blocks cut at
    /// its cell's LOD level; the finest cell is the finest drawn voxel.
    fn update_clipmap(
        &mut self,
        renderer: &mut Renderer,
        encoder: &mut wgpu::CommandEncoder,
        drawn: &[BlockKey],
    ) {
        let Some(finest) = drawn.iter().map(|k| k.level).min() else { return };
        let resolution = self.manifest.grid.resolution;
        let layout = ClipmapLayout::for_scene(resolution, 1u32 << finest.min(30), CLIP_CELLS);
        let sources: Vec<Vec<BlockKey>> =
            (0..layout.levels).map(|k| self.sources_at_level(drawn, layout.cell(k).ilog2() as u8)).collect();
        let eye = self.eye();
        let forward = view_forward(self.view_proj(), eye);
        let before = renderer.clipmap.counters;
        renderer.update_clipmap(encoder, resolution, layout, (eye, forward), &sources, |k| self.block(k));
        let after = renderer.clipmap.counters;
        self.stats.ao_clipmap_updates += (after.updates - before.updates) as u32;
        self.stats.ao_clipmap_splats += after.splats - before.splats;
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
