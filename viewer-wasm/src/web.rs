//! Browser entry point: canvas and WebGPU surface, fetch scheduling, pointer
//! input, the stats line, `window.voxstream`, and `document.body.dataset.ready`.
//!
//! Frames are drawn on demand (a block arrived, the camera moved, the canvas
//! resized), never continuously: SwiftShader, a CPU WebGPU, takes about a
//! second per frame of a detailed scene.

use std::cell::{Cell, RefCell};

use rustc_hash::FxHashMap as HashMap;
use voxstream_format::{Manifest, SceneSummary};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{HtmlCanvasElement, PointerEvent, WheelEvent};

use crate::fetch::{BlockSource, FetchError, http};
use crate::render::Renderer;
use crate::request::Request;
use crate::scene::Scene;
use crate::select::Refinement;
use crate::worker::{DecodePool, OccupancyWorker, WorkerResult};

const CANVAS_ID: &str = "voxstream-canvas";
const STATS_ID: &str = "voxstream-stats";

thread_local! {
    // wasm is single-threaded; the app lives here so that wgpu callbacks
    // (which must be Send) can reach it without capturing it.
    static APP: RefCell<Option<App>> = const { RefCell::new(None) };
    static FRAME_SCHEDULED: Cell<bool> = const { Cell::new(false) };
    // At most one frame on the GPU at a time: on a slow (CPU) WebGPU, queueing
    // frames only delays the one that shows the latest state.
    static FRAME_IN_FLIGHT: Cell<bool> = const { Cell::new(false) };
    static REDRAW_AFTER_FLIGHT: Cell<bool> = const { Cell::new(false) };
    // The canvas's size in device pixels, as the ResizeObserver last saw it.
    // Reading clientWidth in a frame would force a layout there (the stats line
    // changed the page since the last one): milliseconds of main thread.
    static CANVAS_SIZE: Cell<Option<(u32, u32)>> = const { Cell::new(None) };
}

/// Keeps [`CANVAS_SIZE`] current: the observer runs after layout, where reading the size is free.
fn observe_canvas_size(canvas: &HtmlCanvasElement) -> Result<(), String> {
    let observed = canvas.clone();
    let on_resize = Closure::<dyn FnMut(js_sys::Array)>::new(move |_entries: js_sys::Array| {
        let size = canvas_pixels(&observed);
        if CANVAS_SIZE.with(|c| c.replace(Some(size))) != Some(size) {
            request_frame();
        }
    });
    let observer = web_sys::ResizeObserver::new(on_resize.as_ref().unchecked_ref())
        .map_err(|e| format!("ResizeObserver: {e:?}"))?;
    observer.observe(canvas);
    // Both live as long as the page.
    on_resize.forget();
    std::mem::forget(observer);
    Ok(())
}

struct Pointer {
    x: f32,
    y: f32,
    button: i16,
    shift: bool,
}

struct App {
    renderer: Renderer,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    scene: Scene,
    source: BlockSource,
    canvas: HtmlCanvasElement,
    pointers: HashMap<i32, Pointer>,
    last_view_proj: [f32; 16],
    /// Decode workers; `None` where workers could not start (then the main thread decodes).
    decoder: Option<DecodePool>,
    /// Builds the AO volume; `None` where it could not start (then the main thread builds it).
    occupancy_worker: Option<OccupancyWorker>,
    /// Abort handles of requests in flight, by [`request_id`].
    aborts: HashMap<String, web_sys::AbortController>,
    ready: bool,
    /// Fly mode: drag looks around, WASD/QE move.
    fly_mode: bool,
    /// The view the page opened with, for reset.
    home: crate::camera::OrbitCamera,
    start_ms: f64,
    frames: u64,
    /// The last double-click's answer: the surface point (grid units), or `None` for none.
    last_pick: Option<Option<glam::Vec3>>,
    picks_answered: u64,
    /// The screenshot button asks for the next frame's image.
    screenshot_pending: bool,
    /// When the stats line was last written (`now_ms`).
    stats_shown_ms: f64,
}

fn request_id(r: &Request) -> String {
    match r {
        Request::Page(p) => format!("page {}", p.root),
        Request::Block(k) => format!("block {k}"),
    }
}

fn window() -> web_sys::Window {
    web_sys::window().expect("a browser window")
}

fn now_ms() -> f64 {
    thread_local! {
        // Looked up once: `window.performance` is a call into JS, and the frame reads the clock often.
        static PERFORMANCE: Option<web_sys::Performance> = window().performance();
    }
    PERFORMANCE.with(|p| p.as_ref().map_or(0.0, |p| p.now()))
}

fn log(msg: &str) {
    web_sys::console::log_1(&JsValue::from_str(msg));
}

