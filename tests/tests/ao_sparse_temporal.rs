//! Reduced-resolution tracing with joint bilateral upsampling, and jittered
//! temporal accumulation with reprojection (issue 9 item 1, seed 001), on
//! lavapipe with scenes generated in code (built at 256³, rendered by
//! `voxstream render`'s code at 96×64):
//!
//! - the bilateral upsample keeps a depth edge sharp: at the pixels along the
//!   silhouette of a plate in front of a wall, half-resolution AO upsampled
//!   bilaterally stays close to the full-resolution trace; the control, plain
//!   bilinear upsampling, blurs the wall's dark contact shadow onto the plate;
//! - a pixel whose surface no traced texel around it shares is traced
//!   itself: on fins one or two pixels wide it then equals the
//!   full-resolution trace; the control, the bilateral blend alone, misses
//!   those pixels; on a comb so dense that more pixels need it than the
//!   retrace queue holds, more pixels than that come out traced;
//! - accumulating jittered frames lowers the error against the exact values on
//!   the sphere on a plane; the control, the same accumulation without jitter,
//!   averages identical frames and changes nothing;
//! - reprojection drops the history after a camera jump: surface points the
//!   first camera never saw start afresh (their V is the new frame's); the
//!   control, keeping disoccluded history, blends in what the old view saw at
//!   the reprojected pixels.

use std::path::{Path, PathBuf};

use voxstream::reference::analytic::{self, AnalyticScene, Shape, exact_error, exact_image};
use voxstream::render::{CameraSpec, RenderOutput, RenderRequest, render_view};
use voxstream_viewer::ao::{AoSettings, Upsample};
use voxstream_viewer::offscreen::{GBufferFrame, Offscreen, OffscreenFrame, RenderOptions};

const WIDTH: u32 = 96;
const HEIGHT: u32 = 64;
const RESOLUTION: u32 = 256;

fn camera(eye: [f64; 3], target: [f64; 3]) -> CameraSpec {
    CameraSpec { eye, target, up: [0.0, 1.0, 0.0], fov_y_deg: 45.0, near: 0.05, far: 50.0 }
}

fn rect(corner: [f64; 3], u: [f64; 3], v: [f64; 3]) -> Shape {
    Shape::Rect { corner: corner.into(), u: u.into(), v: v.into() }
}

/// A 1×1 plate 0.15 in front of a 4×3 wall, both facing +z, seen from the
/// front and a little to the side: the plate's face is open (V near 1) while
/// the wall around its silhouette lies in its contact shadow.
fn plate_before_wall() -> AnalyticScene {
    analytic::scene_from_shapes(
        "plate_before_wall",
        vec![
            rect([-2.0, -0.5, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0]),
            rect([-0.5, 0.5, 0.15], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        ],
        camera([0.5, 1.3, 2.0], [0.0, 1.0, 0.0]),
    )
}

/// A comb: `fins` thin fins 0.3 deep standing out of a wall, `spacing`
/// apart, seen head-on. Each fin's front is a line one or two pixels wide,
/// open to the front (V near 1), between strips of wall deep in the fins'
/// shadow: at half resolution some of its pixels have no traced texel on a
/// fin at all.
fn comb_on_wall(fins: usize, spacing: f64) -> AnalyticScene {
    let mut shapes = vec![rect([-2.0, -0.5, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0])];
    for i in 0..fins {
        let x = spacing * (i as f64 - 0.5 * (fins - 1) as f64);
        shapes.push(rect([x, 0.5, 0.0], [0.0, 0.0, 0.3], [0.0, 1.0, 0.0]));
    }
    analytic::scene_from_shapes("comb_on_wall", shapes, camera([0.0, 1.0, 2.0], [0.0, 1.0, 0.0]))
}

fn build(scene: &AnalyticScene, store: &Path) -> PathBuf {
    analytic::build(scene, store, RESOLUTION).expect("build the scene")
}

fn render(scene_dir: &Path, camera: CameraSpec, ao: AoSettings, frames: u32) -> RenderOutput {
    render_view(&RenderRequest {
        scene_dir: scene_dir.to_path_buf(),
        camera,
        width: WIDTH,
        height: HEIGHT,
        ao,
        max_distance: None,
        timing_runs: 0,
        ao_frames: frames,
    })
    .unwrap_or_else(|e| {
        panic!(
            "rendering: {e:#}\n(native rendering needs Vulkan: scripts/setup.sh installs mesa-vulkan-drivers)"
        )
    })
}

/// Surface pixels with a 4-neighbour on another surface across a depth
/// discontinuity: the neighbour lies more than `gap` (source units) off the
/// pixel's tangent plane.
fn depth_edge_pixels(out: &RenderOutput, gap: f64) -> Vec<usize> {
    let (w, h) = (out.info.width as i64, out.info.height as i64);
    let surface = |i: usize| out.ao[i].is_finite();
    let mut edges = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            if !surface(i) {
                continue;
            }
            let (p, n) = (out.position[i], out.normal[i]);
            let across = [(-1, 0), (1, 0), (0, -1), (0, 1)].iter().any(|&(dx, dy)| {
                let (nx, ny) = (x + dx, y + dy);
                if !(0..w).contains(&nx) || !(0..h).contains(&ny) {
                    return false;
                }
                let j = (ny * w + nx) as usize;
                let q = out.position[j];
                let plane: f64 = (0..3).map(|a| (q[a] - p[a]) * n[a] as f64).sum();
                surface(j) && plane.abs() > gap
            });
            if across {
                edges.push(i);
            }
        }
    }
    edges
}

