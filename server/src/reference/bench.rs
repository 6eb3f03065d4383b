//! `voxstream ao-bench`: run time against error of the cone-traced AO over a
//! sweep of settings, on the analytic scenes (generated in code) and the named
//! real views present in the data directory. Each view is built once, its
//! reference (BVH, cosine-weighted rays at the render's own points) computed
//! once per image size, and every setting rendered with timing (median of
//! three frames with AO, three without, on whatever Vulkan adapter is there).
//! Writes `ao-benchmark.md` and `ao-pareto.png` (mean frame time against mean
//! RMSE over the views, Pareto front joined) and prints the JSON.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;
use voxstream_viewer::ao::AoSettings;

use crate::reference::analytic::{self, exact_error, exact_image};
use crate::reference::metrics::compare;
use crate::reference::{AoParams, MeshBvh, reference_at};
use crate::render::{CameraSpec, RenderRequest, render_view};

#[derive(Debug, Clone, clap::Args)]
pub struct AoBenchArgs {
    /// Where ao-benchmark.md and ao-pareto.png go.
    #[arg(long, default_value = "docs")]
    pub out_dir: PathBuf,
    /// Reduced image size (the sweep); one point is also rendered at twice this.
    #[arg(long, default_value_t = 96)]
    pub width: u32,
    #[arg(long, default_value_t = 64)]
    pub height: u32,
    /// Reference rays per pixel.
    #[arg(long, default_value_t = 512)]
    pub rays: u32,
    /// Where the real meshes are (views whose mesh is absent are skipped and listed).
    #[arg(long, default_value = "../shared/data")]
    pub data_dir: PathBuf,
    /// Scene resolution the views are built at.
    #[arg(long, default_value_t = 256)]
    pub resolution: u32,
    /// Only these views (repeatable; default: every view present).
    #[arg(long = "view")]
    pub views: Vec<String>,
    /// Which settings to sweep: the cone tracer's (cone count, step,
    /// aperture, skipping, image size) or reduced-resolution tracing and
    /// temporal accumulation (`sparse-temporal`).
    #[arg(long, value_enum, default_value_t = Sweep::Cones)]
    pub sweep: Sweep,
    /// Frame counts N of the `sparse-temporal` sweep's accumulated points
    /// (comma-separated; default: the viewer's own N, and 16). The other
    /// sweeps' accumulated points take the first (default: the viewer's N).
    #[arg(long, value_delimiter = ',')]
    pub frames: Vec<u32>,
    /// Also write each view's per-pixel arrays under DIR/<view>/<point index>/:
    /// ao.f32, reference.f32, reference_variance.f32 (little-endian f32),
    /// position.f64 (source units, xyz), normal.f32 (xyz) and
    /// info.json (size, grid origin, voxel size, R), for error maps.
    #[arg(long)]
    pub dump_dir: Option<PathBuf>,
    /// Time every point without a reference (no error columns): for timing on
    /// a GPU at full size, e.g. `--time-only --width 1920 --height 1080`.
    /// Writes ao-timing.md instead of ao-benchmark.md and the plot.
    #[arg(long)]
    pub time_only: bool,
    /// Timed frames per point, with AO and without (medians).
    #[arg(long, default_value_t = 3)]
    pub timing_runs: usize,
    /// Keep each view's built scene and camera under DIR and reuse them on the
    /// next run (which then needs neither the mesh nor a build, only with
    /// --time-only: the reference needs the mesh).
    #[arg(long, value_name = "DIR")]
    pub scene_cache: Option<PathBuf>,
    /// Also time every view and point in headless Chromium (SwiftShader
    /// WebGPU, timestamp queries): the viewer served from this binary draws
    /// each, driven by --browser-script. Needs node, the harness's packages
    /// and Chromium (scripts/setup.sh).
    #[arg(long)]
    pub browser: bool,
    #[arg(long, default_value = "tests/browser/ao-bench.mjs")]
    pub browser_script: PathBuf,
    /// With --browser: the viewer's files (default: the one built into this binary).
    #[arg(long, value_name = "DIR")]
    pub web: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Sweep {
    Cones,
    SparseTemporal,
    /// The occupancy structures side by side: the volume and the clipmap at
    /// the default setting (1/2 resolution, bilateral, jittered, interleaved,
    /// N frames) and at the cone sweep's full-resolution single frame.
    Structure,
    /// Both AO modes: cone tracing (the default setting, N frames, and the
    /// full-resolution single frame) and the precomputed AO field (full
    /// resolution, one frame: the field has no noise to accumulate).
    Mode,
    /// The default setting alone (clipmap, N frames): the quickest before/after.
    Default,
}

/// One setting of the sweep.
#[derive(Debug, Clone, Serialize)]
pub struct Point {
    pub label: String,
    pub settings: AoSettings,
    /// Image scale relative to --width/--height.
    pub scale: u32,
    /// Frames of the still view accumulated (1: one frame).
    pub frames: u32,
}

/// N of the accumulated points of the sweeps that have one: the first of
/// `--frames`, else the viewer's own ([`AoSettings::default`]).
fn accumulated_frames(frames: &[u32]) -> u32 {
    frames
        .first()
        .copied()
        .unwrap_or(AoSettings::default().temporal_frames)
        .clamp(1, voxstream_viewer::ao::MAX_TEMPORAL_FRAMES)
}

/// The viewer's default setting, its N frames accumulated (see [`accumulated_frames`]).
fn default_point(frames: &[u32]) -> Point {
    let n = accumulated_frames(frames);
    Point { label: format!("default ({n} frames)"), settings: AoSettings::default(), scale: 1, frames: n }
}

/// Full or reduced resolution, one frame or `frames` accumulated (default:
/// the viewer's N and 16), at the default cone setting, with three
/// comparisons: accumulation without jitter, the bilateral upsample without
/// re-tracing the pixels it cannot match, and plain bilinear upsampling.
fn sparse_temporal_sweep(frames: &[u32]) -> Vec<Point> {
    use voxstream_viewer::ao::Upsample;
    let default_frames = [AoSettings::default().temporal_frames, 16];
    let frames = if frames.is_empty() { &default_frames[..] } else { frames };
    let d = AoSettings {
        trace_downscale: 1,
        jitter: true,
        interleave: false,
        temporal_frames: 1,
        ..AoSettings::default()
    };
    let point =
        |label: String, settings: AoSettings, frames: u32| Point { label, settings, scale: 1, frames };
    let counts: Vec<u32> =
        frames.iter().map(|&n| n.clamp(2, voxstream_viewer::ao::MAX_TEMPORAL_FRAMES)).collect();
    let mut points = vec![point("full res, 1 frame".into(), d, 1)];
    for &n in &counts {
        points.push(point(format!("full res, {n} frames jittered"), d, n));
    }
    if let Some(&n) = counts.last() {
        points.push(point(format!("full res, {n} frames, no jitter"), AoSettings { jitter: false, ..d }, n));
    }
    for f in [2, 4] {
        let s = AoSettings { trace_downscale: f, ..d };
        points.push(point(format!("1/{f} res + bilateral, 1 frame"), s, 1));
        for &n in &counts {
            points.push(point(format!("1/{f} res + bilateral, {n} frames jittered"), s, n));
        }
    }
    let interleaved = AoSettings { trace_downscale: 2, interleave: true, ..d };
    points.push(point("1/2 res + bilateral, interleaved, 1 frame".into(), interleaved, 1));
    for &n in &counts {
        points.push(point(format!("1/2 res + bilateral, interleaved, {n} frames jittered"), interleaved, n));
    }
    let interleaved_full = AoSettings { interleave: true, ..d };
    points.push(point("full res, interleaved, 1 frame".into(), interleaved_full, 1));
    points.push(point(
        format!("1/2 res + bilateral without re-tracing, interleaved, {} frames jittered", counts[0]),
        AoSettings { upsample: Upsample::BilateralOnly, ..interleaved },
        counts[0],
    ));
    points.push(point(
        "1/2 res + bilinear, 1 frame".into(),
        AoSettings { trace_downscale: 2, upsample: Upsample::Bilinear, ..d },
        1,
    ));
    points
}

fn structure_sweep(frames: &[u32]) -> Vec<Point> {
    use voxstream_viewer::ao::AoStructure;
    let n = accumulated_frames(frames);
    let mut points = Vec::new();
    for structure in [AoStructure::Volume, AoStructure::Clipmap] {
        let name = structure.name();
        points.push(Point {
            label: format!("{name}, default ({n} frames)"),
            settings: AoSettings { structure, ..AoSettings::default() },
            scale: 1,
            frames: n,
        });
        points.push(Point {
            label: format!("{name}, 6 cones, full res, 1 frame"),
            settings: AoSettings {
                structure,
                trace_downscale: 1,
                interleave: false,
                temporal_frames: 1,
                ..AoSettings::default()
            },
            scale: 1,
            frames: 1,
        });
    }
    points
}

fn mode_sweep(frames: &[u32]) -> Vec<Point> {
    use voxstream_viewer::ao::AoMode;
    let n = accumulated_frames(frames);
    let full =
        AoSettings { trace_downscale: 1, interleave: false, temporal_frames: 1, ..AoSettings::default() };
    vec![
        Point {
            label: format!("cone, default ({n} frames)"),
            settings: AoSettings::default(),
            scale: 1,
            frames: n,
        },
        Point { label: "cone, 6 cones, full res, 1 frame".into(), settings: full, scale: 1, frames: 1 },
        Point {
            label: "field, full res, 1 frame".into(),
            settings: AoSettings { mode: AoMode::Field, ..full },
            scale: 1,
            frames: 1,
        },
    ]
}

/// The cone tracer alone (full resolution, one frame, the fixed cone set) at
/// each cone count, step, aperture and with skipping, after the viewer's
/// default setting (`frames` accumulated) for where it sits among them.
fn sweep(frames: &[u32]) -> Vec<Point> {
    let d = AoSettings { trace_downscale: 1, interleave: false, temporal_frames: 1, ..AoSettings::default() };
    let mut points = vec![default_point(frames)];
    for cones in [3, 5, 6, 8, 16] {
        points.push(Point {
            label: format!("{cones} cones"),
            settings: AoSettings { cones, ..d },
            scale: 1,
            frames: 1,
        });
    }
    for (cones, step) in [(6, 0.5), (16, 0.5), (6, 1.0)] {
        points.push(Point {
            label: format!("{cones} cones, step {step}"),
            settings: AoSettings { cones, step, ..d },
            scale: 1,
            frames: 1,
        });
    }
    points.push(Point {
        label: "6 cones, aperture x1.5".into(),
        settings: AoSettings { aperture_deg: Some(d.aperture() * 1.5), ..d },
        scale: 1,
        frames: 1,
    });
    points.push(Point {
        label: "6 cones, empty skip".into(),
        settings: AoSettings { empty_skip: true, ..d },
        scale: 1,
        frames: 1,
    });
    points.push(Point { label: "6 cones, 2x resolution".into(), settings: d, scale: 2, frames: 1 });
    points
}

#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub view: String,
    pub point: String,
    pub width: u32,
    pub height: u32,
    /// Frames of the still view accumulated.
    pub frames: u32,
    pub frame_ms: f64,
    pub frame_no_ao_ms: f64,
    pub ao_over_frame: f64,
    pub rmse: f64,
    pub bias: f64,
    pub ssim: f64,
    pub equal_error_rays: Option<f64>,
    /// Analytic views: mean |V − exact|.
    pub exact_mae: Option<f64>,
    /// Against the ray-traced view of the mesh (voxelization included).
    pub primary_rmse: f64,
    pub primary_bias: f64,
    /// GPU time of the AO passes and of the frame without AO (timestamp queries; `None` without them).
    pub gpu_ao_ms: Option<f64>,
    pub gpu_frame_no_ao_ms: Option<f64>,
    /// Each pass's GPU time in the frame with AO.
    pub gpu_passes_ms: Option<Vec<crate::render::PassMs>>,
    /// The same view and point drawn by the viewer in Chromium (`--browser`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chromium: Option<super::chromium::ChromiumTimes>,
}

