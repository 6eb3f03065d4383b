//! What the AO tests on analytic scenes share: a still view at a setting,
//! the error against exact values over a chosen set of pixels, and a render with a modified copy of the shipped AO shader (the
//! rule's negative control, loaded through `VOXSTREAM_DEV_AO_WGSL`, which is
//! process-wide: each such test is its own test binary).

// Each test binary that includes this module uses only part of it.
#![allow(dead_code)]

use std::path::Path;

use voxstream::reference::analytic::{AnalyticScene, exact_image};
use voxstream::render::{RenderOutput, RenderRequest, render_view};
use voxstream_viewer::ao::AoSettings;

pub const WIDTH: u32 = 96;
pub const HEIGHT: u32 = 64;
pub const RESOLUTION: u32 = 256;
pub const QUADRATURE: u32 = 48;

/// `ao` as the viewer shows a still view: its jittered frames accumulated.
/// `max_distance`: R in source units (default: the render's own).
pub fn render_with(
    scene_dir: &Path,
    scene: &AnalyticScene,
    ao: AoSettings,
    max_distance: Option<f64>,
) -> RenderOutput {
    render_view(&RenderRequest {
        scene_dir: scene_dir.to_path_buf(),
        camera: scene.camera,
        width: WIDTH,
        height: HEIGHT,
        ao,
        max_distance,
        timing_runs: 0,
        ao_frames: ao.temporal_frames,
    })
    .unwrap_or_else(|e| {
        panic!(
            "rendering {}: {e:#}\n(native rendering needs Vulkan: scripts/setup.sh installs mesa-vulkan-drivers)",
            scene.name
        )
    })
}

/// The default setting, as [`render_with`].
pub fn render_still(scene_dir: &Path, scene: &AnalyticScene, max_distance: Option<f64>) -> RenderOutput {
    render_with(scene_dir, scene, AoSettings::default(), max_distance)
}

/// (pixels, mean |V − exact|, mean exact V) over the surface pixels whose
/// position (source units) and normal `keep` accepts.
pub fn error_where(
    scene: &AnalyticScene,
    out: &RenderOutput,
    keep: impl Fn(&[f64; 3], &[f32; 3]) -> bool,
) -> (usize, f64, f64) {
    let exact = exact_image(&scene.shapes, out, QUADRATURE);
    let (mut n, mut err, mut v) = (0usize, 0.0, 0.0);
    for (((&ao, &e), p), nrm) in out.ao.iter().zip(&exact).zip(&out.position).zip(&out.normal) {
        if ao.is_finite() && e.is_finite() && keep(p, nrm) {
            n += 1;
            err += (ao as f64 - e as f64).abs();
            v += e as f64;
        }
    }
    let k = n.max(1) as f64;
    (n, err / k, v / k)
}

/// Runs `f` with `ao_wgsl` in place of the shipped shaders/ao.wgsl.
pub fn with_ao_shader<T>(ao_wgsl: &str, f: impl FnOnce() -> T) -> T {
    with_dev_shaders(ao_wgsl, None, f)
}

/// Runs `f` with `voxel_wgsl` in place of the shipped shaders/voxel.wgsl (the AO shaders as shipped).
pub fn with_voxel_shader<T>(voxel_wgsl: &str, f: impl FnOnce() -> T) -> T {
    with_dev_shaders(voxstream_viewer::shaders::AO_WGSL, Some(voxel_wgsl), f)
}

/// Runs `f` with the given ao.wgsl and, if any, voxel.wgsl loaded through `VOXSTREAM_DEV_AO_WGSL`.
fn with_dev_shaders<T>(ao_wgsl: &str, voxel_wgsl: Option<&str>, f: impl FnOnce() -> T) -> T {
    let shaders = tempfile::tempdir().unwrap();
    std::fs::write(shaders.path().join("ao.wgsl"), ao_wgsl).unwrap();
    std::fs::write(shaders.path().join("ao_trace.wgsl"), voxstream_viewer::shaders::AO_TRACE_WGSL).unwrap();
    if let Some(voxel) = voxel_wgsl {
        std::fs::write(shaders.path().join("voxel.wgsl"), voxel).unwrap();
    }
    // SAFETY: each test binary using this runs one test; no other thread reads the environment.
    unsafe { std::env::set_var(voxstream_viewer::shaders::DEV_AO_WGSL_ENV, shaders.path()) };
    let out = f();
    unsafe { std::env::remove_var(voxstream_viewer::shaders::DEV_AO_WGSL_ENV) };
    out
}

/// The shipped ao.wgsl with the crevice probe off (`crevice_bend`: no bend
/// anywhere), for tests whose control or isolation needs the tracer without it.
pub fn ao_wgsl_without_crevice_probe() -> String {
    let src = voxstream_viewer::shaders::AO_WGSL
        .replace("let bend = crevice_bend(p, n, base_cell, cell);", "let bend = 0.0;");
    assert_eq!(
        src.matches("let bend = 0.0;").count(),
        1,
        "the crevice probe is no longer where tests switch it off"
    );
    src
}

/// Floor pixels (normal up) of the sphere on a plane whose horizontal
/// distance from the point below the sphere's centre lies in `lo..hi`
/// (source units; the sphere's radius is 0.5), as [`error_where`] takes them.
pub fn floor_ring(lo: f64, hi: f64) -> impl Fn(&[f64; 3], &[f32; 3]) -> bool + Copy {
    move |p, n| n[1] > 0.9 && (lo..hi).contains(&p[0].hypot(p[2]))
}
