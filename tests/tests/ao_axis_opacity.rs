//! Opacity per axis (shaders/ao.wgsl, `cone_axis_weights`; viewer-wasm's
//! `clipmap::voxel_axes`): a clipmap cell holds its opacity along x, y and z,
//! a voxel blocking the axes of its exposed faces, and a cone weighs them by
//! |dir_a| / max |dir|. A sheet then blocks the cones that cross it, not
//! those that run along it through a cell it passes.
//!
//! Checked against exact values (the analytic quadrature at the render's own
//! points) where that shows:
//! - the parallel plates (two sheets 0.2 apart, R 0.3: every cone of every
//!   point meets a plate, many at a grazing angle), over the whole image;
//! - floor pixels in the voxel next to the foot of a wall one voxel thick,
//!   whose cones running along the wall stay within the half cell of opacity
//!   the trilinear tent spreads past the wall's faces.
//!
//! In each, the mean |V − exact| must be lower by at least its `MIN_GAIN`
//! than the negative control's: the same tracer with every axis counted fully
//! (a cell opaque along any axis is opaque to every cone, the previous
//! behaviour), a copy of the shipped shader loaded through
//! `VOXSTREAM_DEV_AO_WGSL`. This file is its own test binary because that
//! variable is process-wide.

mod ao_support;

use ao_support::{RESOLUTION, error_where, render_still, with_ao_shader};
use voxstream::reference::analytic::{self, Shape};

/// The plates: 0.0082 when written (0.0392 against 0.0474 at 96×64).
const PLATES_MIN_GAIN: f64 = 0.004;
/// The wall's foot: 0.066 when written (0.066 against 0.132).
const WALL_FOOT_MIN_GAIN: f64 = 0.02;

/// The shipped shader with every axis counted fully.
fn isotropic_shader() -> String {
    let src = voxstream_viewer::shaders::AO_WGSL;
    let weights = "    let a = abs(dir);\n    return a / max(max(a.x, a.y), max(a.z, 1e-6));";
    assert_eq!(
        src.matches(weights).count(),
        1,
        "the axis weights are no longer where this test switches them off"
    );
    src.replace(weights, "    return vec3<f32>(1.0);")
}

#[test]
fn cones_along_a_sheet_are_not_blocked_by_it() {
    let control_shader = isotropic_shader();

    let plates = analytic::scenes().into_iter().find(|s| s.name == "parallel_plates").expect("the plates");
    let store = tempfile::tempdir().unwrap();
    let dir = analytic::build(&plates, store.path(), RESOLUTION).expect("build the plates");
    let everywhere = |_: &[f64; 3], _: &[f32; 3]| true;
    let (pixels, mae, exact_v) = error_where(&plates, &render_still(&dir, &plates, None), everywhere);
    let control = with_ao_shader(&control_shader, || render_still(&dir, &plates, None));
    let (_, control_mae, _) = error_where(&plates, &control, everywhere);
    println!(
        "parallel plates: {pixels} px, exact V {exact_v:.3}; mean |V − exact| per axis {mae:.4}, every axis counted (control) {control_mae:.4}"
    );
    assert!(pixels >= 3000, "only {pixels} pixels: the camera misses the plates");
    assert!(
        exact_v < 0.8,
        "the plates hardly occlude each other (exact V {exact_v:.3}): the test sees nothing"
    );
    assert!(
        control_mae - mae >= PLATES_MIN_GAIN,
        "opacity per axis does not lower the error on the plates: mean |V − exact| {mae:.4} against {control_mae:.4} with every axis counted (need {PLATES_MIN_GAIN} less)"
    );

    let rect =
        |c: [f64; 3], u: [f64; 3], v: [f64; 3]| Shape::Rect { corner: c.into(), u: u.into(), v: v.into() };
    // The bounding cube [-2, 2]³ at 256 voxels, 1/64 each; the wall sits
    // mid-voxel, so the conservative voxelization makes it one voxel thick.
    let voxel = 4.0 / RESOLUTION as f64;
    let x_wall = 0.5 * voxel;
    let floor = rect([-2.0, 0.0, -2.0], [0.0, 0.0, 4.0], [4.0, 0.0, 0.0]);
    let wall = rect([x_wall, 0.0, -2.0], [0.0, 1.5, 0.0], [0.0, 0.0, 4.0]);
    // Looking down at the wall's foot from the open side, along the wall.
    let camera = voxstream::render::CameraSpec {
        eye: [0.5, 0.45, 0.9],
        target: [x_wall + 0.05, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 50.0,
        near: 0.01,
        far: 20.0,
    };
    let scene = analytic::scene_from_shapes("wall_foot", vec![floor, wall], camera);
    let dir = analytic::build(&scene, store.path(), RESOLUTION).expect("build the wall");
    // Floor pixels in the voxel next to the wall's voxels (which end at x = voxel).
    let at_foot = |p: &[f64; 3], n: &[f32; 3]| n[1] > 0.9 && p[0] >= voxel && p[0] - voxel < voxel;
    let (pixels, mae, exact_v) = error_where(&scene, &render_still(&dir, &scene, Some(0.4)), at_foot);
    let control = with_ao_shader(&control_shader, || render_still(&dir, &scene, Some(0.4)));
    let (_, control_mae, _) = error_where(&scene, &control, at_foot);
    println!(
        "wall foot: {pixels} px, exact V {exact_v:.3}; mean |V − exact| per axis {mae:.4}, every axis counted (control) {control_mae:.4}"
    );
    assert!(pixels >= 30, "only {pixels} pixels at the wall's foot: the camera misses it");
    assert!(exact_v < 0.9, "the wall hardly occludes its foot (exact V {exact_v:.3}): the test sees nothing");
    assert!(
        control_mae - mae >= WALL_FOOT_MIN_GAIN,
        "opacity per axis does not lower the error at the wall's foot: mean |V − exact| {mae:.4} against {control_mae:.4} with every axis counted (need {WALL_FOOT_MIN_GAIN} less)"
    );
}