impl Row {
    /// GPU AO ÷ GPU frame without AO (timestamp queries), natively.
    fn gpu_ratio(&self) -> Option<f64> {
        self.gpu_ao_ms.zip(self.gpu_frame_no_ao_ms).map(|(a, f)| a / f)
    }

    /// The same in Chromium.
    fn chromium_ratio(&self) -> Option<f64> {
        self.chromium.as_ref().and_then(|c| c.ao_over_frame)
    }
}

/// One image scale's reference: scale, the points, V, one-ray variance, exact V
/// (analytic views) and V of the ray-traced view.
struct ScaleReference {
    scale: u32,
    positions: Vec<[f64; 3]>,
    v: Vec<f32>,
    variance: Vec<f32>,
    exact: Option<Vec<f32>>,
    primary: Vec<f32>,
}

struct View {
    name: String,
    mesh: PathBuf,
    camera: CameraSpec,
    shapes: Option<Vec<analytic::Shape>>,
}

/// A view's built scene kept by `--scene-cache`: `<dir>/<view>@<resolution>.json`
/// names the scene's directory (relative to `<dir>`) and the camera.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
struct CachedScene {
    scene: String,
    camera: CameraSpec,
}

impl CachedScene {
    fn path(dir: &Path, view: &str, resolution: u32) -> PathBuf {
        dir.join(format!("{view}@{resolution}.json"))
    }

