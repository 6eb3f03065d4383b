//! Translation invariance: the koala moved by 1e3, 1e6 and 1e7 units gives the
//! identical voxel set (and identical encoded blocks).
//!
//! The offsets must be exactly representable sums, or the input itself differs:
//! the koala's coordinates are snapped to a 2^-16 lattice first, so `p + 1e7`
//! is exact in f64 (24 + 16 bits < 53).

use std::path::Path;

use voxstream::pipeline::pyramid::build_levels;
use voxstream::pipeline::read::{TriangleMesh, read_mesh};
use voxstream::pipeline::voxelize::{choose_frame, voxelize};
use voxstream::pipeline::write::packed_block;
use voxstream_format::encode_block;

fn koala_on_lattice() -> TriangleMesh {
    let (mut mesh, _) = read_mesh(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")).unwrap();
    for p in &mut mesh.positions {
        *p = p.map(|c| (c * 65536.0).round() / 65536.0);
    }
    mesh
}

fn encoded_levels(mesh: &TriangleMesh, resolution: u32) -> Vec<Vec<Vec<u8>>> {
    let frame = choose_frame(mesh, resolution).unwrap();
    let (level0, _) = voxelize(mesh, &frame).unwrap();
    build_levels(level0, resolution)
        .iter()
        .map(|level| level.iter().map(|b| encode_block(&packed_block(b))).collect())
        .collect()
}

#[test]
fn translated_koala_gives_identical_voxels() {
    let mesh = koala_on_lattice();
    let reference = encoded_levels(&mesh, 256);
    let voxels: usize =
        reference[0].iter().map(|b| voxstream_format::decode_block(b).unwrap().voxels.len()).sum();
    assert!(voxels > 50_000, "only {voxels} voxels");
    for offset in [[1e3, 0.0, 0.0], [0.0, -1e6, 1e6], [1e7, 1e7, -1e7]] {
        let mut moved = mesh.clone();
        for p in &mut moved.positions {
            for a in 0..3 {
                let q = p[a] + offset[a];
                assert_eq!(q - offset[a], p[a], "offset {offset:?} is not exact for {p:?}");
                p[a] = q;
            }
        }
        let frame = choose_frame(&moved, 256).unwrap();
        assert_eq!(frame.origin[0] - offset[0], choose_frame(&mesh, 256).unwrap().origin[0]);
        assert!(encoded_levels(&moved, 256) == reference, "offset {offset:?} changed the voxels");
    }
}

#[test]
fn a_non_lattice_shift_is_still_close() {
    // Not bit-identical input, so only nearly identical output: a guard that the
    // frame follows the mesh rather than the world origin.
    let mesh = koala_on_lattice();
    let mut moved = mesh.clone();
    for p in &mut moved.positions {
        p[0] += 1e7 + 0.1;
    }
    let count = |m: &TriangleMesh| -> usize {
        let frame = choose_frame(m, 256).unwrap();
        let (blocks, _) = voxelize(m, &frame).unwrap();
        blocks.iter().map(|b| b.voxels.len()).sum()
    };
    let (a, b) = (count(&mesh), count(&moved));
    assert!((a as f64 - b as f64).abs() / (a as f64) < 0.001, "{a} vs {b}");
}
