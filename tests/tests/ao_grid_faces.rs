//! A clipmap level whose face lies on the scene grid's face (shaders/ao.wgsl,
//! `clip_contains`): the cells beyond it are outside the grid, empty by
//! definition, so the level holds samples right up to the grid's face. Before
//! this rule such a sample, in the half cell next to the face, fell back to
//! the next coarser level, whose wider cells smear the surface on the grid's
//! face (here the floor) over the points just above it.
//!
//! The scene: a sphere resting on a floor that is the grid's bottom face,
//! seen so that the floor around the contact is homed at clipmap level 1,
//! which is the grid's size (centred on it, `ClipmapLayout::origin`). Checked
//! against exact values over the floor pixels around the contact: the rule
//! must lower the mean |V − exact| by at least [`MIN_GAIN`] against the
//! negative control, a copy of the shipped shader with the rule switched off
//! (loaded through `VOXSTREAM_DEV_AO_WGSL`, so this file is its own test binary).

use std::path::Path;

use voxstream::reference::analytic::{self, AnalyticScene, exact_image};
use voxstream::render::{RenderOutput, RenderRequest, render_view};
use voxstream_viewer::ao::AoSettings;

const WIDTH: u32 = 96;
const HEIGHT: u32 = 64;
const RESOLUTION: u32 = 256;
const QUADRATURE: u32 = 48;
/// How much the rule must lower the mean |V − exact| in the ring around the
/// contact (0.011 when written: the renders are deterministic).
const MIN_GAIN: f64 = 0.005;

fn render(scene_dir: &Path, scene: &AnalyticScene) -> RenderOutput {
    let ao = AoSettings::default();
    render_view(&RenderRequest {
        scene_dir: scene_dir.to_path_buf(),
        camera: scene.camera,
        width: WIDTH,
        height: HEIGHT,
        ao,
        max_distance: None,
        timing_runs: 0,
        ao_frames: ao.temporal_frames,
    })
    .unwrap_or_else(|e| panic!("rendering {}: {e:#}", scene.name))
}

/// (pixels, mean |V − exact|, mean exact V) over the floor pixels whose
/// horizontal distance from the point below the sphere's centre lies in
/// `ring` (source units): the half shadow around the contact, where the
/// floor's occlusion comes from cones that skim it.
fn contact_error(scene: &AnalyticScene, out: &RenderOutput, ring: (f64, f64)) -> (usize, f64, f64) {
    let exact = exact_image(&scene.shapes, out, QUADRATURE);
    let (mut n, mut err, mut v) = (0usize, 0.0, 0.0);
    for (((&ao, &e), p), nrm) in out.ao.iter().zip(&exact).zip(&out.position).zip(&out.normal) {
        if ao.is_finite() && e.is_finite() && nrm[1] > 0.9 && (ring.0..ring.1).contains(&p[0].hypot(p[2])) {
            n += 1;
            err += (ao as f64 - e as f64).abs();
            v += e as f64;
        }
    }
    let k = n.max(1) as f64;
    (n, err / k, v / k)
}

#[test]
fn a_level_on_the_grids_face_holds_samples_up_to_it() {
    let scene = analytic::scenes().into_iter().find(|s| s.name == "sphere_on_plane").expect("scene");
    let store = tempfile::tempdir().unwrap();
    let dir = analytic::build(&scene, store.path(), RESOLUTION).expect("build");
    let ring = (0.3, 0.5);
    let out = render(&dir, &scene);
    let (pixels, mae, exact_v) = contact_error(&scene, &out, ring);

    // Negative control: the level must hold all eight cells of a read, even
    // those beyond the grid (the tracer before the rule).
    let shaders = tempfile::tempdir().unwrap();
    let src = voxstream_viewer::shaders::AO_WGSL;
    let switched =
        src.replace("let lo = select(o, vec3<f32>(-1e30), o <= vec3<f32>(0.0));", "let lo = o;").replace(
            "let hi = select(o + n - 1.0, vec3<f32>(1e30), o + n >= vec3<f32>(clip_grid_cells(level)));",
            "let hi = o + n - 1.0;",
        );
    assert_eq!(
        switched.matches("let lo = o;").count(),
        1,
        "the rule is no longer where this test switches it off"
    );
    assert_eq!(
        switched.matches("let hi = o + n - 1.0;").count(),
        1,
        "the rule is no longer where this test switches it off"
    );
    std::fs::write(shaders.path().join("ao.wgsl"), switched).unwrap();
    std::fs::write(shaders.path().join("ao_trace.wgsl"), voxstream_viewer::shaders::AO_TRACE_WGSL).unwrap();
    // SAFETY: this test binary runs this one test; no other thread reads the environment.
    unsafe { std::env::set_var(voxstream_viewer::shaders::DEV_AO_WGSL_ENV, shaders.path()) };
    let control = render(&dir, &scene);
    unsafe { std::env::remove_var(voxstream_viewer::shaders::DEV_AO_WGSL_ENV) };
    let (_, control_mae, _) = contact_error(&scene, &control, ring);

    println!(
        "sphere on a plane: {pixels} floor px {ring:?} from the contact, exact V {exact_v:.3}; mean |V − exact| with the rule {mae:.4}, without (control) {control_mae:.4}"
    );
    assert!(pixels >= 80, "only {pixels} floor pixels around the contact: the camera misses it");
    assert!(
        exact_v < 0.9,
        "the sphere hardly occludes the floor (exact V {exact_v:.3}): the test sees nothing"
    );
    assert!(
        control_mae - mae >= MIN_GAIN,
        "reads beyond the grid's face do not help: mean |V − exact| {mae:.4} against {control_mae:.4} without the rule (need {MIN_GAIN} less)"
    );
}