    /// The cached scene, if its record parses and its manifest is there.
    fn load(dir: &Path, view: &str, resolution: u32) -> Option<Self> {
        let c: CachedScene =
            serde_json::from_slice(&std::fs::read(Self::path(dir, view, resolution)).ok()?).ok()?;
        dir.join(&c.scene).join("manifest.json").is_file().then_some(c)
    }
}

/// The view's scene directory: from the cache, or built (into the cache, when there is one).
fn scene_for(view: &View, args: &AoBenchArgs, scratch: &Path) -> anyhow::Result<PathBuf> {
    if let Some((dir, c)) =
        args.scene_cache.as_ref().and_then(|d| Some((d, CachedScene::load(d, &view.name, args.resolution)?)))
    {
        return Ok(dir.join(c.scene));
    }
    let store = args.scene_cache.clone().unwrap_or_else(|| scratch.to_path_buf());
    let name = view.name.replace('_', "-");
    let options = crate::pipeline::BuildOptions {
        resolution: crate::pipeline::Resolution::Explicit(args.resolution),
        // A cache holds a view at several resolutions, each its own scene.
        name: Some(if args.scene_cache.is_some() { format!("{name}-{}", args.resolution) } else { name }),
        // Both modes are benchmarked from one build; cone tracing ignores the field.
        ao_field: Some(Default::default()),
        ..Default::default()
    };
    let scene_dir = crate::pipeline::build_scene(&view.mesh, &store, &options)
        .with_context(|| format!("building {}", view.mesh.display()))?
        .scene_dir;
    if let Some(dir) = &args.scene_cache {
        let scene = scene_dir.strip_prefix(dir).unwrap_or(&scene_dir).to_string_lossy().into_owned();
        let record = serde_json::to_vec_pretty(&CachedScene { scene, camera: view.camera })?;
        let path = CachedScene::path(dir, &view.name, args.resolution);
        std::fs::write(&path, record).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(scene_dir)
}

impl Row {
    /// A render's size and times; its error columns NaN (`--time-only`, or
    /// filled in by the caller against the reference).
    fn timed(view: &View, point: &Point, out: &crate::render::RenderOutput) -> Self {
        let t = &out.info.timings;
        Row {
            view: view.name.clone(),
            point: point.label.clone(),
            width: out.info.width,
            height: out.info.height,
            frames: point.frames,
            frame_ms: t.frame_ms.unwrap_or(f64::NAN),
            frame_no_ao_ms: t.frame_no_ao_ms.unwrap_or(f64::NAN),
            ao_over_frame: t.ao_over_frame.unwrap_or(f64::NAN),
            rmse: f64::NAN,
            bias: f64::NAN,
            ssim: f64::NAN,
            equal_error_rays: None,
            exact_mae: None,
            primary_rmse: f64::NAN,
            primary_bias: f64::NAN,
            gpu_ao_ms: t.gpu_ao_ms,
            gpu_frame_no_ao_ms: t.gpu_frame_no_ao_ms,
            gpu_passes_ms: t.gpu_passes_ms.clone(),
            chromium: None,
        }
    }
}

/// `--time-only`: ao-timing.md (every view and point: wall-clock frames, and
/// each pass's GPU time where the adapter has timestamps) and the JSON.
fn write_timing(
    args: &AoBenchArgs,
    rows: &[Row],
    summary: &[Summary],
    skipped: &[String],
    browser: Option<&str>,
) -> anyhow::Result<()> {
    use std::fmt::Write;
    let adapter = voxstream_viewer::offscreen::Gpu::shared().map(|g| g.adapter_name()).unwrap_or_default();
    let mut s = String::new();
    writeln!(s, "# AO pass timing on {adapter}\n")?;
    writeln!(
        s,
        "Written by `voxstream ao-bench --time-only` (server/src/reference/bench.rs): scenes built at {}³, images {}×{} (2× for a `2x resolution` point), {} timed frames per point with AO and as many without, medians. `frame` is wall time from encoding to GPU idle (CPU work included); `GPU` columns are timestamp queries around each pass. GPU AO = trace + upsample + temporal passes; `GPU AO / frame` divides it by the GPU time of the frame without AO (G-buffer draw, composite, depth reduce).\n",
        args.resolution, args.width, args.height, args.timing_runs
    )?;
    if !skipped.is_empty() {
        writeln!(s, "Views skipped: {}.\n", skipped.join("; "))?;
    }
    if let Some(browser) = browser {
        writeln!(s, "{}\n", chromium_note(browser))?;
    }
    writeln!(s, "## Means over the views\n")?;
    writeln!(s, "| setting | views | GPU AO / frame | Chromium AO / frame |")?;
    writeln!(s, "|---|---:|---:|---:|")?;
    for x in summary {
        writeln!(
            s,
            "| {} | {} | {} | {} |",
            x.point,
            x.views,
            fmt_opt(x.mean_gpu_ao_over_frame, 2),
            fmt_opt(x.mean_chromium_ao_over_frame, 2)
        )?;
    }
    writeln!(s, "\n## Every view and setting\n")?;
    writeln!(
        s,
        "| view | setting | size | frame ms | no-AO frame ms | GPU AO ms | GPU frame without AO ms | GPU AO / frame | Chromium GPU AO ms | Chromium GPU frame without AO ms | Chromium AO / frame | GPU passes with AO (ms) |"
    )?;
    writeln!(s, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")?;
    for r in rows {
        let passes = r.gpu_passes_ms.as_ref().map_or("—".to_string(), |p| {
            p.iter().map(|x| format!("{} {:.3}", x.pass, x.ms)).collect::<Vec<_>>().join(", ")
        });
        writeln!(
            s,
            "| {} | {} | {}×{} | {:.2} | {:.2} | {} | {} | {} | {} | {} | {} | {} |",
            r.view,
            r.point,
            r.width,
            r.height,
            r.frame_ms,
            r.frame_no_ao_ms,
            fmt_opt(r.gpu_ao_ms, 3),
            fmt_opt(r.gpu_frame_no_ao_ms, 3),
            fmt_opt(r.gpu_ratio(), 2),
            fmt_opt(r.chromium.as_ref().map(|c| c.ao_ms), 3),
            fmt_opt(r.chromium.as_ref().map(|c| c.frame_no_ao_ms), 3),
            fmt_opt(r.chromium_ratio(), 2),
            passes
        )?;
    }
    let path = args.out_dir.join("ao-timing.md");
    std::fs::write(&path, s).with_context(|| format!("writing {}", path.display()))?;
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "adapter": adapter,
            "resolution": args.resolution,
            "width": args.width,
            "height": args.height,
            "timing_runs": args.timing_runs,
            "browser": browser,
            "skipped": skipped,
            "rows": rows,
        }))?
    );
    Ok(())
}

