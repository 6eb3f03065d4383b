//! Level of detail that does not depend on the build's resolution (issue 10: bytes to converge
//! "flat as the resolution grows"). The same sphere built at 128 and at 512 voxels an edge, seen
//! from the same place at 1 px: the traversal must want about the same number of voxels from
//! both, since they are the same surface. The control, the build's bound alone
//! (`TraverseParams::strict`), wants several times more from the finer build: its coarse cubes
//! measure as less accurate, because the surface clips some of them at a corner.

use glam::Vec3;
use voxstream::reference::analytic;
use voxstream_viewer::camera::OrbitCamera;
use voxstream_viewer::select::{ViewParams, lod_error};
use voxstream_viewer::traverse::{TraverseParams, traverse};

/// The view's height: small enough that the 128 build's view stops above its level 0 (at more
/// pixels the coarse build runs out of detail and any rule wants all of it).
const HEIGHT_PX: f32 = 96.0;

/// Voxels the view wants at 1 px from the lone sphere built at `resolution`, and the most
/// (capped) error of a wanted block in pixels.
fn wanted_voxels(resolution: u32, strict: bool) -> (u64, usize) {
    let scene = analytic::scenes().into_iter().find(|s| s.name == "lone_sphere").expect("lone_sphere");
    let dir = tempfile::tempdir().unwrap();
    let scene_dir = analytic::build(&scene, dir.path(), resolution).unwrap();
    let stored = voxstream::store::open_scene(scene_dir.parent().unwrap(), "lone-sphere").unwrap();
    let index = stored.index.read().clone();
    // The same physical view for every build: the grid framed.
    let grid = resolution as f32;
    let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(grid));
    let view = ViewParams {
        view_proj: cam.view_proj(16.0 / 9.0),
        eye: cam.eye(),
        focal_pixels: cam.focal_pixels(HEIGHT_PX),
    };
    let params = TraverseParams { strict, ..Default::default() };
    let t = traverse(&index, &stored.manifest.root.key, &view, &params, &Default::default());
    assert_eq!(t.held_by_budget, 0);
    for k in &t.blocks {
        let e = index.block(k).unwrap();
        assert!(lod_error(e) <= e.geometric_error && lod_error(e) <= 0.8661 * (1u64 << k.level) as f32);
    }
    (t.blocks.iter().map(|k| index.block(k).unwrap().voxels as u64).sum(), t.blocks.len())
}

#[test]
fn a_view_wants_the_same_detail_from_a_coarse_and_a_fine_build() {
    let (coarse, coarse_blocks) = wanted_voxels(128, false);
    let (fine, fine_blocks) = wanted_voxels(512, false);
    let ratio = fine as f64 / coarse as f64;
    eprintln!(
        "capped: {coarse} voxels ({coarse_blocks} blocks) at 128, {fine} ({fine_blocks}) at 512: ×{ratio:.2}"
    );
    assert!(ratio < 1.5, "the finer build wants {ratio:.2}× the voxels");
    // Control: the bound alone refines the finer build's view further.
    let (coarse_strict, _) = wanted_voxels(128, true);
    let (fine_strict, _) = wanted_voxels(512, true);
    let strict_ratio = fine_strict as f64 / coarse_strict as f64;
    eprintln!("strict: {coarse_strict} voxels at 128, {fine_strict} at 512: ×{strict_ratio:.2}");
    assert!(strict_ratio > 2.0, "the control wants only {strict_ratio:.2}× the voxels");
}