fn mean_abs_difference(a: &RenderOutput, b: &RenderOutput, pixels: &[usize]) -> f64 {
    pixels.iter().map(|&i| (a.ao[i] - b.ao[i]).abs() as f64).sum::<f64>() / pixels.len().max(1) as f64
}

#[test]
fn bilateral_upsampling_keeps_a_depth_edge_sharp() {
    let store = tempfile::tempdir().unwrap();
    let scene = plate_before_wall();
    let dir = build(&scene, store.path());
    let fixed = AoSettings { jitter: false, interleave: false, ..AoSettings::default() };
    let full = render(&dir, scene.camera, AoSettings { trace_downscale: 1, ..fixed }, 1);
    let bilateral = render(&dir, scene.camera, AoSettings { trace_downscale: 2, ..fixed }, 1);
    let bilinear = render(
        &dir,
        scene.camera,
        AoSettings { trace_downscale: 2, upsample: Upsample::Bilinear, ..fixed },
        1,
    );
    assert_eq!(full.position.len(), bilateral.position.len());
    let edges = depth_edge_pixels(&full, 0.05);
    assert!(edges.len() > 40, "only {} depth-edge pixels: the scene does not show its edge", edges.len());
    let bilateral_error = mean_abs_difference(&bilateral, &full, &edges);
    let bilinear_error = mean_abs_difference(&bilinear, &full, &edges);
    let surface: Vec<usize> = (0..full.ao.len()).filter(|&i| full.ao[i].is_finite()).collect();
    println!(
        "{} edge pixels: mean |V(1/2 res) − V(full res)|: bilateral {bilateral_error:.4}, bilinear {bilinear_error:.4}; \
         over all {} surface pixels: bilateral {:.4}, bilinear {:.4}",
        edges.len(),
        surface.len(),
        mean_abs_difference(&bilateral, &full, &surface),
        mean_abs_difference(&bilinear, &full, &surface),
    );
    assert!(bilateral_error < 0.05, "the bilateral upsample blurs the depth edge: {bilateral_error:.4}");
    // Control: plain bilinear upsampling mixes the two sides of the edge.
    assert!(
        bilinear_error > 2.0 * bilateral_error && bilinear_error > 0.04,
        "bilinear upsampling ({bilinear_error:.4}) should blur the edge that bilateral ({bilateral_error:.4}) keeps"
    );
    for out in [&bilateral, &bilinear] {
        assert!(out.ao.iter().all(|v| v.is_nan() || (0.0..=1.0).contains(v)));
    }
}