/// What the Chromium columns are.
fn chromium_note(browser: &str) -> String {
    format!(
        "Chromium columns (`--browser`): the viewer itself in headless {browser} (SwiftShader: WebGPU on the CPU), the same view, size and setting, each pass timed by WebGPU timestamp queries (`?gpu-timing=1`); medians of the same number of frames. `Chromium AO / frame` = the AO passes (trace, upsample, temporal) ÷ every timed pass of the frame without AO, as natively. The viewer draws what its own traversal picks (occlusion culling on), which may differ from the native render's blocks."
    )
}

/// Writes one render's per-pixel arrays beside the reference's (`--dump-dir`).
fn dump_pixels(
    dir: &std::path::Path,
    out: &crate::render::RenderOutput,
    reference: &[f32],
    variance: &[f32],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let f32s = |v: &mut dyn Iterator<Item = f32>| v.flat_map(f32::to_le_bytes).collect::<Vec<u8>>();
    std::fs::write(dir.join("ao.f32"), f32s(&mut out.ao.iter().copied()))?;
    std::fs::write(dir.join("reference.f32"), f32s(&mut reference.iter().copied()))?;
    std::fs::write(dir.join("reference_variance.f32"), f32s(&mut variance.iter().copied()))?;
    std::fs::write(dir.join("normal.f32"), f32s(&mut out.normal.iter().flatten().copied()))?;
    let pos: Vec<u8> = out.position.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(dir.join("position.f64"), pos)?;
    let info = serde_json::json!({
        "width": out.info.width,
        "height": out.info.height,
        "grid_origin": out.info.grid_origin,
        "voxel_size": out.info.voxel_size,
        "grid_resolution": out.info.grid_resolution,
        "max_distance": out.info.ao.max_distance,
        "levels_drawn": out.info.levels_drawn,
    });
    std::fs::write(dir.join("info.json"), serde_json::to_vec_pretty(&info)?)?;
    Ok(())
}