fn show_status(text: &str) {
    if let Some(el) = window().document().and_then(|d| d.get_element_by_id(STATS_ID)) {
        el.set_text_content(Some(text));
    }
}

fn fail(msg: &str) {
    web_sys::console::error_1(&JsValue::from_str(msg));
    show_status(&format!("error: {msg}"));
}

#[wasm_bindgen(start)]
pub fn start() {
    console_error_panic_hook::set_once();
    // The decode workers load this module too; they have no window and run no viewer.
    if web_sys::window().is_none() {
        return;
    }
    wasm_bindgen_futures::spawn_local(async {
        if let Err(e) = run().await {
            fail(&e);
        }
    });
}

/// A query parameter of the page URL, if present and not empty.
fn url_param(name: &str) -> Option<String> {
    let search = window().location().search().ok()?;
    web_sys::UrlSearchParams::new_with_str(&search).ok()?.get(name).filter(|s| !s.is_empty())
}

/// A numeric query parameter within `range`; anything else is ignored with a console note.
fn url_number(name: &str, range: std::ops::RangeInclusive<f32>) -> Option<f32> {
    let text = url_param(name)?;
    match text.parse::<f32>() {
        Ok(v) if range.contains(&v) => Some(v),
        _ => {
            log(&format!("voxstream: ignoring ?{name}={text} (expected a number in {range:?})"));
            None
        }
    }
}

/// The page's default scene: `<meta name="voxstream-scene" content="<id>">`, which a static
/// publish (`voxstream publish`) writes into its copy of index.html.
fn meta_scene() -> Option<String> {
    let doc = window().document()?;
    let el = doc.query_selector("meta[name=\"voxstream-scene\"]").ok()??;
    el.get_attribute("content").filter(|s| !s.is_empty())
}

/// Whether the page is a static publish (`<meta name="voxstream-static" content="packs">`,
/// written by `voxstream publish`): no API, blocks are range reads of packs.
fn meta_static_packs() -> bool {
    let Some(doc) = window().document() else { return false };
    let Ok(Some(el)) = doc.query_selector("meta[name=\"voxstream-static\"]") else { return false };
    el.get_attribute("content").as_deref() == Some("packs")
}

/// The scene id: `?scene=<id>`, else the page's `voxstream-scene` meta tag, else the first
/// scene the server lists. URLs are relative to the page (`api/scenes/...`), so the viewer
/// works at a server's root and from a static publish in any folder.
async fn scene_id() -> Result<String, String> {
    if let Some(id) = url_param("scene").or_else(meta_scene) {
        return Ok(id);
    }
    let bytes = http::get_bytes("api/scenes", "scene list").await.map_err(|e| e.to_string())?;
    let scenes: Vec<SceneSummary> = serde_json::from_slice(&bytes).map_err(|e| format!("scene list: {e}"))?;
    scenes.into_iter().next().map(|s| s.id).ok_or_else(|| "the server has no scenes".to_string())
}

/// How often the stats line is rewritten: often enough to read as live.
const STATS_LINE_INTERVAL_MS: f64 = 250.0;

/// Main-thread milliseconds a frame may spend uploading blocks ([`crate::expand::UploadPacer`]).
const UPLOAD_BUDGET_MS: f64 = 2.0;

/// Canvas drawing-buffer size: its CSS size in device pixels.
fn canvas_pixels(canvas: &HtmlCanvasElement) -> (u32, u32) {
    let dpr = window().device_pixel_ratio().max(1.0);
    let w = (canvas.client_width().max(1) as f64 * dpr).round() as u32;
    let h = (canvas.client_height().max(1) as f64 * dpr).round() as u32;
    (w.clamp(1, 8192), h.clamp(1, 8192))
}

