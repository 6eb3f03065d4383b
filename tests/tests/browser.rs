//! Browser end-to-end test: the real server (in-process, ephemeral port) serving a scene built from
//! data/koala.obj and the wasm viewer bundle, opened in headless Chromium with a SwiftShader
//! (CPU) WebGPU adapter by tests/browser/e2e.mjs (playwright-core).
//!
//! Checks that the page draws blocks and that the silhouette in its canvas screenshot matches the
//! CPU coverage mask of the blocks it reports as drawn, projected with the matrix it reports.
//!
//! Needs: viewer-wasm/dist (scripts/build-web.sh), node + tests/browser/node_modules and
//! /usr/bin/chromium (scripts/setup.sh). Missing pieces fail the test with the command to run.
//! The screenshot and the page's JSON are kept in <target>/e2e/ for people to look at.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value;
use voxstream::http::{AppState, router};
use voxstream::pipeline::{BuildOptions, Resolution, build_scene};
use voxstream_e2e::coverage;
use voxstream_format::{BlockKey, decode_block};
use voxstream_viewer::BACKGROUND_RGBA8;

/// How long the whole node harness may take (its own ready timeout is 240 s by default).
const HARNESS_TIMEOUT: Duration = Duration::from_secs(480);

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// `<workspace target dir>/e2e` (CARGO_TARGET_TMPDIR is `<target>/tmp`).
fn artifacts_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).parent().expect("target/tmp has a parent").join("e2e")
}

fn require(path: &Path, fix: &str) {
    assert!(path.exists(), "{} is missing: {fix}", path.display());
}

/// The node harness's packages (playwright-core) are installed.
fn require_harness(root: &Path) {
    require(
        &root.join("tests/browser/node_modules/playwright-core/package.json"),
        "install the harness dependencies: bash scripts/setup.sh (npm ci in tests/browser)",
    );
}

/// Runs `cmd`, echoing and collecting its stdout+stderr lines; kills it after `timeout`.
/// Returns (success, collected output).
fn run_with_timeout(mut cmd: Command, timeout: Duration) -> (bool, String) {
    let mut child: Child =
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap_or_else(|e| {
            panic!("cannot start {cmd:?}: {e} (is node installed? run scripts/setup.sh)")
        });
    let log = Arc::new(Mutex::new(String::new()));
    let pump = |stream: Box<dyn Read + Send>, log: Arc<Mutex<String>>| {
        std::thread::spawn(move || {
            for line in BufReader::new(stream).lines().map_while(Result::ok) {
                println!("{line}");
                let mut log = log.lock().unwrap();
                log.push_str(&line);
                log.push('\n');
            }
        })
    };
    let readers = [
        pump(Box::new(child.stdout.take().unwrap()), log.clone()),
        pump(Box::new(child.stderr.take().unwrap()), log.clone()),
    ];
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().expect("waiting for node") {
            break Some(status);
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    for r in readers {
        let _ = r.join();
    }
    let mut out = log.lock().unwrap().clone();
    match status {
        Some(s) if s.success() => (true, out),
        Some(s) => {
            out.push_str(&format!("(harness exited with {s})\n"));
            (false, out)
        }
        None => {
            out.push_str(&format!("(harness killed after {timeout:?})\n"));
            (false, out)
        }
    }
}

/// Decodes the screenshot into (width, height, RGB8 pixels).
fn read_png_rgb(path: &Path) -> (u32, u32, Vec<u8>) {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().expect("screenshot is a PNG");
    let mut buf = vec![0; reader.output_buffer_size().expect("PNG size fits in memory")];
    let info = reader.next_frame(&mut buf).expect("decode screenshot");
    let (w, h) = (info.width, info.height);
    let channels = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => panic!("unexpected screenshot colour type {other:?}"),
    };
    let rgb = buf[..info.buffer_size()].chunks_exact(channels).flat_map(|p| [p[0], p[1], p[2]]).collect();
    (w, h, rgb)
}

fn json_f32_array<const N: usize>(v: &Value, what: &str) -> [f32; N] {
    let arr = v.as_array().unwrap_or_else(|| panic!("{what} is not an array: {v}"));
    assert_eq!(arr.len(), N, "{what} should have {N} numbers: {v}");
    std::array::from_fn(|i| arr[i].as_f64().unwrap_or_else(|| panic!("{what}[{i}] is not a number")) as f32)
}