/// The benchmark's camera for a real scan: inside it (a fifth in from one end
/// of its longest horizontal axis, looking along it) or around it.
pub fn camera_around(mesh: &crate::pipeline::read::TriangleMesh, inside: bool) -> CameraSpec {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &mesh.positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let c: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
    let e: [f64; 3] = std::array::from_fn(|a| hi[a] - lo[a]);
    let r = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt() * 0.5;
    if inside {
        // Along the longest horizontal axis, a quarter in from one end, a fifth up.
        let long = if e[0] >= e[2] { 0 } else { 2 };
        let mut eye = c;
        eye[long] = lo[long] + 0.2 * e[long];
        eye[1] = lo[1] + 0.25 * e[1];
        let mut target = c;
        target[long] = hi[long] - 0.2 * e[long];
        target[1] = lo[1] + 0.3 * e[1];
        CameraSpec { eye, target, up: [0.0, 1.0, 0.0], fov_y_deg: 60.0, near: r * 1e-3, far: r * 4.0 }
    } else {
        let eye = [c[0] + 0.9 * r, c[1] + 0.6 * r, c[2] + 1.9 * r];
        CameraSpec { eye, target: c, up: [0.0, 1.0, 0.0], fov_y_deg: 40.0, near: r * 1e-2, far: r * 10.0 }
    }
}