async fn run() -> Result<(), String> {
    let start_ms = now_ms();
    let document = window().document().ok_or("no document")?;
    let canvas: HtmlCanvasElement = document
        .get_element_by_id(CANVAS_ID)
        .ok_or_else(|| format!("no #{CANVAS_ID} element"))?
        .dyn_into()
        .map_err(|_| format!("#{CANVAS_ID} is not a canvas"))?;
    if !wgpu::util::is_browser_webgpu_supported().await {
        return Err("this browser does not offer WebGPU".into());
    }
    show_status("starting WebGPU…");
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends: wgpu::Backends::BROWSER_WEBGPU,
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    let surface = instance
        .create_surface(wgpu::SurfaceTarget::Canvas(canvas.clone()))
        .map_err(|e| format!("surface: {e}"))?;
    let adapter = instance
        .request_adapter(&wgpu::RequestAdapterOptions {
            compatible_surface: Some(&surface),
            ..Default::default()
        })
        .await
        .map_err(|e| format!("no WebGPU adapter: {e}"))?;
    // ?gpu-timing=1: timestamp queries around each pass, read back into
    // window.voxstream.stats().gpuTimed (the AO benchmark's Chromium times).
    let mut required_features = wgpu::Features::empty();
    if url_param("gpu-timing").as_deref() == Some("1") {
        if adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            required_features |= wgpu::Features::TIMESTAMP_QUERY;
        } else {
            log("voxstream: ?gpu-timing=1 but the adapter has no timestamp queries");
        }
    }
    let (device, queue) = adapter
        .request_device(&wgpu::DeviceDescriptor {
            label: Some("voxstream"),
            required_features,
            required_limits: wgpu::Limits::default().using_resolution(adapter.limits()),
            ..Default::default()
        })
        .await
        .map_err(|e| format!("no WebGPU device: {e}"))?;

    let caps = surface.get_capabilities(&adapter);
    let format = if caps.formats.contains(&crate::COLOR_FORMAT) {
        crate::COLOR_FORMAT
    } else {
        *caps.formats.first().ok_or("the canvas offers no format")?
    };
    let (width, height) = canvas_pixels(&canvas);
    CANVAS_SIZE.with(|c| c.set(Some((width, height))));
    observe_canvas_size(&canvas)?;
    canvas.set_width(width);
    canvas.set_height(height);
    let mut config =
        surface.get_default_config(&adapter, width, height).ok_or("the canvas is not supported")?;
    config.format = format;
    if caps.alpha_modes.contains(&wgpu::CompositeAlphaMode::Opaque) {
        config.alpha_mode = wgpu::CompositeAlphaMode::Opaque;
    }
    surface.configure(&device, &config);
    log(&format!("voxstream: {} canvas {width}x{height} {format:?}", adapter.get_info().name));

    let id = scene_id().await?;
    show_status(&format!("loading scene {id}…"));
    let static_packs = meta_static_packs();
    if static_packs {
        log("voxstream: static site: blocks are range reads of packs");
    }
    let source = BlockSource::Http {
        scene_url: format!("api/scenes/{}", String::from(js_sys::encode_uri_component(&id))),
        static_packs,
    };
    let manifest_bytes = source.manifest_bytes().await.map_err(|e| e.to_string())?;
    let manifest = Manifest::from_json(&manifest_bytes).map_err(|e| format!("scene {id}: {e}"))?;
    let renderer = Renderer::new(device, queue, format, manifest.grid.resolution);
    let mut scene = Scene::new(manifest, (width, height));
    // Half the 4 ms a main-thread task may take: the rest of the frame needs the other half.
    scene.pace_uploads(UPLOAD_BUDGET_MS);
    // ?ao=0 turns ambient occlusion off, ?px=3 coarsens the LOD (max projected geometric error).
    if let Some(ao) = url_number("ao", 0.0..=1.0) {
        scene.ao_strength = ao;
    }
    if let Some(px) = url_number("px", 0.25..=64.0) {
        scene.select_params.max_error_pixels = px;
    }
    // ?budget=64 holds the viewer to 64 MiB of GPU memory (default 512).
    if let Some(mib) = url_number("budget", 16.0..=65536.0) {
        scene.set_budget_bytes((mib as f64 * (1 << 20) as f64) as u64);
    }
    scene.record_bytes_fetched(manifest_bytes.len() as u64);
    let home = scene.camera;
    // ?view=x,y,z,yaw,pitch,distance opens a shared view.
    if let Some(v) = url_param("view") {
        if !scene.camera.apply_url(&v) {
            log(&format!("voxstream: ignoring ?view={v}"));
        }
    }
    // ?camera=eye x,y,z,target x,y,z,fov: a look-at view in the scene's source
    // coordinates (camera.json's eye, target and fov_y_deg; +Y up).
    if let Some(text) = url_param("camera") {
        let grid = &scene.manifest.grid;
        if !scene.camera.apply_source_look_at(&text, grid.origin, grid.voxel_size) {
            log(&format!("voxstream: ignoring ?camera={text} (expected 7 numbers: eye, target, fov_y_deg)"));
        }
    }
    // Level changes cross-fade over 250 ms; ?fade=0 makes them pop, ?fade=1000 slows them.
    scene.clock = now_ms;
    scene.crossfade =
        crate::crossfade::Crossfade::new(url_number("fade", 0.0..=5000.0).map_or(250.0, f64::from));
    if url_param("refine").as_deref() == Some("holes") {
        scene.select_params.refinement = Refinement::HolesAllowed;
    }
    if url_param("occlusion").as_deref() == Some("0") {
        scene.occlusion_culling = false;
    }

    let decoder = match DecodePool::new(|result: WorkerResult| {
        let started = now_ms();
        with_app(|app| {
            let live = app.decoder.as_mut().is_some_and(|pool| pool.done(&result.key));
            if !live {
                return;
            }
            if let Err(e) = &result.block {
                web_sys::console::warn_1(&JsValue::from_str(&format!("voxstream: {e}")));
            }
            app.scene.insert_worker_result(result.key, result.fetched, result.block);
            app.start_fetches();
            app.scene.stats.note_main_thread_task("block taken in", now_ms() - started);
        });
        request_frame();
    }) {
        Ok(pool) => Some(pool),
        Err(e) => {
            log(&format!("voxstream: decoding on the main thread ({e})"));
            None
        }
    };
    let occupancy_worker = match OccupancyWorker::new(|_, mips| {
        let started = now_ms();
        with_app(|app| {
            app.scene.finish_occupancy_job(&app.renderer, mips);
            app.scene.stats.note_main_thread_task("AO volume taken in", now_ms() - started);
        });
        request_frame();
    }) {
        Ok(worker) => Some(worker),
        Err(e) => {
            log(&format!("voxstream: building the AO volume on the main thread ({e})"));
            None
        }
    };
    scene.occupancy_offload = occupancy_worker.is_some();
    APP.with(|app| {
        *app.borrow_mut() = Some(App {
            renderer,
            surface,
            config,
            scene,
            source,
            canvas: canvas.clone(),
            pointers: HashMap::default(),
            last_view_proj: [0.0; 16],
            last_pick: None,
            picks_answered: 0,
            screenshot_pending: false,
            stats_shown_ms: f64::NEG_INFINITY,
            aborts: HashMap::default(),
            decoder,
            occupancy_worker,
            ready: false,
            fly_mode: false,
            home,
            start_ms,
            frames: 0,
        })
    });
    install_input(&canvas)?;
    install_js_api()?;
    request_frame();
    Ok(())
}

