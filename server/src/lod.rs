//! LOD: exposed-face masks and the 2³ merge that builds coarser levels
//! (seed 003 §3): a parent voxel exists if any of its 8 children does, its
//! face mask is the OR of theirs and its normal sum is the sum of theirs.
//!
//! Skirts: a level-0 face on a block's boundary is always marked exposed,
//! whatever the neighbour block holds, so a block next to a coarser or finer
//! neighbour never shows a crack. The OR carries those faces upwards.

use std::collections::BTreeMap;

use rayon::prelude::*;
use voxstream_format::{BLOCK_SIZE, BLOCK_VOXELS, BlockKey, Face, demorton3, morton3};

use crate::voxelize::{BuildVoxel, SparseBlock};

/// Block-local position of a voxel.
pub fn local_position(v: &BuildVoxel) -> [u32; 3] {
    demorton3(v.morton)
}

/// Marks each voxel's faces whose neighbour inside the block is empty, and
/// every face on the block boundary (the skirt).
pub fn mark_exposed_faces(block: &mut SparseBlock) {
    let mut occupied = vec![0u64; BLOCK_VOXELS / 64];
    for v in &block.voxels {
        occupied[v.morton as usize / 64] |= 1 << (v.morton % 64);
    }
    let is_set = |p: [u32; 3]| {
        let m = morton3(p[0], p[1], p[2]);
        occupied[m as usize / 64] & (1 << (m % 64)) != 0
    };
    for v in &mut block.voxels {
        let p = demorton3(v.morton);
        let mut mask = 0u8;
        for f in Face::ALL {
            let a = f.axis();
            let exposed = if f.sign() < 0 {
                p[a] == 0 || {
                    let mut q = p;
                    q[a] -= 1;
                    !is_set(q)
                }
            } else {
                p[a] == BLOCK_SIZE - 1 || {
                    let mut q = p;
                    q[a] += 1;
                    !is_set(q)
                }
            };
            if exposed {
                mask |= f.bit();
            }
        }
        v.faces = mask;
    }
    // A voxel buried on all six sides is never drawn; dropping it keeps blocks small.
    block.voxels.retain(|v| v.faces != 0);
}

/// Builds the parent block `key` from its children (any may be missing).
pub fn merge_children(key: BlockKey, children: &[&SparseBlock]) -> Option<SparseBlock> {
    // Dense accumulator indexed by parent-local Morton; `faces == 0` marks an empty slot
    // because merged children only ever hold voxels with exposed faces.
    let mut acc = vec![BuildVoxel::EMPTY; BLOCK_VOXELS];
    let mut any = false;
    for child in children {
        debug_assert_eq!(child.key.parent(), key);
        let octant = child.key.coord().map(|c| (c & 1) * (BLOCK_SIZE / 2));
        for v in &child.voxels {
            let p = demorton3(v.morton);
            let q = [0, 1, 2].map(|a| octant[a] + p[a] / 2);
            let m = morton3(q[0], q[1], q[2]);
            let slot = &mut acc[m as usize];
            slot.morton = m;
            slot.faces |= v.faces;
            for a in 0..3 {
                slot.normal_sum[a] += v.normal_sum[a];
                slot.color_sum[a] += v.color_sum[a];
            }
            slot.color_weight += v.color_weight;
            any = true;
        }
    }
    if !any {
        return None;
    }
    // Copied out rather than `into_iter().collect()`, which would keep the 9 MB
    // accumulator as every coarse block's allocation (in-place collect).
    let voxels = acc.iter().filter(|v| v.faces != 0).copied().collect();
    Some(SparseBlock { key, voxels })
}

/// Number of levels for a grid: enough that the coarsest is one block.
pub fn level_count(resolution: u32) -> u8 {
    let mut levels = 1;
    let mut r = resolution;
    while r > BLOCK_SIZE {
        r /= 2;
        levels += 1;
    }
    levels
}

/// Turns level-0 blocks (faces not yet marked) into every level, finest first.
pub fn build_levels(mut level0: Vec<SparseBlock>, resolution: u32) -> Vec<Vec<SparseBlock>> {
    level0.par_iter_mut().for_each(mark_exposed_faces);
    level0.retain(|b| !b.voxels.is_empty());
    let mut levels = vec![level0];
    for _ in 1..level_count(resolution) {
        let finer = levels.last().expect("level 0 exists");
        let mut groups: BTreeMap<BlockKey, Vec<&SparseBlock>> = BTreeMap::new();
        for b in finer {
            groups.entry(b.key.parent()).or_default().push(b);
        }
        let coarser: Vec<SparseBlock> =
            groups.into_par_iter().filter_map(|(key, children)| merge_children(key, &children)).collect();
        levels.push(coarser);
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block_of(key: BlockKey, points: &[[u32; 3]]) -> SparseBlock {
        let mut voxels: Vec<BuildVoxel> = points
            .iter()
            .map(|p| BuildVoxel {
                morton: morton3(p[0], p[1], p[2]),
                normal_sum: [0.0, 0.0, 1.0],
                ..BuildVoxel::EMPTY
            })
            .collect();
        voxels.sort_by_key(|v| v.morton);
        SparseBlock { key, voxels }
    }

    #[test]
    fn faces_between_neighbours_are_hidden_and_skirts_kept() {
        let mut b = block_of(BlockKey::new(0, 0, 0, 0), &[[10, 10, 10], [11, 10, 10], [0, 5, 5]]);
        mark_exposed_faces(&mut b);
        let by_pos = |p: [u32; 3]| b.voxels.iter().find(|v| local_position(v) == p).unwrap().faces;
        assert_eq!(by_pos([10, 10, 10]), 63 & !Face::PosX.bit());
        assert_eq!(by_pos([11, 10, 10]), 63 & !Face::NegX.bit());
        // On the x = 0 boundary: the -x face stays as a skirt.
        assert_eq!(by_pos([0, 5, 5]) & Face::NegX.bit(), Face::NegX.bit());
    }

    #[test]
    fn buried_voxels_are_dropped() {
        let mut pts = Vec::new();
        for z in 20..23 {
            for y in 20..23 {
                for x in 20..23 {
                    pts.push([x, y, z]);
                }
            }
        }
        let mut b = block_of(BlockKey::new(0, 0, 0, 0), &pts);
        mark_exposed_faces(&mut b);
        assert_eq!(b.voxels.len(), 26);
        assert!(b.voxels.iter().all(|v| local_position(v) != [21, 21, 21]));
    }

    #[test]
    fn merge_ors_faces_and_places_octants() {
        let mut a = block_of(BlockKey::new(0, 1, 0, 0), &[[0, 0, 0], [1, 1, 1]]);
        let mut b = block_of(BlockKey::new(0, 0, 1, 0), &[[63, 63, 63]]);
        mark_exposed_faces(&mut a);
        mark_exposed_faces(&mut b);
        let parent = merge_children(BlockKey::new(1, 0, 0, 0), &[&a, &b]).unwrap();
        let got: Vec<([u32; 3], u8)> = parent.voxels.iter().map(|v| (local_position(v), v.faces)).collect();
        // a's two voxels collapse into parent (32, 0, 0); b's lands at (31, 63, 31).
        assert_eq!(got, vec![([32, 0, 0], 63), ([31, 63, 31], 63)]);
        assert_eq!(parent.voxels[0].normal_sum, [0.0, 0.0, 2.0]);
    }

    #[test]
    fn level_counts() {
        assert_eq!(level_count(32), 1);
        assert_eq!(level_count(64), 1);
        assert_eq!(level_count(512), 4);
    }
}