pub fn ao_bench_main(args: &AoBenchArgs) -> anyhow::Result<()> {
    let work = tempfile::tempdir().context("temporary directory")?;
    let store = work.path().join("store");
    let mut views = Vec::new();
    for s in analytic::scenes() {
        let mesh = work.path().join(format!("{}.obj", s.name));
        s.write_obj(&mesh)?;
        views.push(View { name: s.name.to_string(), mesh, camera: s.camera, shapes: Some(s.shapes) });
    }
    let mut skipped = Vec::new();
    views.retain(|v| args.views.is_empty() || args.views.contains(&v.name));
    for (name, file, inside) in [
        ("cornell_box", "CornellBox-Original.obj", None),
        ("dragon", "dragon_vrip_res4.ply", Some(false)),
        ("sponza_inside", "sponza.obj", Some(true)),
        ("conference_inside", "conference.obj", Some(true)),
        ("cedar_creek_inside", "matterport_cedar_creek.ply", Some(true)),
    ] {
        let mesh = args.data_dir.join(file);
        if !args.views.is_empty() && !args.views.iter().any(|v| v == name) {
            continue;
        }
        // Timing needs no mesh where the cache holds the view's scene and camera.
        let cached = || args.scene_cache.as_deref().and_then(|d| CachedScene::load(d, name, args.resolution));
        if let Some(cached) = (args.time_only && !mesh.is_file()).then(cached).flatten() {
            views.push(View { name: name.to_string(), mesh, camera: cached.camera, shapes: None });
            continue;
        }
        if !mesh.is_file() {
            skipped.push(format!("{name}: {} absent", mesh.display()));
            continue;
        }
        let camera = match inside {
            None => CameraSpec {
                eye: [0.0, 1.0, 3.0],
                target: [0.0, 1.0, 0.0],
                up: [0.0, 1.0, 0.0],
                fov_y_deg: 40.0,
                near: 0.05,
                far: 20.0,
            },
            Some(inside) => camera_around(&crate::pipeline::read::read_mesh(&mesh)?.0, inside),
        };
        views.push(View { name: name.to_string(), mesh, camera, shapes: None });
    }
    let points = match args.sweep {
        Sweep::Cones => sweep(&args.frames),
        Sweep::SparseTemporal => sparse_temporal_sweep(&args.frames),
        Sweep::Structure => structure_sweep(&args.frames),
        Sweep::Mode => mode_sweep(&args.frames),
        Sweep::Default => vec![default_point(&args.frames)],
    };
    let mut rows = Vec::new();
    let mut built = Vec::new();
    for view in &views {
        eprintln!("ao-bench: {} ...", view.name);
        let scene_dir = scene_for(view, args, &store)?;
        built.push(super::chromium::BrowserView {
            name: view.name.clone(),
            scene_dir: scene_dir.clone(),
            camera: view.camera,
        });
        let mesh = if args.time_only { None } else { Some(crate::pipeline::read::read_mesh(&view.mesh)?.0) };
        let mut bvh: Option<MeshBvh> = None;
        // Reference per image scale, at the default render's points.
        let mut references: Vec<ScaleReference> = Vec::new();
        for point in &points {
            let (w, h) = (args.width * point.scale, args.height * point.scale);
            let out = render_view(&RenderRequest {
                scene_dir: scene_dir.clone(),
                camera: view.camera,
                width: w,
                height: h,
                ao: point.settings,
                max_distance: None,
                timing_runs: args.timing_runs,
                ao_frames: point.frames,
            })?;
            let Some(mesh) = &mesh else {
                rows.push(Row::timed(view, point, &out));
                let r = rows.last().expect("just pushed");
                eprintln!(
                    "  {:36} {}x{}  frame {:8.2} ms (no AO {:.2})  GPU AO {} ms  GPU frame without AO {} ms",
                    point.label,
                    w,
                    h,
                    r.frame_ms,
                    r.frame_no_ao_ms,
                    fmt_opt(r.gpu_ao_ms, 3),
                    fmt_opt(r.gpu_frame_no_ao_ms, 3)
                );
                continue;
            };
            let bvh = bvh.get_or_insert_with(|| MeshBvh::new(mesh, out.info.grid_origin));
            if !references.iter().any(|r| r.scale == point.scale) {
                let params = AoParams::of_render(&out.info, bvh);
                let reference = reference_at(bvh, &out.position, &out.normal, &params, args.rays);
                let exact = view.shapes.as_ref().map(|s| exact_image(s, &out, 32));
                let (pp, pn) = crate::reference::primary_hits(bvh, &out.info);
                let primary = reference_at(bvh, &pp, &pn, &params, args.rays / 4);
                references.push(ScaleReference {
                    scale: point.scale,
                    positions: out.position.clone(),
                    v: reference.v,
                    variance: reference.variance,
                    exact,
                    primary: primary.v,
                });
            }
            let ScaleReference { positions, v: reference, variance, exact, primary, .. } =
                references.iter().find(|r| r.scale == point.scale).expect("just made");
            anyhow::ensure!(
                positions.iter().zip(&out.position).all(|(a, b)| a == b || (a[0].is_nan() && b[0].is_nan())),
                "{}: the render's points changed with the AO setting",
                view.name
            );
            if let Some(dir) = &args.dump_dir {
                let index = points.iter().position(|p| std::ptr::eq(p, point)).unwrap_or(0);
                dump_pixels(&dir.join(&view.name).join(index.to_string()), &out, reference, variance)?;
            }
            let c = compare(&out.ao, reference, variance, args.rays, w, h);
            let p = compare(&out.ao, primary, variance, args.rays / 4, w, h);
            rows.push(Row {
                rmse: c.rmse,
                bias: c.bias,
                ssim: c.ssim,
                equal_error_rays: c.equal_error_rays,
                exact_mae: exact.as_ref().map(|e| exact_error(&out.ao, e).mae),
                primary_rmse: p.rmse,
                primary_bias: p.bias,
                ..Row::timed(view, point, &out)
            });
            eprintln!(
                "  {:36} {:8.1} ms  RMSE {:.4}  bias {:+.4}  eq. rays {}",
                point.label,
                rows.last().unwrap().frame_ms,
                c.rmse,
                c.bias,
                fmt_opt(c.equal_error_rays, 1)
            );
        }
    }
    let mut browser = None;
    if args.browser {
        eprintln!("ao-bench: Chromium ...");
        let (adapter, times) = super::chromium::time_in_chromium(
            &built,
            &points,
            args.width,
            args.height,
            args.timing_runs,
            &args.browser_script,
            args.web.as_deref(),
        )?;
        for t in times {
            if let Some(r) = rows.iter_mut().find(|r| r.view == t.view && r.point == t.point) {
                r.chromium = Some(t);
            }
        }
        browser = Some(adapter);
    }
    std::fs::create_dir_all(&args.out_dir)?;
    let summary = summarize(&points, &rows);
    if args.time_only {
        return write_timing(args, &rows, &summary, &skipped, browser.as_deref());
    }
    write_markdown(
        &args.out_dir.join("ao-benchmark.md"),
        args,
        &rows,
        &summary,
        &skipped,
        browser.as_deref(),
    )?;
    write_pareto_png(&args.out_dir.join("ao-pareto.png"), &summary)?;
    let adapter = voxstream_viewer::offscreen::Gpu::shared().map(|g| g.adapter_name()).unwrap_or_default();
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "adapter": adapter,
            "rays": args.rays,
            "resolution": args.resolution,
            "skipped": skipped,
            "rows": rows,
            "summary": summary,
        }))?
    );
    Ok(())
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub point: String,
    pub mean_frame_ms: f64,
    pub mean_ao_over_frame: f64,
    pub mean_rmse: f64,
    pub mean_abs_bias: f64,
    pub mean_ssim: f64,
    /// GPU AO ÷ GPU frame without AO, over the views the adapter timed.
    pub mean_gpu_ao_over_frame: Option<f64>,
    /// Over the views Chromium timed (`--browser`).
    pub mean_chromium_ao_over_frame: Option<f64>,
    /// Views with a row for this point.
    pub views: usize,
    pub pareto: bool,
}