#[test]
fn browser_renders_koala_matching_cpu_coverage() {
    let root = workspace_root();
    let web = root.join("viewer-wasm/dist");
    require(&web.join("index.html"), "build the viewer bundle first: bash scripts/build-web.sh");
    let script = root.join("tests/browser/e2e.mjs");
    require(&script, "the browser harness is part of the repository");
    require_harness(&root);

    // 1. Scene: data/koala.obj -> temp store.
    let store = tempfile::tempdir().expect("temp store");
    let t = Instant::now();
    let report = build_scene(
        &root.join("data/koala.obj"),
        store.path(),
        &BuildOptions { resolution: Resolution::Explicit(512), ..Default::default() },
    )
    .expect("build_scene(data/koala.obj)");
    println!(
        "built scene {:?}: {} triangles, {} voxels, {} blocks, {} bytes in {:.1?}",
        report.id,
        report.triangles,
        report.voxels,
        report.blocks,
        report.bytes,
        t.elapsed()
    );
    assert!(report.blocks > 0, "the build produced no blocks");

    // 2. Server on an ephemeral port, running on its own runtime while this thread drives node.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    // No --web: the viewer compiled into the binary (server/build.rs, src/http/web.rs).
    assert!(
        voxstream::http::web::has_embedded_viewer(),
        "the server embeds no viewer: run bash scripts/build-web.sh, then cargo test again"
    );
    let state = AppState::load(store.path(), None).expect("AppState::load");
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).expect("bind 127.0.0.1:0");
    let addr = listener.local_addr().unwrap();
    let server = rt.spawn(async move { axum::serve(listener, router(state)).await });
    // ?gpu-timing=1: the AO benchmark's Chromium times come from these timestamps.
    let url = format!("http://{addr}/?scene={}&gpu-timing=1", report.id);

    // 3. Headless Chromium, with the checks below.
    render_and_check(&url, &artifacts_dir(), &report.scene_dir, true);
    check_gpu_timing(&artifacts_dir().join("browser.json"), true);
    assert!(!server.is_finished(), "the server stopped during the browser run: {:?}", rt.block_on(server));
    server.abort();
}

/// With `?gpu-timing=1` the page's stats hold a drawn frame's GPU time per
/// pass, the G-buffer draw and the AO trace among them, each finite and
/// positive; without it, none.
fn check_gpu_timing(browser_json: &Path, asked: bool) {
    let result: Value = serde_json::from_slice(&std::fs::read(browser_json).unwrap()).unwrap();
    let stats = &result["stats"];
    let timed = &stats["gpuTimed"];
    if !asked {
        assert!(timed.is_null(), "GPU pass times without ?gpu-timing=1: {timed}");
        return;
    }
    let passes = timed["passes"].as_array().unwrap_or_else(|| panic!("no GPU pass times: {stats}"));
    let ms = |label: &str| passes.iter().find(|p| p["label"] == label).and_then(|p| p["ms"].as_f64());
    for label in ["voxels", "cs_trace", "fs_composite"] {
        let t = ms(label).unwrap_or_else(|| panic!("no {label} pass among {passes:?}"));
        assert!(t.is_finite() && t > 0.0 && t < 60_000.0, "{label}: {t} ms");
    }
    let frame = timed["frame"].as_u64().unwrap_or(0);
    assert!(
        frame >= 1 && frame <= stats["framesDrawn"].as_u64().unwrap_or(0),
        "timed frame {frame}: {stats}"
    );
    println!("GPU pass times (SwiftShader) of frame {frame}: {passes:?}");
}

