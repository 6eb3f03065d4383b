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
//!
//! Both renders run with the crevice probe off (`crevice_bend`, tested in
//! `ao_crevice.rs`): under the sphere's overhang it brings the cones down to
//! their axes, and what is left of this rule's gain there (0.0004) would say
//! nothing about the rule.

mod ao_support;

use ao_support::{
    RESOLUTION, ao_wgsl_without_crevice_probe, error_where, floor_ring, render_still, with_ao_shader,
};
use voxstream::reference::analytic;

/// How much the rule must lower the mean |V − exact| in the ring around the
/// contact (0.011 when written: the renders are deterministic).
const MIN_GAIN: f64 = 0.005;

#[test]
fn a_level_on_the_grids_face_holds_samples_up_to_it() {
    let scene = analytic::scenes().into_iter().find(|s| s.name == "sphere_on_plane").expect("scene");
    let store = tempfile::tempdir().unwrap();
    let dir = analytic::build(&scene, store.path(), RESOLUTION).expect("build");
    // The half shadow around the contact, where the floor's occlusion comes
    // from cones that skim it.
    let ring = (0.3, 0.5);
    let in_ring = floor_ring(ring.0, ring.1);
    let src = ao_wgsl_without_crevice_probe();
    let out = with_ao_shader(&src, || render_still(&dir, &scene, None));
    let (pixels, mae, exact_v) = error_where(&scene, &out, in_ring);

    // Negative control: the level must hold all eight cells of a read, even
    // those beyond the grid (the tracer before the rule).
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
    let control = with_ao_shader(&switched, || render_still(&dir, &scene, None));
    let (_, control_mae, _) = error_where(&scene, &control, in_ring);

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