fn summarize(points: &[Point], rows: &[Row]) -> Vec<Summary> {
    let mut out: Vec<Summary> = points
        .iter()
        .map(|p| {
            let r: Vec<&Row> = rows.iter().filter(|r| r.point == p.label).collect();
            let n = r.len().max(1) as f64;
            let mean = |f: &dyn Fn(&Row) -> f64| r.iter().map(|x| f(x)).sum::<f64>() / n;
            // Over the views that have the value.
            let mean_some = |f: &dyn Fn(&Row) -> Option<f64>| {
                let v: Vec<f64> = r.iter().filter_map(|x| f(x)).collect();
                (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
            };
            Summary {
                point: p.label.clone(),
                mean_frame_ms: mean(&|x| x.frame_ms),
                mean_ao_over_frame: mean(&|x| x.ao_over_frame),
                mean_rmse: mean(&|x| x.rmse),
                mean_abs_bias: mean(&|x| x.bias.abs()),
                mean_ssim: mean(&|x| x.ssim),
                mean_gpu_ao_over_frame: mean_some(&Row::gpu_ratio),
                mean_chromium_ao_over_frame: mean_some(&Row::chromium_ratio),
                views: r.len(),
                pareto: false,
            }
        })
        .collect();
    let snapshot = out.clone();
    for s in &mut out {
        s.pareto = !snapshot.iter().any(|o| {
            o.mean_frame_ms <= s.mean_frame_ms
                && o.mean_rmse <= s.mean_rmse
                && (o.mean_frame_ms < s.mean_frame_ms || o.mean_rmse < s.mean_rmse)
        });
    }
    out
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("—".to_string(), |v| format!("{v:.digits$}"))
}

fn write_markdown(
    path: &Path,
    args: &AoBenchArgs,
    rows: &[Row],
    summary: &[Summary],
    skipped: &[String],
    browser: Option<&str>,
) -> anyhow::Result<()> {
    use std::fmt::Write;
    let adapter = voxstream_viewer::offscreen::Gpu::shared().map(|g| g.adapter_name()).unwrap_or_default();
    let mut s = String::new();
    writeln!(s, "# Cone-traced AO: run time against error\n")?;
    writeln!(
        s,
        "Written by `voxstream ao-bench` (server/src/reference/bench.rs) on {adapter}: scenes built at {}³, images {}×{} (2× for one point), reference {} cosine-weighted rays per pixel at the render's own points (obvhs BVH over the original triangles), the ray-traced view of the mesh with {} rays. Times are medians of three frames, with AO and without (the AO runs in its own passes after the G-buffer draw; `AO/frame` = (with − without) / without); an N-frame point's AO is the average of N jittered frames of the still view and costs N frames to converge (`frames`). Equal-error rays: k with mean σ²/k = the renderer's MSE (— where the error is below what the reference resolves). Exact MAE: analytic scenes only, against the exact geometry's quadrature.\n",
        args.resolution,
        args.width,
        args.height,
        args.rays,
        args.rays / 4
    )?;
    if !skipped.is_empty() {
        writeln!(s, "Views skipped: {}.\n", skipped.join("; "))?;
    }
    if let Some(browser) = browser {
        writeln!(s, "{}\n", chromium_note(browser))?;
    }
    // The Chromium column only where it was measured.
    let chromium =
        |v: Option<f64>| if browser.is_some() { format!(" {} |", fmt_opt(v, 2)) } else { String::new() };
    let (chromium_head, chromium_rule) =
        if browser.is_some() { (" Chromium AO/frame |", "---:|") } else { ("", "") };
    writeln!(s, "## Summary (means over the views; * = on the Pareto front of time against RMSE)\n")?;
    writeln!(s, "| setting | frame ms | AO/frame |{chromium_head} RMSE | abs bias | SSIM |")?;
    writeln!(s, "|---|---:|---:|{chromium_rule}---:|---:|---:|")?;
    for x in summary {
        writeln!(
            s,
            "| {}{} | {:.1} | {:.2} |{} {:.4} | {:.4} | {:.3} |",
            x.point,
            if x.pareto { " *" } else { "" },
            x.mean_frame_ms,
            x.mean_ao_over_frame,
            chromium(x.mean_chromium_ao_over_frame),
            x.mean_rmse,
            x.mean_abs_bias,
            x.mean_ssim
        )?;
    }
    writeln!(s, "\n## Every view and setting\n")?;
    writeln!(
        s,
        "| view | setting | size | frames | frame ms | no-AO ms | AO/frame |{chromium_head} RMSE | bias | SSIM | eq. rays | exact MAE | RMSE vs ray-traced view | bias vs ray-traced view |"
    )?;
    writeln!(s, "|---|---|---|---:|---:|---:|---:|{chromium_rule}---:|---:|---:|---:|---:|---:|---:|")?;
    for r in rows {
        writeln!(
            s,
            "| {} | {} | {}×{} | {} | {:.1} | {:.1} | {:.2} |{} {:.4} | {:+.4} | {:.3} | {} | {} | {:.4} | {:+.4} |",
            r.view,
            r.point,
            r.width,
            r.height,
            r.frames,
            r.frame_ms,
            r.frame_no_ao_ms,
            r.ao_over_frame,
            chromium(r.chromium_ratio()),
            r.rmse,
            r.bias,
            r.ssim,
            fmt_opt(r.equal_error_rays, 1),
            fmt_opt(r.exact_mae, 4),
            r.primary_rmse,
            r.primary_bias
        )?;
    }
    std::fs::write(path, s).with_context(|| format!("writing {}", path.display()))
}

/// A 640×480 scatter of mean frame time (x, log scale) against mean RMSE (y,
/// linear from 0), points as squares (filled red on the Pareto front, grey
/// otherwise), the front joined by a line; no text (the table has the numbers).
fn write_pareto_png(path: &Path, summary: &[Summary]) -> anyhow::Result<()> {
    let (w, h) = (640usize, 480usize);
    let mut img = vec![255u8; w * h * 3];
    let (l, r, t, b) = (60.0, 620.0, 20.0, 440.0);
    let finite: Vec<&Summary> =
        summary.iter().filter(|s| s.mean_frame_ms > 0.0 && s.mean_rmse.is_finite()).collect();
    let tmin = finite.iter().map(|s| s.mean_frame_ms).fold(f64::INFINITY, f64::min).ln();
    let tmax = finite.iter().map(|s| s.mean_frame_ms).fold(0.0, f64::max).ln();
    let emax = finite.iter().map(|s| s.mean_rmse).fold(0.0, f64::max) * 1.1;
    let px = |ms: f64| l + (ms.ln() - tmin) / (tmax - tmin).max(1e-9) * (r - l);
    let py = |e: f64| b - e / emax.max(1e-9) * (b - t);
    let mut put = |x: i64, y: i64, c: [u8; 3]| {
        if (0..w as i64).contains(&x) && (0..h as i64).contains(&y) {
            let i = (y as usize * w + x as usize) * 3;
            img[i..i + 3].copy_from_slice(&c);
        }
    };
    for x in l as i64..=r as i64 {
        put(x, b as i64, [0, 0, 0]);
    }
    for y in t as i64..=b as i64 {
        put(l as i64, y, [0, 0, 0]);
    }
    let mut front: Vec<&&Summary> = finite.iter().filter(|s| s.pareto).collect();
    front.sort_by(|a, b| a.mean_frame_ms.total_cmp(&b.mean_frame_ms));
    for pair in front.windows(2) {
        let (x0, y0, x1, y1) = (
            px(pair[0].mean_frame_ms),
            py(pair[0].mean_rmse),
            px(pair[1].mean_frame_ms),
            py(pair[1].mean_rmse),
        );
        let n = ((x1 - x0).abs().max((y1 - y0).abs()) as usize).max(1);
        for k in 0..=n {
            let f = k as f64 / n as f64;
            put((x0 + (x1 - x0) * f) as i64, (y0 + (y1 - y0) * f) as i64, [200, 40, 40]);
        }
    }
    for s in &finite {
        let (x, y) = (px(s.mean_frame_ms) as i64, py(s.mean_rmse) as i64);
        let c = if s.pareto { [200, 40, 40] } else { [120, 120, 120] };
        for dy in -3..=3 {
            for dx in -3..=3 {
                put(x + dx, y + dy, c);
            }
        }
    }
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header()?.write_image_data(&img)?;
    Ok(())
}
