//! The viewer's state for one scene, shared by the browser and the native
//! offscreen path: camera, current selection, the block cache (decoded blocks
//! and their GPU buffers), what to fetch next, what to draw, and stats.
//! It never fetches by itself; the caller feeds it fetched bytes, so the same
//! code runs under the browser's event loop and a blocking native loop.

use std::collections::{HashMap, HashSet};

use glam::{Mat4, Vec3};
use voxstream_format::{Block, BlockKey, HierarchyPage, Manifest, PageRef, SceneIndex};

use crate::ao::OccupancyVolume;
use crate::camera::OrbitCamera;
use crate::decode::decode_fetched;
use crate::expand::GpuBlock;
use crate::fetch::FetchError;
use crate::render::{FrameParams, Renderer};
use crate::select::{SelectParams, ViewParams, block_bounds, resolve_draw_set, scene_bounds, select_blocks};
use crate::stats::Stats;

/// GPU bytes of cached blocks beyond which blocks that are neither wanted nor
/// drawn are evicted, least recently drawn first.
const CACHE_BUDGET_BYTES: u64 = 384 << 20;
/// While streaming, rebuild the occupancy volume at most this often.
const OCCUPANCY_REBUILD_MS: f64 = 400.0;

struct CachedBlock {
    block: Block,
    /// `None` for a block without faces.
    gpu: Option<GpuBlock>,
    last_drawn: u64,
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

/// What `Scene::wanted` was last computed for.
type SelectedFor = (OrbitCamera, (u32, u32), usize, Option<FixedView>);

/// What a call to [`Scene::draw`] drew.
#[derive(Debug, Clone, PartialEq)]
pub struct DrawnFrame {
    pub view_proj: Mat4,
    pub drawn: Vec<BlockKey>,
    /// Every wanted block was loaded (or failed for good) and is drawn as itself.
    pub complete: bool,
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
    pub stats: Stats,
    viewport: (u32, u32),
    /// Camera, viewport, pages loaded and fixed view when `wanted` was computed.
    selected_for: Option<SelectedFor>,
    wanted: Vec<BlockKey>,
    /// Pages the current view needs, largest projected error first.
    wanted_pages: Vec<PageRef>,
    pending_pages: HashSet<BlockKey>,
    failed_pages: HashMap<BlockKey, String>,
    cache: HashMap<BlockKey, CachedBlock>,
    pending: HashSet<BlockKey>,
    failed: HashMap<BlockKey, String>,
    drawn: Vec<BlockKey>,
    occupancy_for: Option<Vec<BlockKey>>,
    occupancy_built_ms: f64,
    frame_counter: u64,
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
            stats: Stats::default(),
            viewport: (viewport.0.max(1), viewport.1.max(1)),
            selected_for: None,
            wanted: Vec::new(),
            wanted_pages: Vec::new(),
            pending_pages: HashSet::new(),
            failed_pages: HashMap::new(),
            cache: HashMap::new(),
            pending: HashSet::new(),
            failed: HashMap::new(),
            drawn: Vec::new(),
            occupancy_for: None,
            occupancy_built_ms: f64::NEG_INFINITY,
            frame_counter: 0,
        }
    }

    pub fn viewport(&self) -> (u32, u32) {
        self.viewport
    }

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

    /// The blocks this view wants, recomputed when the camera, the viewport or
    /// the loaded part of the hierarchy changed.
    pub fn wanted(&mut self) -> &[BlockKey] {
        let now = (self.camera, self.viewport, self.index.pages_loaded(), self.fixed_view);
        if self.selected_for != Some(now) {
            let view = ViewParams {
                view_proj: self.view_proj(),
                eye: self.eye(),
                focal_pixels: self
                    .fixed_view
                    .map_or_else(|| self.camera.focal_pixels(self.viewport.1 as f32), |v| v.focal_pixels),
            };
            let selection = select_blocks(&self.index, &self.manifest.root.key, &view, &self.select_params);
            self.wanted = selection.blocks;
            self.wanted_pages = selection.pages;
            self.selected_for = Some(now);
        }
        &self.wanted
    }

    /// Hierarchy pages the view needs that are neither loaded, in flight nor
    /// failed, most needed first, at most `max`; they are marked in flight.
    /// Fetch them before blocks: they decide which blocks are wanted.
    pub fn next_page_fetches(&mut self, max: usize) -> Vec<PageRef> {
        self.wanted();
        let todo: Vec<PageRef> = self
            .wanted_pages
            .iter()
            .filter(|p| !self.pending_pages.contains(&p.root) && !self.failed_pages.contains_key(&p.root))
            .take(max)
            .cloned()
            .collect();
        self.pending_pages.extend(todo.iter().map(|p| p.root));
        todo
    }

    /// Takes a fetched page. A page that fails is not asked for again; the
    /// blocks above it stay drawn as they are.
    pub fn insert_page(&mut self, page: &PageRef, result: Result<Vec<u8>, FetchError>) {
        self.pending_pages.remove(&page.root);
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
    }

    /// The wanted blocks and all their ancestors present in the manifest: the
    /// ancestors are the stand-ins while finer blocks stream in (or fail).
    fn needed(&mut self) -> HashSet<BlockKey> {
        self.wanted();
        let max_level = self.manifest.coarsest_level();
        let mut needed = HashSet::new();
        for key in &self.wanted {
            let mut k = *key;
            while needed.insert(k) && k.level < max_level {
                k = k.parent();
            }
        }
        needed.retain(|k| self.index.block(k).is_some());
        needed
    }

    /// Needed blocks that are neither cached, in flight nor failed, coarsest
    /// first (so the view fills in coarse to fine), nearest first within a
    /// level, at most `max`; they are marked in flight.
    pub fn next_fetches(&mut self, max: usize) -> Vec<BlockKey> {
        let mut todo: Vec<BlockKey> = self
            .needed()
            .into_iter()
            .filter(|k| {
                !self.cache.contains_key(k) && !self.pending.contains(k) && !self.failed.contains_key(k)
            })
            .collect();
        let eye = self.eye();
        let dist = |k: &BlockKey| block_bounds(&self.index, k).map_or(f32::INFINITY, |b| b.distance_to(eye));
        todo.sort_by(|a, b| b.level.cmp(&a.level).then(dist(a).total_cmp(&dist(b))).then(a.cmp(b)));
        todo.truncate(max);
        self.pending.extend(todo.iter().copied());
        todo
    }

    pub fn in_flight(&self) -> usize {
        self.pending.len() + self.pending_pages.len()
    }

    pub fn record_bytes_fetched(&mut self, bytes: u64) {
        self.stats.bytes_fetched += bytes;
    }

    /// Takes fetched results: decodes them, expands them on the GPU in one
    /// submission and caches them. Failures are recorded (stats line) and the
    /// block is not asked for again; its ancestor keeps standing in for it.
    pub fn insert_fetched(
        &mut self,
        renderer: &Renderer,
        results: impl IntoIterator<Item = (BlockKey, Result<Vec<u8>, FetchError>)>,
    ) {
        let mut encoder = renderer
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("expand blocks") });
        let mut expanded = 0;
        for (key, result) in results {
            self.pending.remove(&key);
            let bytes = match result {
                Ok(bytes) => bytes,
                Err(e) => {
                    self.fail(key, e.to_string());
                    continue;
                }
            };
            self.stats.bytes_fetched += bytes.len() as u64;
            let block = match decode_fetched(key, self.index.block(&key), &bytes) {
                Ok(block) => block,
                Err(e) => {
                    self.fail(key, e.to_string());
                    continue;
                }
            };
            let gpu =
                renderer.expander.expand(&renderer.device, &mut encoder, &block, &renderer.block_layout);
            expanded += 1;
            self.stats.blocks_loaded += 1;
            self.cache.insert(key, CachedBlock { block, gpu, last_drawn: self.frame_counter });
        }
        if expanded > 0 {
            renderer.queue.submit([encoder.finish()]);
        }
    }

    fn fail(&mut self, key: BlockKey, message: String) {
        self.stats.record_error(message);
        self.failed.insert(key, self.stats.last_error.clone().unwrap_or_default());
    }

    pub fn failures(&self) -> impl Iterator<Item = (&BlockKey, &String)> {
        self.failed.iter()
    }

    /// Every wanted block and page is settled (loaded or failed) and nothing is in flight.
    pub fn is_settled(&mut self) -> bool {
        self.wanted();
        self.pending.is_empty()
            && self.pending_pages.is_empty()
            && self.wanted.iter().all(|k| self.cache.contains_key(k) || self.failed.contains_key(k))
            && self.wanted_pages.iter().all(|p| self.failed_pages.contains_key(&p.root))
    }

    pub fn is_cached(&self, key: &BlockKey) -> bool {
        self.cache.contains_key(key)
    }

    /// The decoded block, if cached.
    pub fn block(&self, key: &BlockKey) -> Option<&Block> {
        self.cache.get(key).map(|c| &c.block)
    }

    pub fn gpu_block(&self, key: &BlockKey) -> Option<&GpuBlock> {
        self.cache.get(key).and_then(|c| c.gpu.as_ref())
    }

    /// Keys drawn by the last [`Scene::draw`].
    pub fn drawn(&self) -> &[BlockKey] {
        &self.drawn
    }

    /// Draws the current view into `target` and submits it. `now_ms` paces
    /// occupancy rebuilds while streaming.
    pub fn draw(&mut self, renderer: &mut Renderer, target: &wgpu::TextureView, now_ms: f64) -> DrawnFrame {
        self.frame_counter += 1;
        let settled = self.is_settled();
        let max_level = self.manifest.coarsest_level();
        let cache = &self.cache;
        let drawn = resolve_draw_set(&self.wanted, max_level, |k| cache.contains_key(k));
        let complete = settled && drawn == self.wanted;

        self.update_occupancy(renderer, &drawn, settled, now_ms);

        let mut gpu_blocks = Vec::with_capacity(drawn.len());
        let mut faces = 0u64;
        for key in &drawn {
            if let Some(c) = self.cache.get_mut(key) {
                c.last_drawn = self.frame_counter;
                if let Some(g) = &c.gpu {
                    faces += g.faces as u64;
                }
            }
        }
        for key in &drawn {
            if let Some(g) = self.gpu_block(key) {
                gpu_blocks.push(g);
            }
        }
        let params = FrameParams {
            view_proj: self.view_proj(),
            eye: self.eye(),
            grid_resolution: self.manifest.grid.resolution as f32,
            ao_strength: self.ao_strength,
        };
        let mut encoder =
            renderer.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        renderer.encode_frame(&mut encoder, target, self.viewport, &params, &gpu_blocks);
        renderer.queue.submit([encoder.finish()]);

        self.stats.blocks_drawn = drawn.len() as u32;
        self.stats.faces_drawn = faces;
        self.drawn = drawn.clone();
        self.evict();
        DrawnFrame { view_proj: params.view_proj, drawn, complete }
    }

    /// The blocks the occupancy volume is splatted from: the drawn blocks, each
    /// finer than an occupancy cell replaced by its cached ancestor whose voxels
    /// are one cell wide. Those ancestors are few, cheap to splat, and mostly
    /// independent of the view, so orbiting and refining rarely rebuild the
    /// volume and the AO does not change with the LOD.
    fn occupancy_sources(&self, drawn: &[BlockKey], cells: u32) -> Vec<BlockKey> {
        let cell_level = (self.manifest.grid.resolution / cells.max(1)).max(1).ilog2() as u8;
        let mut sources: Vec<BlockKey> = drawn
            .iter()
            .map(|key| {
                let mut a = *key;
                while a.level < cell_level {
                    a = a.parent();
                }
                if self.cache.contains_key(&a) { a } else { *key }
            })
            .collect();
        sources.sort();
        sources.dedup();
        sources
    }

    /// Rebuilds and uploads the occupancy volume when its sources changed; at
    /// most every [`OCCUPANCY_REBUILD_MS`] while blocks are still streaming in.
    fn update_occupancy(&mut self, renderer: &Renderer, drawn: &[BlockKey], settled: bool, now_ms: f64) {
        if self.ao_strength <= 0.0 {
            return;
        }
        let sources = self.occupancy_sources(drawn, renderer.occupancy_cells());
        if self.occupancy_for.as_ref() == Some(&sources)
            || !(settled || now_ms - self.occupancy_built_ms >= OCCUPANCY_REBUILD_MS)
        {
            return;
        }
        // Nothing drawn yet: the texture starts out empty, no need to splat nothing.
        if !sources.is_empty() || self.occupancy_for.is_some() {
            let volume = OccupancyVolume::build(
                self.manifest.grid.resolution,
                sources.iter().filter_map(|k| self.block(k)),
            );
            if volume.cells == renderer.occupancy_cells() {
                renderer.upload_occupancy(&volume);
            }
        }
        self.occupancy_for = Some(sources);
        self.occupancy_built_ms = now_ms;
    }

    /// Drops least recently drawn blocks beyond the budget, never one that is
    /// needed (wanted or a stand-in), drawn, or on the coarsest level.
    fn evict(&mut self) {
        let mut total: u64 = self.cache.values().filter_map(|c| c.gpu.as_ref()).map(|g| g.gpu_bytes).sum();
        if total <= CACHE_BUDGET_BYTES {
            return;
        }
        let mut keep = self.needed();
        keep.extend(self.drawn.iter().copied());
        let coarsest = self.manifest.coarsest_level();
        let mut victims: Vec<(u64, BlockKey)> = self
            .cache
            .iter()
            .filter(|(k, _)| !keep.contains(k) && k.level != coarsest)
            .map(|(k, c)| (c.last_drawn, *k))
            .collect();
        victims.sort();
        for (_, key) in victims {
            if total <= CACHE_BUDGET_BYTES {
                break;
            }
            if let Some(g) = self.cache.remove(&key).and_then(|c| c.gpu) {
                total -= g.gpu_bytes;
                g.destroy();
            }
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
