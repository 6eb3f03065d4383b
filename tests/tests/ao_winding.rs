//! Both sides of a triangle are surface (issue 9's definition), and scans'
//! triangles disagree on their winding. A stored normal more than 45° past
//! edge-on to the eye belongs to the side we do not see, and the G-buffer
//! turns it over (shaders/voxel.wgsl, `OTHER_SIDE_COS`): the AO hemisphere
//! and the light are then those of the visible side.
//!
//! The scene: a closed room tilted off the grid's axes (so its walls are
//! voxel staircases, whose step faces the old rule, a bend towards the drawn
//! face, left alone), built twice from the same rectangles, wound inwards
//! and wound outwards, and seen from inside. Over the pixels whose surface
//! faces the eye within 40° (where the outward build's stored normal is
//! clearly the other side), the outward build must render the inward one's
//! normals, AO and colours. Negative control: the shipped voxel.wgsl that
//! never turns a normal over, loaded through `VOXSTREAM_DEV_AO_WGSL`; it must
//! differ. This file is its own test binary because that variable is
//! process-wide.

mod ao_support;

use ao_support::{RESOLUTION, render_still, with_voxel_shader};
use glam::DVec3;
use voxstream::reference::analytic::{self, AnalyticScene, Shape};
use voxstream::render::{CameraSpec, RenderOutput};

/// Within 40° of head-on: cos 40° ≈ 0.766, past the rule's 45°.
const FACING: f64 = 0.766;
/// The shipped rule: mean |ΔV| over those pixels, 0.0002 when written.
const MAX_AO_GAP: f64 = 0.01;
/// The control: mean |ΔV| at least this (0.454 when written, with mean
/// n·n 0.19 and 807 of 3702 normals facing away: the old bend towards the
/// drawn face left a wall's normal 70° off where the wall is 20° off the grid).
const MIN_CONTROL_AO_GAP: f64 = 0.2;

fn rotate(p: DVec3) -> DVec3 {
    // 20° about y, then 12° about x: no wall is parallel to a grid plane.
    let (sy, cy) = 20f64.to_radians().sin_cos();
    let (sx, cx) = 12f64.to_radians().sin_cos();
    let q = DVec3::new(cy * p.x + sy * p.z, p.y, -sy * p.x + cy * p.z);
    DVec3::new(q.x, cx * q.y - sx * q.z, sx * q.y + cx * q.z)
}

/// The closed room of `analytic::scenes()` (wound inwards), centred and
/// tilted; `outwards` swaps every rectangle's edges, which turns its
/// triangles over and nothing else.
fn tilted_room(outwards: bool) -> AnalyticScene {
    let (x, y, z) = (2.0, 1.5, 2.5);
    let centre = DVec3::new(x, y, z) * 0.5;
    let walls = [
        ([0.0, 0.0, 0.0], [0.0, 0.0, z], [x, 0.0, 0.0]),
        ([0.0, y, 0.0], [x, 0.0, 0.0], [0.0, 0.0, z]),
        ([0.0, 0.0, 0.0], [x, 0.0, 0.0], [0.0, y, 0.0]),
        ([0.0, 0.0, z], [0.0, y, 0.0], [x, 0.0, 0.0]),
        ([0.0, 0.0, 0.0], [0.0, y, 0.0], [0.0, 0.0, z]),
        ([x, 0.0, 0.0], [0.0, 0.0, z], [0.0, y, 0.0]),
    ];
    let shapes = walls
        .iter()
        .map(|&(c, u, v)| {
            let (u, v) = if outwards { (v, u) } else { (u, v) };
            Shape::Rect {
                corner: rotate(DVec3::from(c) - centre),
                u: rotate(DVec3::from(u)),
                v: rotate(DVec3::from(v)),
            }
        })
        .collect();
    let camera = CameraSpec {
        eye: rotate(DVec3::new(0.6, 0.4, 0.8)).to_array(),
        target: rotate(DVec3::new(-0.7, -0.4, -0.9)).to_array(),
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 60.0,
        near: 0.01,
        far: 20.0,
    };
    analytic::scene_from_shapes(if outwards { "room_outwards" } else { "room_inwards" }, shapes, camera)
}

/// The shipped voxel.wgsl with the turn switched off (the previous rule).
fn never_turning_shader() -> String {
    let src = voxstream_viewer::shaders::VOXEL_WGSL;
    let rule = "const OTHER_SIDE_COS: f32 = -0.70710678;";
    assert_eq!(src.matches(rule).count(), 1, "the rule is no longer where this test switches it off");
    src.replace(rule, "const OTHER_SIDE_COS: f32 = -2.0;")
}