/// Opens `url` in headless Chromium (tests/browser/e2e.mjs), waits for the ready marker and checks
/// the screenshot's silhouette against the CPU coverage of the blocks the page says it drew, read
/// from `scene_dir` (the store's scene folder). Artifacts go to `out`.
/// With `interact`, the harness then presses the screenshot button and double-clicks a background
/// corner and the canvas centre; [`check_interactions`] judges what came of it.
fn render_and_check(url: &str, out: &Path, scene_dir: &Path, interact: bool) {
    let root = workspace_root();
    let script = root.join("tests/browser/e2e.mjs");
    std::fs::create_dir_all(out).unwrap();
    for name in ["browser.png", "browser.json"] {
        let _ = std::fs::remove_file(out.join(name));
    }
    let mut cmd = Command::new("node");
    cmd.arg(&script).arg(url).arg(out).current_dir(&root);
    if interact {
        cmd.env("VOXSTREAM_E2E_INTERACT", "1");
    }
    let (ok, log) = run_with_timeout(cmd, HARNESS_TIMEOUT);
    assert!(ok, "browser harness failed for {url}; its output (page console included):\n{log}");

    // 4. What the page reported.
    let json_path = out.join("browser.json");
    let result: Value = serde_json::from_slice(
        &std::fs::read(&json_path).unwrap_or_else(|e| panic!("{}: {e}\n{log}", json_path.display())),
    )
    .expect("browser.json is JSON");
    let page_errors = result["pageErrors"].as_array().expect("browser.json has pageErrors");
    assert!(page_errors.is_empty(), "uncaught exceptions on the page: {page_errors:?}\n{log}");
    let stats = &result["stats"];
    let view = &result["view"];
    let blocks_drawn = stats["blocksDrawn"].as_u64().unwrap_or_else(|| panic!("stats.blocksDrawn: {stats}"));
    assert!(blocks_drawn > 0, "the page drew no blocks: stats = {stats}");
    assert_eq!(
        view["viewProj"], result["viewAfter"]["viewProj"],
        "the camera moved while the screenshot was taken; the comparison needs a still view"
    );
    let view_proj: [f32; 16] = json_f32_array(&view["viewProj"], "view.viewProj");
    let keys: Vec<String> = view["drawnBlocks"]
        .as_array()
        .unwrap_or_else(|| panic!("view.drawnBlocks: {view}"))
        .iter()
        .map(|k| k.as_str().expect("block keys are strings").to_owned())
        .collect();
    assert_eq!(keys.len() as u64, blocks_drawn, "view.drawnBlocks and stats.blocksDrawn disagree");

    // 5. Screenshot silhouette.
    let (w, h, rgb) = read_png_rgb(&out.join("browser.png"));
    assert_eq!(
        (Some(w as u64), Some(h as u64)),
        (view["width"].as_u64(), view["height"].as_u64()),
        "screenshot size differs from the canvas size the page reports (CSS size != drawing buffer?)"
    );
    let silhouette: Vec<bool> = rgb.chunks_exact(3).map(|p| p != &BACKGROUND_RGBA8[..3]).collect();
    let lit = silhouette.iter().filter(|&&s| s).count();
    assert!(lit > 0, "the screenshot is pure background colour: nothing visible was rendered");
    assert!(lit < silhouette.len(), "the screenshot has no background pixel at all");

    // 6. CPU coverage of the drawn blocks, read back from the store the server used
    //    (each block's range of its pack).
    let id = scene_dir.file_name().and_then(|n| n.to_str()).expect("a scene folder");
    let scene = voxstream::store::open_scene(scene_dir.parent().expect("a store"), id)
        .unwrap_or_else(|e| panic!("{}: {e}", scene_dir.display()));
    let blocks: Vec<_> = keys
        .iter()
        .map(|k| {
            let key: BlockKey = k.parse().unwrap_or_else(|e| panic!("bad block key {k:?}: {e}"));
            let entry =
                scene.index.read().block(&key).cloned().unwrap_or_else(|| panic!("{k} is not in the scene"));
            let bytes = scene.read_block(&entry).unwrap_or_else(|e| panic!("{k}: {e}"));
            (key, decode_block(&bytes).unwrap_or_else(|e| panic!("decode {k}: {e}")))
        })
        .collect();
    let expected = coverage::coverage_mask(&blocks, &view_proj, w, h);
    let cmp = coverage::compare_masks(&silhouette, &expected, w, h);
    println!("browser silhouette vs CPU coverage: {cmp:?}; artifacts in {}", out.display());
    assert!(
        cmp.within_tolerance(),
        "browser silhouette differs from the CPU coverage mask: {cmp:?} (screenshot: {})",
        out.join("browser.png").display()
    );

    // The comparison must be able to fail: the same blocks under a camera moved by ~5% of the
    // width must not match the screenshot.
    let mut moved = view_proj;
    moved[12] += 0.1 * moved[15];
    let wrong = coverage::compare_masks(&silhouette, &coverage::coverage_mask(&blocks, &moved, w, h), w, h);
    assert!(!wrong.within_tolerance(), "a moved camera still matched the screenshot: {wrong:?}");
    // The AO's clipmap (the default structure) was built on the GPU: compute passes splatted
    // blocks into it. Any occupancy volume (the comparison structure) came from the worker.
    let clipmap_updates = stats["aoClipmapUpdates"].as_u64().unwrap_or(0);
    let clipmap_splats = stats["aoClipmapSplats"].as_u64().unwrap_or(0);
    assert!(clipmap_updates > 0 && clipmap_splats > 0, "the AO clipmap was never built: {stats}");
    let volumes = stats["aoVolumes"].as_u64().unwrap_or(0);
    assert_eq!(
        stats["aoVolumesFromWorker"].as_u64(),
        Some(volumes),
        "the main thread built an AO volume: {stats}"
    );
    // The main thread's longest task, split into the viewer's own work and its WebGPU calls.
    let ms = |k: &str| stats[k].as_f64().unwrap_or(f64::NAN);
    let (task, own, webgpu) = (ms("longestMainTaskMs"), ms("longestOwnTaskMs"), ms("longestWebgpuMs"));
    println!(
        "main thread: longest task {task:.1} ms, own work {own:.1} ms ({}), longest in WebGPU calls {webgpu:.1} ms; \
         {} of {} tasks over 4 ms of own work; longest traversal {:.1} ms; longest frame steps (ms) {}",
        stats["longestOwnTaskKind"],
        stats["ownTasksOver4ms"],
        stats["mainTasks"],
        ms("longestTraversalMs"),
        stats["longestPhasesMs"]
    );
    assert!(own > 0.0 && own <= task && webgpu <= task, "main-thread split out of order: {stats}");
    if interact {
        check_interactions(&result, out, &silhouette, &view_proj, (w, h));
    }
}