/// What the re-tracing upsample does on a comb, against the full-resolution
/// trace: (edge pixels, those the blend alone missed by > 0.02 that came out
/// exactly, mean edge error re-tracing, the same for the blend alone, pixels
/// away from the edges that changed, pixels away from the edges, pixels
/// anywhere that came out exactly and unlike the blend: the ones traced),
/// tracing one pixel of each `f`×`f` block.
fn retrace_on_comb(fins: usize, spacing: f64, f: u32) -> (usize, usize, f64, f64, usize, usize, usize) {
    let store = tempfile::tempdir().unwrap();
    let scene = comb_on_wall(fins, spacing);
    let dir = build(&scene, store.path());
    // Fixed cones and no interleaving: a pixel traced by the upsample sees
    // exactly the cones the full-resolution trace gave it.
    let fixed = AoSettings { jitter: false, interleave: false, ..AoSettings::default() };
    let full = render(&dir, scene.camera, AoSettings { trace_downscale: 1, ..fixed }, 1);
    let retrace = render(&dir, scene.camera, AoSettings { trace_downscale: f, ..fixed }, 1);
    // Control: the same upsample without tracing the pixels it cannot match.
    let blend_only = render(
        &dir,
        scene.camera,
        AoSettings { trace_downscale: f, upsample: Upsample::BilateralOnly, ..fixed },
        1,
    );
    let edges = depth_edge_pixels(&full, 0.05);
    let same_as_full = |out: &RenderOutput, i: usize| (out.ao[i] - full.ao[i]).abs() < 1e-4;
    let mended = edges
        .iter()
        .filter(|&&i| same_as_full(&retrace, i) && (blend_only.ao[i] - full.ao[i]).abs() > 0.02)
        .count();
    let retrace_error = mean_abs_difference(&retrace, &full, &edges);
    let blend_error = mean_abs_difference(&blend_only, &full, &edges);
    let interior: Vec<usize> =
        (0..full.ao.len()).filter(|&i| full.ao[i].is_finite() && !edges.contains(&i)).collect();
    let moved = interior.iter().filter(|&&i| (retrace.ao[i] - blend_only.ao[i]).abs() > 1e-6).count();
    let traced = (0..full.ao.len())
        .filter(|&i| {
            full.ao[i].is_finite()
                && same_as_full(&retrace, i)
                && (retrace.ao[i] - blend_only.ao[i]).abs() > 1e-6
        })
        .count();
    println!(
        "1/{f} resolution, {traced} pixels traced by the upsample; {fins} fins {spacing} apart, {} edge pixels: mean |V(1/{f} res) − V(full res)|: re-tracing {retrace_error:.4}, \
         blend only {blend_error:.4}; {mended} pixels the blend missed by > 0.02 traced exactly; \
         {moved} of {} pixels away from the edges changed",
        edges.len(),
        interior.len()
    );
    (edges.len(), mended, retrace_error, blend_error, moved, interior.len(), traced)
}

#[test]
fn pixels_no_traced_texel_matches_are_traced_themselves() {
    let (edges, mended, retrace_error, blend_error, moved, interior, _) = retrace_on_comb(8, 0.1, 2);
    assert!(edges > 40, "only {edges} depth-edge pixels: the scene does not show its edge");
    assert!(mended >= 5, "only {mended} edge pixels were traced where the blend could not match them");
    assert!(
        retrace_error < 0.8 * blend_error,
        "re-tracing ({retrace_error:.4}) should follow the full-resolution trace at the edge better than the blend alone ({blend_error:.4})"
    );
    // Away from the edges the two agree: only unmatched pixels are traced.
    assert!(
        moved * 10 < interior,
        "{moved} of {interior} pixels away from the depth edges changed: the upsample traces more than the pixels it cannot match"
    );
}

/// A comb so dense that more pixels need tracing than the retrace queue
/// holds (one pixel in 8): the upsample traces the rest itself.
#[test]
fn pixels_past_the_retrace_queue_are_traced_too() {
    let (_, _, retrace_error, blend_error, .., traced) = retrace_on_comb(49, 0.05, 4);
    let room = (WIDTH * HEIGHT).div_ceil(8) as usize;
    assert!(
        traced > room,
        "{traced} pixels came out traced; the queue holds {room}, so none was traced past it"
    );
    assert!(retrace_error < 0.8 * blend_error, "re-tracing {retrace_error:.4}, blend only {blend_error:.4}");
}