/// Runs `f` on the app unless it is missing or already borrowed (re-entrancy).
fn with_app<R>(f: impl FnOnce(&mut App) -> R) -> Option<R> {
    APP.with(|app| app.try_borrow_mut().ok().and_then(|mut a| a.as_mut().map(f)))
}

fn request_frame() {
    if FRAME_IN_FLIGHT.with(Cell::get) {
        REDRAW_AFTER_FLIGHT.with(|r| r.set(true));
        return;
    }
    if FRAME_SCHEDULED.with(|s| s.replace(true)) {
        return;
    }
    let cb = Closure::once_into_js(move |now: f64| {
        FRAME_SCHEDULED.with(|s| s.set(false));
        with_app(|app| app.frame(now));
    });
    if window().request_animation_frame(cb.unchecked_ref()).is_err() {
        FRAME_SCHEDULED.with(|s| s.set(false));
    }
}

impl App {
    fn frame(&mut self, now: f64) {
        let started = now_ms();
        self.frame_inner(now);
        self.scene.stats.note_main_thread_task("frame", now_ms() - started);
    }

    fn frame_inner(&mut self, now: f64) {
        let mut step = now_ms();
        self.resize_if_needed();
        self.start_fetches();
        self.scene.stats.note_phase("fetches", &mut step, now_ms());

        let webgpu_from = now_ms();
        let surface_texture = self.surface.get_current_texture();
        self.scene.stats.note_webgpu(now_ms() - webgpu_from);
        let texture = match surface_texture {
            wgpu::CurrentSurfaceTexture::Success(t) | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                self.surface.configure(&self.renderer.device, &self.config);
                request_frame();
                return;
            }
            other => {
                log(&format!("voxstream: no canvas texture this frame ({other:?})"));
                request_frame();
                return;
            }
        };
        let view = texture.texture.create_view(&Default::default());
        let frame = self.scene.draw(&mut self.renderer, &view, now);
        if std::mem::take(&mut self.screenshot_pending) {
            // Same task as the draw: the canvas still holds this frame's image.
            self.save_screenshot();
        }
        let webgpu_from = now_ms();
        self.renderer.queue.present(texture);
        self.scene.stats.note_webgpu(now_ms() - webgpu_from);
        if let Some(job) = self.scene.take_occupancy_job() {
            let grid = self.scene.manifest.grid.resolution;
            if let Some(Err(e)) = self.occupancy_worker.as_mut().map(|w| w.submit(grid, job)) {
                self.scene.finish_occupancy_job(&self.renderer, Err(e));
            }
        }
        if let Some(answer) = self.scene.take_picked() {
            self.last_pick = Some(answer);
            self.picks_answered += 1;
            if answer.is_some() {
                self.camera_moved();
            }
        }
        if self.scene.needs_another_frame() || self.renderer.ao_accumulating() {
            // Blocks wait for the per-frame upload cap, occlusion feedback is
            // settling, or the AO of a still view is still accumulating frames.
            REDRAW_AFTER_FLIGHT.with(|r| r.set(true));
        }
        self.last_view_proj = frame.view_proj.to_cols_array();
        self.frames += 1;
        let frame_number = self.frames;
        let complete = frame.complete;
        FRAME_IN_FLIGHT.with(|f| f.set(true));
        // Done on the GPU: time the frame, mark the page ready after the first
        // complete frame, and draw again if anything changed meanwhile.
        self.renderer.queue.on_submitted_work_done(move || {
            FRAME_IN_FLIGHT.with(|f| f.set(false));
            with_app(|app| app.frame_done(frame_number, now, complete));
            if REDRAW_AFTER_FLIGHT.with(|r| r.replace(false)) {
                request_frame();
            }
        });
        let mut step = now_ms();
        self.show_stats(false);
        self.scene.stats.note_phase("stats line", &mut step, now_ms());
    }

    fn frame_done(&mut self, frame_number: u64, started: f64, complete: bool) {
        let done = now_ms();
        self.scene.stats.frame_ms = done - started;
        self.take_gpu_times();
        if self.scene.stats.first_image_ms == 0.0 && self.scene.stats.blocks_drawn > 0 {
            self.scene.stats.first_image_ms = done - self.start_ms;
        }
        let became_ready = complete && !self.ready && frame_number == self.frames;
        if became_ready {
            self.ready = true;
            self.scene.stats.ready_ms = done - self.start_ms;
            if let Some(body) = window().document().and_then(|d| d.body()) {
                let _ = body.dataset().set("ready", "1");
            }
            log(&format!(
                "voxstream: ready after {:.0} ms ({} blocks, {} faces, {} bytes)",
                done - self.start_ms,
                self.scene.stats.blocks_drawn,
                self.scene.stats.faces_drawn,
                self.scene.stats.bytes_fetched
            ));
        }
        // The ready frame's line and the last one before the page goes still are
        // what people (and tests) read: those are always written.
        let last_for_now = !REDRAW_AFTER_FLIGHT.with(Cell::get) && !FRAME_SCHEDULED.with(Cell::get);
        self.show_stats(became_ready || last_for_now);
    }

    /// The last frame the pass timer read back, into the stats (it arrives
    /// asynchronously: both the stats line and `stats()` take it when they read).
    fn take_gpu_times(&mut self) {
        self.scene.stats.gpu_timed = self.renderer.pass_timer.as_ref().and_then(|t| t.latest());
    }

    /// Writes the stats line, at most every [`STATS_LINE_INTERVAL_MS`] unless `force`d: each
    /// write formats the line and re-lays the page out inside the frame's task, twice a frame.
    /// `stats()` gives the same numbers to JavaScript at any time.
    fn show_stats(&mut self, force: bool) {
        let now = now_ms();
        if !force && now - self.stats_shown_ms < STATS_LINE_INTERVAL_MS {
            return;
        }
        self.stats_shown_ms = now;
        show_status(&self.scene.stats.line());
    }

    fn resize_if_needed(&mut self) {
        let Some(canvas) = CANVAS_SIZE.with(Cell::get) else { return };
        let (w, h) = crate::scene::drawing_size_within(canvas, self.scene.budget_bytes());
        if (w, h) != (self.config.width, self.config.height) {
            if (w, h) != canvas {
                log(&format!(
                    "voxstream: drawing {w}x{h} of the canvas's {}x{} device pixels: the frame's targets may take half the {} MiB GPU budget",
                    canvas.0,
                    canvas.1,
                    self.scene.budget_bytes() >> 20
                ));
            }
            self.canvas.set_width(w);
            self.canvas.set_height(h);
            self.config.width = w;
            self.config.height = h;
            self.surface.configure(&self.renderer.device, &self.config);
            self.scene.set_viewport(w, h);
        }
    }

    fn start_fetches(&mut self) {
        // Requests the view no longer needs give their connection back.
        for stale in self.scene.take_stale_requests() {
            if let Some(abort) = self.aborts.remove(&request_id(&stale)) {
                abort.abort();
            }
            if let (Request::Block(key), Some(pool)) = (&stale, self.decoder.as_mut()) {
                pool.abort(key);
            }
        }
        for request in self.scene.start_requests() {
            if let (Request::Block(key), Some(pool)) = (&request, self.decoder.as_mut()) {
                // Fetch and decode in a worker; the main thread only uploads.
                let entry = self.scene.index.block(key);
                let hash = entry.map(|e| e.hash.as_str());
                let range = self.scene.index.pack_range(key);
                let block = self.source.block_request(*key, hash, range.as_ref());
                pool.submit(*key, &block, entry.map(|e| e.voxels), hash);
                continue;
            }
            let source = self.source.clone();
            let abort = web_sys::AbortController::new().ok();
            let signal = abort.as_ref().map(|a| a.signal());
            if let Some(a) = abort {
                self.aborts.insert(request_id(&request), a);
            }
            match request {
                Request::Page(page) => {
                    wasm_bindgen_futures::spawn_local(async move {
                        let result = source.page_bytes_with(&page, signal.as_ref()).await;
                        with_app(|app| {
                            // Aborted (no longer needed): the queue has already let it go.
                            if app.aborts.remove(&request_id(&Request::Page(page.clone()))).is_none() {
                                return;
                            }
                            app.scene.insert_page(&page, result);
                            app.start_fetches();
                        });
                        request_frame();
                    });
                }
                Request::Block(key) => {
                    let hash = self.scene.index.block(&key).map(|e| e.hash.clone());
                    let range = self.scene.index.pack_range(&key);
                    wasm_bindgen_futures::spawn_local(async move {
                        let result: Result<Vec<u8>, FetchError> = source
                            .block_bytes_with(key, hash.as_deref(), range.as_ref(), signal.as_ref())
                            .await;
                        with_app(|app| {
                            if app.aborts.remove(&request_id(&Request::Block(key))).is_none() {
                                return;
                            }
                            let errors = app.scene.stats.errors;
                            app.scene.insert_fetched([(key, result)]);
                            if app.scene.stats.errors > errors {
                                let e = app.scene.stats.last_error.as_deref().unwrap_or("");
                                web_sys::console::warn_1(&JsValue::from_str(&format!("voxstream: {e}")));
                            }
                            // Keep the connections busy; frames come at the GPU's pace.
                            app.start_fetches();
                        });
                        request_frame();
                    });
                }
            }
        }
    }

    fn pointer_down(&mut self, e: &PointerEvent) {
        let _ = self.canvas.set_pointer_capture(e.pointer_id());
        self.pointers.insert(
            e.pointer_id(),
            Pointer {
                x: e.client_x() as f32,
                y: e.client_y() as f32,
                button: e.button(),
                shift: e.shift_key(),
            },
        );
    }

    fn pointer_move(&mut self, e: &PointerEvent) {
        let (x, y) = (e.client_x() as f32, e.client_y() as f32);
        let css_height = self.canvas.client_height().max(1) as f32;
        let Some(p) = self.pointers.get(&e.pointer_id()) else { return };
        let (dx, dy) = (x - p.x, y - p.y);
        if self.pointers.len() == 1 {
            if p.button == 0 && !p.shift && self.fly_mode {
                self.scene.camera.look(dx, dy);
            } else if p.button == 0 && !p.shift {
                self.scene.camera.orbit(dx, dy);
            } else {
                self.scene.camera.pan(dx, dy, css_height);
            }
        } else {
            // Two fingers: spread to zoom, move together to pan.
            let others: Vec<(f32, f32)> = self
                .pointers
                .iter()
                .filter(|(id, _)| **id != e.pointer_id())
                .map(|(_, q)| (q.x, q.y))
                .collect();
            if let Some(&(ox, oy)) = others.first() {
                let before = ((p.x - ox).powi(2) + (p.y - oy).powi(2)).sqrt();
                let after = ((x - ox).powi(2) + (y - oy).powi(2)).sqrt();
                if before > 1.0 && after > 1.0 {
                    self.scene.camera.zoom(before / after);
                }
                self.scene.camera.pan(dx * 0.5, dy * 0.5, css_height);
            }
        }
        if let Some(p) = self.pointers.get_mut(&e.pointer_id()) {
            p.x = x;
            p.y = y;
        }
        self.camera_moved();
    }

    /// After any camera change: the URL carries the view, and a frame follows.
    fn camera_moved(&mut self) {
        let location = window().location();
        if let (Ok(search), Ok(history)) = (location.search(), window().history()) {
            if let Ok(params) = web_sys::UrlSearchParams::new_with_str(&search) {
                params.set("view", &self.scene.camera.to_url());
                let _ = history.replace_state_with_url(
                    &JsValue::NULL,
                    "",
                    Some(&format!("?{}", String::from(params.to_string()))),
                );
            }
        }
        request_frame();
    }

    fn key_down(&mut self, e: &web_sys::KeyboardEvent) {
        let step = self.scene.camera.fly_speed() * if e.shift_key() { 0.2 } else { 0.05 };
        let cam = &mut self.scene.camera;
        match e.key().to_lowercase().as_str() {
            "f" => {
                self.fly_mode = !self.fly_mode;
                log(&format!("voxstream: fly mode {}", if self.fly_mode { "on" } else { "off" }));
            }
            "r" => *cam = self.home,
            "w" => cam.fly(step, 0.0, 0.0),
            "s" => cam.fly(-step, 0.0, 0.0),
            "a" => cam.fly(0.0, -step, 0.0),
            "d" => cam.fly(0.0, step, 0.0),
            "e" => cam.fly(0.0, 0.0, step),
            "q" => cam.fly(0.0, 0.0, -step),
            _ => return,
        }
        self.camera_moved();
    }

    /// `window.voxstream.set({px, budget, ao, aoStructure, aoMode, aoSettings, occlusion, fly})`:
    /// the panel's settings (`aoSettings`: any fields of [`crate::ao::AoSettings`]).
    /// Every call draws a frame, so `set({})` asks for one.
    fn apply_settings(&mut self, settings: &serde_json::Value) {
        if let Some(px) = settings["px"].as_f64().filter(|v| (0.25..=64.0).contains(v)) {
            self.scene.select_params.max_error_pixels = px as f32;
        }
        if let Some(mib) = settings["budget"].as_f64().filter(|v| (16.0..=65536.0).contains(v)) {
            self.scene.set_budget_bytes((mib * (1 << 20) as f64) as u64);
        }
        if let Some(ao) = settings["ao"].as_f64().filter(|v| (0.0..=1.0).contains(v)) {
            self.scene.ao_strength = ao as f32;
        }
        match settings["aoStructure"].as_str() {
            Some("clipmap") => self.renderer.ao.structure = crate::ao::AoStructure::Clipmap,
            Some("volume") => self.renderer.ao.structure = crate::ao::AoStructure::Volume,
            _ => {}
        }
        match settings["aoMode"].as_str() {
            Some("cone") => self.renderer.ao.mode = crate::ao::AoMode::Cone,
            Some("field") => self.renderer.ao.mode = crate::ao::AoMode::Field,
            _ => {}
        }
        if let Some(patch) = settings.get("aoSettings") {
            match self.renderer.ao.patched(patch) {
                Ok(ao) => self.renderer.ao = ao,
                Err(e) => log(&format!("voxstream: {e}")),
            }
        }
        if let Some(on) = settings["occlusion"].as_bool() {
            self.scene.occlusion_culling = on;
        }
        match settings["refinement"].as_str() {
            Some("closed") => self.scene.select_params.refinement = Refinement::AlwaysClosed,
            Some("holes") => self.scene.select_params.refinement = Refinement::HolesAllowed,
            _ => {}
        }
        if let Some(on) = settings["fly"].as_bool() {
            self.fly_mode = on;
        }
        if settings["reset"].as_bool() == Some(true) {
            self.scene.camera = self.home;
        }
        if settings["screenshot"].as_bool() == Some(true) {
            self.screenshot_pending = true;
        }
        self.start_fetches();
        self.camera_moved();
    }

    /// Double-click: re-centre the orbit on the surface under the cursor.
    fn double_click(&mut self, e: &web_sys::MouseEvent) {
        let (css_w, css_h) =
            (self.canvas.client_width().max(1) as f32, self.canvas.client_height().max(1) as f32);
        let (w, h) = self.scene.viewport();
        let pixel = (e.offset_x() as f32 * w as f32 / css_w, e.offset_y() as f32 * h as f32 / css_h);
        self.scene.pick(pixel);
        request_frame();
    }

    /// Downloads the canvas as a PNG named after the scene and the view.
    fn save_screenshot(&self) {
        let Ok(url) = self.canvas.to_data_url_with_type("image/png") else {
            log("voxstream: the canvas could not be read for a screenshot");
            return;
        };
        let Some(document) = window().document() else { return };
        let Ok(link) = document.create_element("a") else { return };
        let name = format!(
            "voxstream-{}.png",
            self.scene.manifest.name.replace(|c: char| !c.is_ascii_alphanumeric(), "_")
        );
        let _ = link.set_attribute("href", &url);
        let _ = link.set_attribute("download", &name);
        if let Ok(link) = link.dyn_into::<web_sys::HtmlElement>() {
            link.click();
        }
    }

    fn pointer_up(&mut self, e: &PointerEvent) {
        self.pointers.remove(&e.pointer_id());
    }

    fn wheel(&mut self, e: &WheelEvent) {
        let pixels = match e.delta_mode() {
            WheelEvent::DOM_DELTA_LINE => e.delta_y() * 16.0,
            WheelEvent::DOM_DELTA_PAGE => e.delta_y() * 400.0,
            _ => e.delta_y(),
        };
        self.scene.camera.zoom((pixels * 0.0015).clamp(-1.0, 1.0).exp() as f32);
        self.camera_moved();
    }
}