/// The screenshot button saved the canvas as drawn, a double-click on the background changed
/// nothing, and one on the scan put the orbit centre on the surface under the cursor.
fn check_interactions(
    result: &Value,
    out: &Path,
    silhouette: &[bool],
    view_proj: &[f32; 16],
    size: (u32, u32),
) {
    let interact = &result["interact"];
    assert!(interact.is_object(), "the harness reported no interactions: {result}");
    let (dw, dh, rgb) = read_png_rgb(&out.join("download.png"));
    assert_eq!((dw, dh), size, "the screenshot button's PNG is not the canvas size");
    let saved: Vec<bool> = rgb.chunks_exact(3).map(|p| p != &BACKGROUND_RGBA8[..3]).collect();
    let cmp = coverage::compare_masks(&saved, silhouette, size.0, size.1);
    println!("screenshot button vs page screenshot: {cmp:?}");
    assert!(cmp.within_tolerance() && saved.iter().any(|&s| s), "the saved PNG is not the view: {cmp:?}");

    let target = |v: &Value| -> Vec<f64> {
        v.as_array()
            .unwrap_or_else(|| panic!("camera target: {v}"))
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let before = target(&result["view"]["camera"]["target"]);
    assert_eq!(
        interact["cornerPick"], "none",
        "a double-click on the background found a surface: {interact}"
    );
    assert_eq!(
        target(&interact["cornerTarget"]),
        before,
        "a double-click on the background moved the orbit centre"
    );
    let picked = target(&interact["centrePick"]);
    assert_eq!(target(&interact["centreTarget"]), picked, "the orbit centre is not the picked point");
    assert_ne!(picked, before, "the orbit centre did not move");
    // The picked point lies on the clicked pixel's ray: it projects back onto the canvas centre.
    let m = glam::Mat4::from_cols_array(view_proj);
    let c = m * glam::Vec4::new(picked[0] as f32, picked[1] as f32, picked[2] as f32, 1.0);
    let ndc = c.truncate() / c.w;
    let px = ((ndc.x * 0.5 + 0.5) * size.0 as f32, (0.5 - ndc.y * 0.5) * size.1 as f32);
    let centre = (size.0 as f32 / 2.0, size.1 as f32 / 2.0);
    let off = ((px.0 - centre.0).powi(2) + (px.1 - centre.1).powi(2)).sqrt();
    assert!(off < 2.5, "the picked point projects to {px:?}, {off:.1} px from the clicked {centre:?}");
    assert!((0.0..1.0).contains(&ndc.z), "the picked point is outside the depth range: {ndc}");
    // And it is on the scan: some drawn pixel near the click.
    let (cx, cy) = (centre.0 as usize, centre.1 as usize);
    assert!(silhouette[cy * size.0 as usize + cx], "the clicked pixel shows no surface in the screenshot");
}

/// The upload page against the full server (jobs, tus, SSE, thumbnails) on an empty store:
/// tests/browser/upload.mjs drops data/koala.obj onto the page, one PATCH is cut and resumed,
/// both progress bars reach 100 %, the link opens the viewer, which becomes ready.
#[test]
fn upload_page_builds_and_opens_scene() {
    let started = Instant::now();
    let root = workspace_root();
    let web = root.join("viewer-wasm/dist");
    for page in ["index.html", "upload.html", "upload.js", "upload.css"] {
        require(&web.join(page), "build the viewer bundle first: bash scripts/build-web.sh");
    }
    let script = root.join("tests/browser/upload.mjs");
    require(&script, "the upload harness is part of the repository");
    require_harness(&root);
    let mesh = root.join("data/koala.obj");

    // The server as `voxstream serve` runs it (jobs, uploads, recovery), at a low default
    // resolution so SwiftShader draws the result quickly.
    let store = tempfile::tempdir().expect("temp store");
    let mut config = voxstream::config::ServerConfig::new(store.path());
    config.web = Some(web.clone());
    config.resolution = Some(64);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let shutdown = tokio_util::sync::CancellationToken::new();
    let state = rt.block_on(async { AppState::start(config, shutdown) }).expect("AppState::start");
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).expect("bind 127.0.0.1:0");
    let addr = listener.local_addr().unwrap();
    let app = router(state.clone()).into_make_service_with_connect_info::<std::net::SocketAddr>();
    let server = rt.spawn(async move { axum::serve(listener, app).await });
    let base = format!("http://{addr}");

    let out = artifacts_dir();
    std::fs::create_dir_all(&out).unwrap();
    for name in ["upload.png", "upload-viewer.png", "upload.json"] {
        let _ = std::fs::remove_file(out.join(name));
    }
    let mut cmd = Command::new("node");
    cmd.arg(&script).arg(&base).arg(&mesh).arg(&out).current_dir(&root);
    let (ok, log) = run_with_timeout(cmd, HARNESS_TIMEOUT);
    assert!(!server.is_finished(), "the server stopped during the browser run: {:?}", rt.block_on(server));
    assert!(ok, "upload harness failed for {base}; its output (page console included):\n{log}");
    let json_path = out.join("upload.json");
    let result: Value = serde_json::from_slice(
        &std::fs::read(&json_path).unwrap_or_else(|e| panic!("{}: {e}\n{log}", json_path.display())),
    )
    .expect("upload.json is JSON");
    let page = &result["page"];
    assert_eq!(result["pageErrors"].as_array().map(Vec::len), Some(0), "uncaught exceptions: {result}");
    assert_eq!(page["error"], Value::Null, "the page showed an error: {page}");

    // Both bars moved forward only and ended at 100 %; the upload went up in several chunks.
    for bar in ["upload", "build"] {
        let seen: Vec<f64> = page["bars"][bar]
            .as_array()
            .unwrap_or_else(|| panic!("bars.{bar}: {page}"))
            .iter()
            .map(|v| v.as_f64().expect("bar values are numbers"))
            .collect();
        assert_eq!(seen.last(), Some(&100.0), "{bar} bar did not end at 100: {seen:?}");
        assert!(seen.windows(2).all(|w| w[0] <= w[1]), "{bar} bar went backwards: {seen:?}");
        assert_eq!(page[bar]["aria"], "100", "{bar} aria-valuenow: {page}");
        assert_eq!(page[format!("{bar}Value")].as_f64(), Some(100.0), "{bar} <progress> value: {page}");
    }
    let uploads_seen = page["bars"]["upload"].as_array().unwrap().len();
    assert!(uploads_seen >= 4, "the upload bar took only {uploads_seen} values for 4 chunks: {page}");

    // The cut PATCH was resumed: a HEAD, then PATCHes up to the full length, each at the
    // offset the server confirmed.
    let requests = result["requests"].as_array().expect("requests");
    let size = std::fs::metadata(&mesh).unwrap().len();
    assert_eq!(result["tusClient"], true, "the page did not load the vendored tus-js-client: {result}");
    assert_eq!(result["cutPatches"], 1, "the harness should have cut one PATCH: {result}");
    assert!(
        requests.iter().any(|r| r["method"] == "HEAD" && r["status"] == 200),
        "no HEAD after the cut connection: {requests:?}"
    );
    let offsets: Vec<u64> = requests
        .iter()
        .filter(|r| r["method"] == "PATCH")
        .map(|r| {
            assert_eq!(r["status"], 204, "a PATCH failed: {requests:?}");
            r["offset"].as_str().and_then(|o| o.parse().ok()).expect("PATCH answers carry Upload-Offset")
        })
        .collect();
    assert_eq!(offsets.last(), Some(&size), "the upload did not end at the file size: {offsets:?}");
    assert!(offsets.windows(2).all(|w| w[0] < w[1]), "offsets: {offsets:?}");

    // What the API lists is what the page listed and what the link opened.
    let scenes: Value = rt
        .block_on(async { reqwest::get(format!("{base}/api/scenes")).await?.json().await })
        .expect("GET /api/scenes");
    let scenes = scenes.as_array().expect("a JSON array");
    assert_eq!(scenes.len(), 1, "one upload, one scene: {scenes:?}");
    let scene = &scenes[0];
    let (mesh_data, _) = voxstream::pipeline::read::read_mesh(&mesh).expect("read koala.obj");
    assert_eq!(scene["id"], "koala");
    assert_eq!(scene["triangles"].as_u64(), Some(mesh_data.triangles.len() as u64), "{scene}");
    assert_eq!(scene["resolution"], 64, "the server default applies: {scene}");
    assert!(scene["voxels"].as_u64().unwrap_or(0) > 0 && scene["build_seconds"].is_number(), "{scene}");
    assert_eq!(page["link"], "index.html?scene=koala");
    let rows = page["rows"].as_array().expect("rows");
    assert_eq!(rows.len(), 1, "{rows:?}");
    assert_eq!(rows[0]["id"], "koala");
    let cells: Vec<&str> = rows[0]["cells"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
    let count = |n: u64| {
        let s = n.to_string();
        let mut out = String::new();
        for (i, ch) in s.chars().enumerate() {
            if i > 0 && (s.len() - i).is_multiple_of(3) {
                out.push(',');
            }
            out.push(ch);
        }
        out
    };
    assert_eq!(cells[2], count(scene["triangles"].as_u64().unwrap()), "triangles cell: {cells:?}");
    assert_eq!(cells[3], count(scene["voxels"].as_u64().unwrap()), "voxels cell: {cells:?}");
    assert_eq!(rows[0]["thumbnail"]["width"], 256, "thumbnail in the list: {}", rows[0]);
    let viewer = &result["viewer"];
    assert!(viewer["url"].as_str().unwrap().ends_with("/index.html?scene=koala"), "{viewer}");
    assert!(viewer["stats"]["blocksDrawn"].as_u64().unwrap_or(0) > 0, "the viewer drew nothing: {viewer}");
    assert_eq!(viewer["uploadLink"], "upload.html", "the viewer links back to the upload page");

    // Refusals are sentences naming the problem.
    let errors = &result["errors"];
    let not_mesh = errors["notMesh"].as_str().unwrap_or_default();
    assert!(not_mesh.contains("notes.txt") && not_mesh.contains("not a mesh format"), "{errors}");
    let exists = errors["exists"].as_str().unwrap_or_default();
    assert!(exists.contains("\"koala\" exists") && exists.contains("replace"), "{errors}");

    // The thumbnail the page showed is a picture of the scene, not a blank.
    let png = rt
        .block_on(async {
            reqwest::get(format!("{base}/api/scenes/koala/thumbnail.png")).await?.bytes().await
        })
        .expect("GET thumbnail");
    let thumb = out.join("upload-thumbnail.png");
    std::fs::write(&thumb, &png).unwrap();
    let (w, h, rgb) = read_png_rgb(&thumb);
    let lit = rgb.chunks_exact(3).filter(|p| *p != &BACKGROUND_RGBA8[..3]).count();
    assert_eq!((w, h), (256, 256));
    assert!(lit > (w * h / 10) as usize && lit < (w * h) as usize, "thumbnail has {lit} drawn pixels");

    // The server cleaned up after the job: no upload left, the scene published.
    assert!(store.path().join("koala/manifest.json").is_file());
    let leftovers: Vec<_> = std::fs::read_dir(store.path().join(".uploads"))
        .map(|d| d.flatten().map(|e| e.file_name()).collect())
        .unwrap_or_default();
    assert!(leftovers.is_empty(), "uploads left behind: {leftovers:?}");
    let (shot_w, shot_h, _) = read_png_rgb(&out.join("upload.png"));
    assert!(shot_w >= 640 && shot_h >= 400, "upload page screenshot is {shot_w}x{shot_h}");
    println!(
        "upload page test: harness {:.1} s, whole test {:.1?}; artifacts in {}",
        result["elapsedMs"].as_f64().unwrap_or(0.0) / 1000.0,
        started.elapsed(),
        out.display()
    );
    server.abort();
}

/// `voxstream publish` writes a static site of packs and pages (no per-block files); plain static
/// file servers (no voxstream process) serve it and Chromium shows the scene with the same ready
/// marker and silhouette check, reading blocks as `packs/<hash>.vxp?r=<start>-<end>` with a
/// `Range` header: from tower-http's `ServeDir`, which answers 206, and from
/// `python3 -m http.server`, which ignores Range and answers 200 with the whole pack (the viewer
/// slices it). The URL has no `?scene=`: the published index.html names it. Each server's log
/// shows the range requests and no per-block URL. Negative control: the viewer with absolute
/// `/api/...` URLs, or without the meta tag, never gets ready here (there is no `/api/scenes`
/// list or `/blocks/` URL on a static host).
#[test]
fn static_publish_renders_in_chromium() {
    let root = workspace_root();
    require_harness(&root);
    let dir = tempfile::tempdir().expect("temp dir");
    let store = dir.path().join("store");
    let report = build_scene(&root.join("data/koala.obj"), &store, &BuildOptions::default())
        .expect("build_scene(data/koala.obj)");
    // Served from a sub-folder of the host: the viewer's URLs are relative to its page.
    let host_root = dir.path().join("www");
    let site = host_root.join("scans/koala");
    let viewer = if voxstream::http::web::has_embedded_viewer() {
        voxstream::publish::ViewerFiles::Embedded
    } else {
        panic!("the server embeds no viewer: run bash scripts/build-web.sh, then cargo test again")
    };
    let published = voxstream::publish::publish(&store, &report.id, &site, viewer).expect("publish");
    println!(
        "published {} files ({} packs for {} blocks, {} pages), {} bytes",
        published.files, published.packs, published.blocks, published.pages, published.bytes
    );
    let scene = site.join("api/scenes").join(&report.id);
    assert!(!scene.join("blocks").exists(), "per-block files were published");
    let packs = std::fs::read_dir(scene.join("packs")).expect("the site has packs").count();
    assert!(packs > 0 && packs as u64 == published.packs, "{packs} packs in the site");

    // tower-http's ServeDir honours Range: every pack GET must be a 206 of a `?r=` URL.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    // Each request: its URI, its Range header, the status answered.
    type RequestLog = Arc<Mutex<Vec<(String, Option<String>, u16)>>>;
    let seen: RequestLog = Arc::default();
    let log = seen.clone();
    let app = axum::Router::new().fallback_service(tower_http::services::ServeDir::new(&host_root)).layer(
        axum::middleware::from_fn(move |req: axum::extract::Request, next: axum::middleware::Next| {
            let log = log.clone();
            async move {
                let uri = req.uri().to_string();
                let range = req.headers().get("range").and_then(|v| v.to_str().ok()).map(str::to_string);
                let resp = next.run(req).await;
                log.lock().unwrap().push((uri, range, resp.status().as_u16()));
                resp
            }
        }),
    );
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).unwrap();
    let addr = listener.local_addr().unwrap();
    let server = rt.spawn(async move { axum::serve(listener, app).await });
    let url = format!("http://{addr}/scans/koala/");
    render_and_check(&url, &artifacts_dir().join("publish-206"), &report.scene_dir, false);
    server.abort();
    let seen = std::mem::take(&mut *seen.lock().unwrap());
    let pack_gets: Vec<_> = seen.iter().filter(|(u, _, _)| u.contains("/packs/")).collect();
    assert!(!pack_gets.is_empty(), "the viewer read no pack: {seen:?}");
    for (uri, range, status) in &pack_gets {
        let query = uri.split_once("?r=").map(|(_, q)| q.to_string());
        assert!(query.is_some(), "a pack GET without its range in the URL: {uri}");
        assert_eq!(range.as_deref(), query.map(|q| format!("bytes={q}")).as_deref(), "{uri}");
        assert_eq!(*status, 206, "{uri}");
    }
    assert!(seen.iter().all(|(u, _, _)| !u.contains("/blocks/")), "per-block URLs asked for: {seen:?}");
    println!("ServeDir: {} range requests answered 206", pack_gets.len());

    // python3 -m http.server ignores Range: 200 with the whole pack.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let log_path = dir.path().join("http.server.log");
    let mut server = Command::new("python3")
        .args(["-m", "http.server", "--bind", "127.0.0.1", &port.to_string(), "--directory"])
        .arg(&host_root)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log_path).unwrap())
        .spawn()
        .expect("python3 -m http.server (python3 is on every Debian machine)");
    let deadline = Instant::now() + Duration::from_secs(20);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "python3 -m http.server did not listen on {port}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let url = format!("http://127.0.0.1:{port}/scans/koala/");
    let result = std::panic::catch_unwind(|| {
        render_and_check(&url, &artifacts_dir().join("publish"), &report.scene_dir, false)
    });
    let _ = server.kill();
    let _ = server.wait();
    if let Err(e) = result {
        std::panic::resume_unwind(e);
    }
    let log = std::fs::read_to_string(&log_path).unwrap();
    let ranged = log
        .lines()
        .filter(|l| l.contains("/packs/") && l.contains(".vxp?r=") && l.contains("\" 200"))
        .count();
    assert!(ranged > 0, "no pack range URL answered 200 in the server's log:\n{log}");
    assert!(!log.contains("/blocks/"), "per-block URLs asked for:\n{log}");
    println!("python3 -m http.server: {ranged} pack range URLs answered 200 (whole pack, sliced)");
}