#[test]
fn accumulating_jittered_frames_lowers_the_error_against_exact_values() {
    let store = tempfile::tempdir().unwrap();
    let scene =
        analytic::scenes().into_iter().find(|s| s.name == "sphere_on_plane").expect("sphere on a plane");
    let dir = build(&scene, store.path());
    // Three cones: few enough that one fixed set misses much of the
    // hemisphere; full resolution and no per-pixel turn, so only the per-frame
    // jitter differs between the frames.
    let settings = AoSettings { cones: 3, trace_downscale: 1, interleave: false, ..AoSettings::default() };
    let frames = 16;
    let one = render(&dir, scene.camera, settings, 1);
    let exact = exact_image(&scene.shapes, &one, 48);
    let jittered = render(&dir, scene.camera, settings, frames);
    let fixed = render(&dir, scene.camera, AoSettings { jitter: false, ..settings }, frames);
    let (e1, ej, ef) =
        (exact_error(&one.ao, &exact), exact_error(&jittered.ao, &exact), exact_error(&fixed.ao, &exact));
    println!(
        "sphere on a plane, 3 cones, RMSE against exact: 1 frame {:.4}, {frames} jittered frames {:.4}, {frames} frames without jitter {:.4}",
        e1.rmse, ej.rmse, ef.rmse
    );
    assert_eq!(jittered.info.ao.frames, frames);
    assert!(
        ej.rmse < 0.9 * e1.rmse,
        "{frames} jittered frames do not lower the RMSE: {:.4} vs {:.4}",
        ej.rmse,
        e1.rmse
    );
    // Control: without jitter every frame is the same, and so is their average.
    let largest_change =
        one.ao.iter().zip(&fixed.ao).map(|(a, b)| (a - b).abs()).fold(0.0f32, |m, d| m.max(d));
    assert!(largest_change < 1e-5, "accumulating identical frames changed V by {largest_change}");
    assert!((ef.rmse - e1.rmse).abs() < 1e-5);
}

/// Moves `offscreen` to `camera`, loads what it wants and draws `frames`
/// frames there (the AO history carries over from the previous view); the
/// last one read back (`template` gives the frame's other fields).
fn frames_at(
    offscreen: &mut Offscreen,
    template: &OffscreenFrame,
    camera: CameraSpec,
    origin: [f64; 3],
    voxel: f64,
    frames: u32,
) -> GBufferFrame {
    offscreen.scene.fixed_view = Some(camera.fixed_view(origin, voxel, WIDTH, HEIGHT).unwrap());
    offscreen.load_wanted();
    offscreen.draw_frames(frames).unwrap();
    offscreen.read_gbuffer(template.clone()).unwrap()
}

