//! The crevice probe (shaders/ao.wgsl, `crevice_bend`). Where a surface
//! hangs a few cells over a point, the cones come back down to their own axes
//! once those rise above the start offset. Without that every cone starts
//! half-way up the gap, and the floor under a resting sphere comes out far
//! too dark.
//!
//! Checked against exact values over the floor pixels of the crevice around
//! the contact of the sphere on a plane. The probe must lower the mean
//! |V − exact| by at least [`MIN_GAIN`] against the negative control: a copy
//! of the shipped shader with the bend at 0 (loaded through
//! `VOXSTREAM_DEV_AO_WGSL`, so this file is its own test binary). On open
//! floor, where nothing hangs over a point, the probe must change nothing.

mod ao_support;

use ao_support::{
    RESOLUTION, ao_wgsl_without_crevice_probe, error_where, floor_ring, render_still, with_ao_shader,
};
use voxstream::reference::analytic;

/// How much the probe must lower the mean |V − exact| in the crevice
/// (0.042 when written: the renders are deterministic).
const MIN_GAIN: f64 = 0.02;

#[test]
fn cones_under_an_overhang_come_back_to_their_axes() {
    let scene = analytic::scenes().into_iter().find(|s| s.name == "sphere_on_plane").expect("scene");
    let store = tempfile::tempdir().unwrap();
    let dir = analytic::build(&scene, store.path(), RESOLUTION).expect("build");
    // The crevice, where the sphere's underside is 0.06–0.13 above the
    // floor, and open floor beyond the probe's reach.
    let crevice = floor_ring(0.25, 0.4);
    let open = floor_ring(0.8, 1.5);
    let out = render_still(&dir, &scene, None);
    let (pixels, mae, exact_v) = error_where(&scene, &out, crevice);

    let control = with_ao_shader(&ao_wgsl_without_crevice_probe(), || render_still(&dir, &scene, None));
    let (_, control_mae, _) = error_where(&scene, &control, crevice);

    println!(
        "sphere on a plane: {pixels} crevice floor px, exact V {exact_v:.3}; mean |V − exact| with the probe {mae:.4}, without (control) {control_mae:.4}"
    );
    assert!(pixels >= 40, "only {pixels} floor pixels in the crevice: the camera misses it");
    assert!(
        exact_v < 0.8,
        "the sphere hardly occludes the crevice (exact V {exact_v:.3}): the test sees nothing"
    );
    assert!(
        control_mae - mae >= MIN_GAIN,
        "the probe does not help in the crevice: mean |V − exact| {mae:.4} against {control_mae:.4} without it (need {MIN_GAIN} less)"
    );

    // Open floor: nothing within the probe's reach, so not one pixel changes.
    let mut open_pixels = 0;
    for (i, (p, n)) in out.position.iter().zip(&out.normal).enumerate() {
        if out.ao[i].is_finite() && open(p, n) {
            open_pixels += 1;
            assert_eq!(out.ao[i], control.ao[i], "open floor at {p:?} changed with the probe");
        }
    }
    assert!(open_pixels >= 200, "only {open_pixels} open floor pixels");
}