fn listen<E: JsCast + 'static>(
    target: &web_sys::EventTarget,
    name: &str,
    passive: bool,
    mut handler: impl FnMut(&E) + 'static,
) -> Result<(), String> {
    let closure = Closure::<dyn FnMut(web_sys::Event)>::new(move |event: web_sys::Event| {
        if let Some(e) = event.dyn_ref::<E>() {
            handler(e);
        }
    });
    let options = web_sys::AddEventListenerOptions::new();
    options.set_passive(passive);
    target
        .add_event_listener_with_callback_and_add_event_listener_options(
            name,
            closure.as_ref().unchecked_ref(),
            &options,
        )
        .map_err(|e| format!("listening for {name}: {e:?}"))?;
    // Listeners live as long as the page.
    closure.forget();
    Ok(())
}

fn install_input(canvas: &HtmlCanvasElement) -> Result<(), String> {
    let target: &web_sys::EventTarget = canvas.as_ref();
    listen::<PointerEvent>(target, "pointerdown", true, |e| {
        with_app(|app| app.pointer_down(e));
    })?;
    listen::<PointerEvent>(target, "pointermove", true, |e| {
        with_app(|app| app.pointer_move(e));
    })?;
    for name in ["pointerup", "pointercancel"] {
        listen::<PointerEvent>(target, name, true, |e| {
            with_app(|app| app.pointer_up(e));
        })?;
    }
    listen::<WheelEvent>(target, "wheel", false, |e| {
        e.prevent_default();
        with_app(|app| app.wheel(e));
    })?;
    listen::<web_sys::MouseEvent>(target, "contextmenu", false, |e| e.prevent_default())?;
    listen::<web_sys::MouseEvent>(target, "dblclick", true, |e| {
        with_app(|app| app.double_click(e));
    })?;
    listen::<web_sys::Event>(window().as_ref(), "resize", true, |_| request_frame())?;
    listen::<web_sys::KeyboardEvent>(window().as_ref(), "keydown", true, |e| {
        // Typing into the panel's fields is not flying.
        let typing = e
            .target()
            .and_then(|t| t.dyn_into::<web_sys::Element>().ok())
            .is_some_and(|el| matches!(el.tag_name().as_str(), "INPUT" | "SELECT" | "TEXTAREA"));
        if !typing {
            with_app(|app| app.key_down(e));
        }
    })?;
    Ok(())
}