#[test]
fn reprojection_drops_history_after_a_camera_jump() {
    let store = tempfile::tempdir().unwrap();
    let scene =
        analytic::scenes().into_iter().find(|s| s.name == "sphere_on_plane").expect("sphere on a plane");
    let dir = build(&scene, store.path());
    let manifest: voxstream_format::Manifest =
        voxstream_format::Manifest::from_json(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    let (origin, voxel) = (manifest.grid.origin, manifest.grid.voxel_size);
    let front = camera([0.0, 1.0, 2.2], [0.0, 0.4, 0.0]);
    let back = camera([0.0, 1.0, -2.2], [0.0, 0.4, 0.0]);
    let to_grid = |p: [f64; 3]| std::array::from_fn::<f64, 3, _>(|a| (p[a] - origin[a]) / voxel);
    let centre = to_grid([0.0, 0.5, 0.0]);
    let radius = 0.5 / voxel;
    let front_eye = to_grid(front.eye);

    let run = |keep_disoccluded_history: bool| {
        let mut offscreen = Offscreen::open(&dir, &RenderOptions::new(WIDTH, HEIGHT)).expect("open");
        offscreen.renderer.ao = AoSettings {
            jitter: false,
            temporal_frames: 8,
            keep_disoccluded_history,
            ..AoSettings::default()
        };
        offscreen.scene.fixed_view = Some(front.fixed_view(origin, voxel, WIDTH, HEIGHT).unwrap());
        let template = offscreen.render().expect("render");
        frames_at(&mut offscreen, &template, front, origin, voxel, 4);
        // 6 frames of the still view so far (2 in `render`), N = 8: the viewer would draw on.
        assert!(offscreen.renderer.ao_accumulating(), "6 of 8 frames in, yet not accumulating");
        offscreen.draw_frames(2).unwrap();
        assert!(!offscreen.renderer.ao_accumulating(), "8 of 8 frames in, yet still accumulating");
        // The jump: the first frame at the back camera.
        let jumped = frames_at(&mut offscreen, &template, back, origin, voxel, 1);
        assert!(offscreen.renderer.ao_accumulating(), "a moved view must accumulate again");
        // The same view from a fresh history: what one frame there gives.
        offscreen.renderer.ao_passes.reset_history();
        offscreen.draw_frames(1).unwrap();
        let fresh = offscreen.read_gbuffer(jumped.frame.clone()).unwrap();
        (jumped, fresh)
    };
    let (jumped, fresh) = run(false);
    let (leaky, _) = run(true);
    let frames = jumped.history_frames.as_ref().expect("accumulating");
    let leaky_frames = leaky.history_frames.as_ref().expect("accumulating");
    // The sphere's far side as the front camera saw it: points on the sphere
    // facing away from the front eye (by more than the voxel staircase's
    // wobble of the normal: cos < −0.2), which that camera never saw.
    let unseen: Vec<usize> = (0..frames.len())
        .filter(|&i| {
            let (p, n) = (jumped.position_ao[i], jumped.normal[i]);
            if n[3] < 0.5 {
                return false;
            }
            let d: f64 = (0..3).map(|a| (p[a] as f64 - centre[a]).powi(2)).sum::<f64>().sqrt();
            let to_eye: [f64; 3] = std::array::from_fn(|a| front_eye[a] - p[a] as f64);
            let distance = to_eye.iter().map(|c| c * c).sum::<f64>().sqrt();
            let facing: f64 = (0..3).map(|a| to_eye[a] * n[a] as f64).sum::<f64>() / distance;
            (d - radius).abs() < 3.0 && facing < -0.2
        })
        .collect();
    assert!(unseen.len() > 100, "only {} pixels of the sphere's far side", unseen.len());
    let kept = unseen.iter().filter(|&&i| frames[i] > 1.0).count();
    let leaked = unseen.iter().filter(|&&i| leaky_frames[i] > 1.0).count();
    let v_change = |out: &GBufferFrame| {
        unseen.iter().map(|&i| (out.position_ao[i][3] - fresh.position_ao[i][3]).abs() as f64).sum::<f64>()
            / unseen.len() as f64
    };
    // Points both cameras see (the floor around the sphere) keep their history.
    let surface = (0..frames.len()).filter(|&i| jumped.normal[i][3] > 0.5).count();
    let continued = frames.iter().filter(|&&f| f > 1.0).count();
    println!(
        "after the jump: {} unseen sphere pixels, {kept} kept history ({leaked} with disoccluded history kept); \
         mean |V − fresh V| there {:.5} ({:.5} when kept); {continued} of {surface} surface pixels continued",
        unseen.len(),
        v_change(&jumped),
        v_change(&leaky)
    );
    assert_eq!(kept, 0, "history kept on {kept} points the old view never saw");
    assert!(
        v_change(&jumped) < 1e-5,
        "V after the jump is not the new frame's where the history was dropped"
    );
    assert!(
        continued > surface / 10,
        "only {continued} of {surface} pixels kept any history: everything is dropped"
    );
    // Control: without the test, the old view's values leak in.
    assert!(leaked > unseen.len() / 3, "the control kept history on only {leaked} of {}", unseen.len());
    assert!(v_change(&leaky) > 0.01, "the leaked history did not change V: {:.5}", v_change(&leaky));
}
