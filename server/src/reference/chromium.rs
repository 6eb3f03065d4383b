//! The AO benchmark's browser times (`voxstream ao-bench --browser`): every
//! view and point of the sweep drawn by the real viewer in headless Chromium
//! (SwiftShader's CPU WebGPU), each pass timed by timestamp queries.
//!
//! The store the views were built into is served in-process (the viewer
//! embedded in this binary, or `--web`), and `tests/browser/ao-bench.mjs`
//! drives the page: `?scene=…&camera=…&gpu-timing=1`, then
//! `window.voxstream.set({aoSettings, ao})` per point and
//! `stats().gpuTimed` per frame. The ratio is the native one: the AO passes
//! (trace, upsample, temporal) of the frame with AO over every timed pass of
//! the frame without.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, bail, ensure};
use serde::{Deserialize, Serialize};

use super::bench::Point;
use crate::render::{CameraSpec, PassMs};

/// A built view the page opens.
pub struct BrowserView {
    pub name: String,
    pub scene_dir: PathBuf,
    pub camera: CameraSpec,
}

/// One view and point as Chromium drew it (a row of the script's output).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChromiumTimes {
    pub view: String,
    pub point: String,
    pub width: u32,
    pub height: u32,
    /// The eye the page reported, in grid units (the camera asked for, converted by the page).
    pub eye_grid: [f64; 3],
    /// GPU ms of the AO passes in the frame with AO (medians per pass, summed).
    pub ao_ms: f64,
    /// GPU ms of every timed pass of the frame without AO.
    pub frame_no_ao_ms: f64,
    /// ao_ms / frame_no_ao_ms.
    pub ao_over_frame: Option<f64>,
    /// Wall ms from a frame's encoding until the GPU finished it, with AO and without.
    pub wall_ms: Option<f64>,
    pub wall_no_ao_ms: Option<f64>,
    /// Each pass's median GPU ms in the frame with AO.
    pub passes_ms: Vec<PassMs>,
}

/// What the script writes (its rows also carry `passes_no_ao_ms`, not kept).
#[derive(Deserialize)]
struct ScriptOutput {
    adapter: Option<String>,
    rows: Vec<ChromiumTimes>,
}

/// Chromium's times for every view and point, and the adapter it named.
/// Needs node and the harness's packages (`scripts/setup.sh`) and a Chromium.
pub fn time_in_chromium(
    views: &[BrowserView],
    points: &[Point],
    width: u32,
    height: u32,
    runs: usize,
    script: &Path,
    web_dir: Option<&Path>,
) -> anyhow::Result<(String, Vec<ChromiumTimes>)> {
    ensure!(
        script.is_file(),
        "{} not found (run from the repository root, or pass --browser-script)",
        script.display()
    );
    ensure!(
        web_dir.is_some() || crate::http::web::has_embedded_viewer(),
        "this binary embeds no viewer: run bash scripts/build-web.sh and rebuild, or pass --web DIR"
    );
    let Some(store) = views.first().and_then(|v| v.scene_dir.parent()) else {
        return Ok((String::new(), Vec::new()));
    };
    let mut spec_views = Vec::new();
    for v in views {
        ensure!(v.scene_dir.parent() == Some(store), "views built into different stores");
        let scene = v.scene_dir.file_name().context("scene directory without a name")?.to_string_lossy();
        let c = &v.camera;
        let camera = [c.eye[0], c.eye[1], c.eye[2], c.target[0], c.target[1], c.target[2], c.fov_y_deg];
        spec_views.push(serde_json::json!({ "name": v.name, "scene": scene, "camera": camera }));
    }

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let state = crate::http::AppState::load(store, web_dir)?;
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
    let addr = listener.local_addr()?;
    let server = rt.spawn(async move { axum::serve(listener, crate::http::router(state)).await });

    let work = tempfile::tempdir()?;
    let (spec_path, out_path) = (work.path().join("spec.json"), work.path().join("out.json"));
    let spec = serde_json::json!({
        "base": format!("http://{addr}/"),
        "width": width,
        "height": height,
        "runs": runs,
        "views": spec_views,
        "points": points,
    });
    std::fs::write(&spec_path, serde_json::to_vec_pretty(&spec)?)?;
    let status = Command::new("node")
        .arg(script)
        .arg(&spec_path)
        .arg(&out_path)
        // Its log goes with ours to stderr: stdout is the bench's JSON.
        .stdout(std::io::stderr())
        .status()
        .context("running node (install it with scripts/setup.sh)")?;
    server.abort();
    if !status.success() {
        bail!("{} failed ({status})", script.display());
    }
    let out: ScriptOutput = serde_json::from_slice(&std::fs::read(&out_path)?)
        .with_context(|| format!("reading {}", out_path.display()))?;
    Ok((out.adapter.unwrap_or_default(), out.rows))
}