fn json_to_js(value: &serde_json::Value) -> JsValue {
    js_sys::JSON::parse(&value.to_string()).unwrap_or(JsValue::NULL)
}

fn install_js_api() -> Result<(), String> {
    let api = js_sys::Object::new();
    let stats = Closure::<dyn Fn() -> JsValue>::new(|| {
        with_app(|app| {
            app.take_gpu_times();
            json_to_js(&serde_json::to_value(&app.scene.stats).unwrap_or_default())
        })
        .unwrap_or(JsValue::NULL)
    });
    let view = Closure::<dyn Fn() -> JsValue>::new(|| {
        with_app(|app| {
            let (width, height) = app.scene.viewport();
            json_to_js(&serde_json::json!({
                "viewProj": app.last_view_proj,
                "width": width,
                "height": height,
                "drawnBlocks": app.scene.drawn().iter().map(|k| k.to_string()).collect::<Vec<_>>(),
                "camera": {
                    "target": app.scene.camera.target.to_array(),
                    "eye": app.scene.camera.eye().to_array(),
                },
                // null: no double-click answered yet; "none": it hit no surface; else the point.
                "picksAnswered": app.picks_answered,
                "pick": match app.last_pick {
                    None => serde_json::Value::Null,
                    Some(None) => serde_json::json!("none"),
                    Some(Some(p)) => serde_json::json!(p.to_array()),
                },
            }))
        })
        .unwrap_or(JsValue::NULL)
    });
    let set = |name: &str, f: &JsValue| {
        js_sys::Reflect::set(&api, &JsValue::from_str(name), f)
            .map_err(|e| format!("window.voxstream.{name}: {e:?}"))
    };
    let settings = Closure::<dyn Fn(JsValue)>::new(|value: JsValue| {
        let text = js_sys::JSON::stringify(&value).map(String::from).unwrap_or_default();
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) {
            with_app(|app| app.apply_settings(&v));
        }
    });
    set("stats", stats.as_ref())?;
    set("view", view.as_ref())?;
    set("set", settings.as_ref())?;
    stats.forget();
    view.forget();
    settings.forget();
    js_sys::Reflect::set(&window(), &JsValue::from_str("voxstream"), &api)
        .map_err(|e| format!("window.voxstream: {e:?}"))?;
    Ok(())
}