struct Gap {
    pixels: usize,
    /// Mean |V_outwards − V_inwards|.
    ao: f64,
    /// Mean dot of the two normals.
    normal_dot: f64,
    /// Mean |Δ| of the colour channels, 0..1.
    colour: f64,
    /// Pixels of the outward build whose normal faces away from the eye.
    facing_away: usize,
}

/// Compares two renders of the same geometry over the inward render's pixels
/// that face the eye within [`FACING`].
fn gap(eye: DVec3, inwards: &RenderOutput, outwards: &RenderOutput) -> Gap {
    let mut g = Gap { pixels: 0, ao: 0.0, normal_dot: 0.0, colour: 0.0, facing_away: 0 };
    for i in 0..inwards.ao.len() {
        let (a, b) = (inwards.ao[i], outwards.ao[i]);
        if !a.is_finite() || !b.is_finite() {
            continue;
        }
        let p = DVec3::from(inwards.position[i]);
        let to_eye = (eye - p).normalize();
        let n_in = DVec3::from(inwards.normal[i].map(f64::from));
        let n_out = DVec3::from(outwards.normal[i].map(f64::from));
        if n_in.dot(to_eye) < FACING {
            continue;
        }
        g.pixels += 1;
        g.ao += (a as f64 - b as f64).abs();
        g.normal_dot += n_in.dot(n_out);
        g.colour += (0..3)
            .map(|c| (inwards.rgba[4 * i + c] as f64 - outwards.rgba[4 * i + c] as f64).abs() / 255.0)
            .sum::<f64>()
            / 3.0;
        g.facing_away += usize::from(n_out.dot(to_eye) < 0.0);
    }
    let k = g.pixels.max(1) as f64;
    g.ao /= k;
    g.normal_dot /= k;
    g.colour /= k;
    g
}

#[test]
fn a_surface_wound_away_from_the_eye_renders_as_its_seen_side() {
    let store = tempfile::tempdir().unwrap();
    let inwards = tilted_room(false);
    let outwards = tilted_room(true);
    let eye = DVec3::from(inwards.camera.eye);
    let dir_in = analytic::build(&inwards, store.path(), RESOLUTION).expect("build the room wound inwards");
    let dir_out =
        analytic::build(&outwards, store.path(), RESOLUTION).expect("build the room wound outwards");

    let seen_in = render_still(&dir_in, &inwards, None);
    let seen_out = render_still(&dir_out, &outwards, None);
    let shipped = gap(eye, &seen_in, &seen_out);

    let control_shader = never_turning_shader();
    let control = with_voxel_shader(&control_shader, || {
        (render_still(&dir_in, &inwards, None), render_still(&dir_out, &outwards, None))
    });
    let control = gap(eye, &control.0, &control.1);
    for (name, g) in [("shipped", &shipped), ("control (never turned)", &control)] {
        println!(
            "{name}: {} px; mean |ΔV| {:.4}, mean n·n {:.3}, mean |Δcolour| {:.4}, normals facing away {}",
            g.pixels, g.ao, g.normal_dot, g.colour, g.facing_away
        );
    }

    assert!(
        shipped.pixels >= 2000,
        "only {} pixels face the eye: the camera misses the room",
        shipped.pixels
    );
    assert_eq!(shipped.facing_away, 0, "normals of the outward-wound room still face away from the eye");
    assert!(
        shipped.normal_dot > 0.99,
        "the outward-wound room's normals differ: mean n·n {:.3}",
        shipped.normal_dot
    );
    assert!(
        shipped.ao <= MAX_AO_GAP,
        "the winding changes the AO: mean |ΔV| {:.4} (at most {MAX_AO_GAP})",
        shipped.ao
    );
    assert!(shipped.colour <= 0.01, "the winding changes the colours: mean |Δ| {:.4}", shipped.colour);
    // The scene must exercise the rule: without it, the outward build's step faces keep normals facing away.
    assert!(control.facing_away > 0, "without the rule no normal faces away: the scene does not test it");
    assert!(
        control.ao >= MIN_CONTROL_AO_GAP,
        "without the rule the winding hardly changes the AO (mean |ΔV| {:.4}): the test cannot fail",
        control.ao
    );
}