/// Failure handling in the browser: every level-0 block the page asks for fails for good, half
/// with HTTP 500 and half with corrupt bytes (200, garbage body). The page must report them in
/// its stats, draw their parents instead, and still set the ready marker (the harness waits for
/// it). Control: the server counts the level-0 requests it spoiled, so the faults were exercised
/// (the undamaged test above draws level-0 blocks for the same view).
#[test]
fn browser_failed_blocks_are_reported_and_drawn_as_parents() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let root = workspace_root();
    let web = root.join("viewer-wasm/dist");
    require(&web.join("index.html"), "build the viewer bundle first: bash scripts/build-web.sh");
    let script = root.join("tests/browser/e2e.mjs");
    let store = tempfile::tempdir().expect("temp store");
    let report = build_scene(&root.join("data/koala.obj"), store.path(), &BuildOptions::default())
        .expect("build_scene(data/koala.obj)");
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let state = AppState::load(store.path(), Some(&web)).expect("AppState::load");
    let spoiled = Arc::new(AtomicUsize::new(0));
    let counter = spoiled.clone();
    let app = router(state).layer(axum::middleware::from_fn(
        move |req: axum::extract::Request, next: axum::middleware::Next| {
            let counter = counter.clone();
            async move {
                use axum::response::IntoResponse;
                let path = req.uri().path().to_string();
                let level0 = path.rsplit_once("/blocks/0-").map(|(_, rest)| rest.to_string());
                match level0 {
                    Some(rest) => {
                        counter.fetch_add(1, Ordering::SeqCst);
                        let x: u32 = rest.split('-').next().and_then(|x| x.parse().ok()).unwrap_or(0);
                        if x.is_multiple_of(2) {
                            axum::http::StatusCode::INTERNAL_SERVER_ERROR.into_response()
                        } else {
                            (axum::http::StatusCode::OK, vec![0x5a_u8; 300]).into_response()
                        }
                    }
                    None => next.run(req).await,
                }
            }
        },
    ));
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).expect("bind 127.0.0.1:0");
    let addr = listener.local_addr().unwrap();
    let server = rt.spawn(async move { axum::serve(listener, app).await });
    let url = format!("http://{addr}/?scene={}", report.id);
    let out = artifacts_dir().join("failure");
    std::fs::create_dir_all(&out).unwrap();
    let mut cmd = Command::new("node");
    cmd.arg(&script).arg(&url).arg(&out).current_dir(&root);
    let (ok, log) = run_with_timeout(cmd, HARNESS_TIMEOUT);
    assert!(ok, "the page never became ready with failing blocks:\n{log}");
    let result: Value = serde_json::from_slice(&std::fs::read(out.join("browser.json")).unwrap()).unwrap();
    let stats = &result["stats"];
    let spoiled = spoiled.load(Ordering::SeqCst) as u64;
    println!("spoiled {spoiled} level-0 requests; stats {stats}");
    assert!(spoiled > 0, "the view asked for no level-0 block: the faults were never exercised");
    // Requests aborted because the view changed (occlusion feedback) are not failures.
    let failed = stats["blocksFailed"].as_u64().unwrap_or(0);
    assert!(failed > 0 && failed <= spoiled, "spoiled blocks are reported as failed: {stats}");
    // Control for the koala test's pass times: this page did not ask for them.
    check_gpu_timing(&out.join("browser.json"), false);
    let drawn: Vec<BlockKey> = result["view"]["drawnBlocks"]
        .as_array()
        .expect("drawnBlocks")
        .iter()
        .map(|k| k.as_str().unwrap().parse().unwrap())
        .collect();
    assert!(!drawn.is_empty(), "nothing drawn");
    assert!(drawn.iter().all(|k| k.level > 0), "a failed level-0 block is drawn: {drawn:?}");
    assert!(drawn.iter().any(|k| k.level == 1), "no parent stands in for the failed blocks: {drawn:?}");
    server.abort();
}

/// `voxstream ao-bench --browser`'s driver (server/src/reference/chromium.rs and
/// tests/browser/ao-bench.mjs): the page opens at the camera asked for
/// (`?camera=`, source units), each point's settings reach the renderer
/// (`set({aoSettings})`: the half-resolution accumulated default runs the
/// upsample and temporal passes, the full-resolution single frame neither), and
/// every pass time is a positive GPU time.
#[test]
fn ao_bench_times_each_point_in_chromium() {
    use voxstream::reference::bench::{Point, camera_around};
    use voxstream::reference::chromium::{BrowserView, time_in_chromium};
    use voxstream_viewer::ao::AoSettings;
    let root = workspace_root();
    require_harness(&root);
    let store = tempfile::tempdir().expect("temp store");
    let mesh_path = root.join("data/koala.obj");
    let report = build_scene(
        &mesh_path,
        store.path(),
        &BuildOptions { resolution: Resolution::Explicit(256), ..Default::default() },
    )
    .expect("build_scene(data/koala.obj)");
    let mesh = voxstream::pipeline::read::read_mesh(&mesh_path).expect("read koala").0;
    let camera = camera_around(&mesh, false);
    let full =
        AoSettings { trace_downscale: 1, interleave: false, temporal_frames: 1, ..AoSettings::default() };
    let points = vec![
        Point { label: "default".into(), settings: AoSettings::default(), scale: 1, frames: 2 },
        Point { label: "full res".into(), settings: full, scale: 1, frames: 1 },
    ];
    let views = [BrowserView { name: "koala".into(), scene_dir: report.scene_dir.clone(), camera }];
    let (adapter, rows) =
        time_in_chromium(&views, &points, 96, 64, 2, &root.join("tests/browser/ao-bench.mjs"), None)
            .expect("the Chromium timing run");
    println!("{adapter}: {rows:#?}");
    assert_eq!(rows.len(), 2, "{rows:?}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report.scene_dir.join("manifest.json")).unwrap()).unwrap();
    let origin = json_f32_array::<3>(&manifest["grid"]["origin"], "grid.origin");
    let voxel = manifest["grid"]["voxel_size"].as_f64().unwrap();
    let eye: [f64; 3] = std::array::from_fn(|a| (camera.eye[a] - origin[a] as f64) / voxel);
    let has = |r: &voxstream::reference::chromium::ChromiumTimes, pass: &str| {
        r.passes_ms.iter().any(|p| p.pass == pass)
    };
    for r in &rows {
        assert_eq!((r.width, r.height), (96, 64), "{r:?}");
        let off = (0..3).map(|a| (r.eye_grid[a] - eye[a]).powi(2)).sum::<f64>().sqrt();
        assert!(off < 0.5, "eye {:?} (grid units) vs {eye:?} asked", r.eye_grid);
        assert!(r.ao_ms > 0.0 && r.frame_no_ao_ms > 0.0, "{r:?}");
        assert!(r.passes_ms.iter().all(|p| p.ms.is_finite() && p.ms >= 0.0), "{r:?}");
        assert!(has(r, "cs_trace") && has(r, "voxels"), "{r:?}");
        assert!(r.ao_over_frame.is_some_and(|x| x.is_finite() && x > 0.0), "{r:?}");
    }
    let (default, full) = (&rows[0], &rows[1]);
    assert!(
        has(default, "cs_upsample") && has(default, "cs_retrace") && has(default, "cs_temporal"),
        "{default:?}"
    );
    assert!(
        !has(full, "cs_upsample") && !has(full, "cs_retrace") && !has(full, "cs_temporal"),
        "the full-res point's settings were not applied: {full:?}"
    );
}
