//! LOD: exposed-face masks and the 2³ merge that builds coarser levels
//! (seed 003 §3): a parent voxel exists if any of its 8 children does, its
//! face mask is the OR of theirs and its normal and colour sums are the sums
//! of theirs (averaged when packed: `write::packed_block`).
//!
//! Skirts: a level-0 face on a block's boundary is always marked exposed,
//! whatever the neighbour block holds, so a block next to a coarser or finer
//! neighbour never shows a crack. The OR carries those faces upwards.
//!
//! Two measured quantities travel up with each voxel:
//!
//! - **solid**: how many level-0 voxels below it are occupied. Level-0 voxels
//!   buried on all six sides are never drawn, but they are occupied, and the
//!   viewer's ambient occlusion wants solidity, so they are kept through the
//!   merge (faces = 0) and only dropped at the end. Coverage = solid / 8^level.
//! - **error**: an upper bound, in grid units, on the distance from any point
//!   of the voxel's cube to the nearest occupied level-0 voxel below it (the
//!   one-sided Hausdorff distance from what is drawn to what it stands for).
//!   Level 0: 0. A parent of child edge `s` whose children have errors ≤ `e`:
//!   a point inside an occupied child is within `e`; a point inside an empty
//!   octant is within `s·k + e`, `k` = 1, √2 or √3 for the nearest occupied
//!   octant sharing a face, an edge or only a corner. So
//!   `error(parent) = min(e + s·k_max(mask), parent diagonal)`, which is never
//!   smaller than any child's error: **error grows monotonically with level**,
//!   and so does a block's error, the maximum over its drawn voxels.

use std::collections::BTreeMap;

use rayon::prelude::*;
use voxstream_format::{BLOCK_SIZE, BLOCK_VOXELS, BlockKey, demorton3, morton3};

use crate::pipeline::voxelize::{BuildVoxel, SparseBlock};

/// A voxel on any level while the LOD is built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LodVoxel {
    /// Position, sums and face mask; `faces == 0` only for buried voxels, which
    /// [`build_levels`] drops at the end.
    pub voxel: BuildVoxel,
    /// Occupied level-0 voxels below this one (buried ones included).
    pub solid: u32,
    /// Grid units; see the module docs.
    pub error: f32,
}

impl LodVoxel {
    /// Folds a child voxel into this parent voxel: faces OR, sums add, the
    /// error is the worst child's. Both pyramid paths use it, so their blocks
    /// stay byte-identical.
    fn absorb(&mut self, child: &LodVoxel) {
        self.voxel.faces |= child.voxel.faces;
        for a in 0..3 {
            self.voxel.normal_sum[a] += child.voxel.normal_sum[a];
            self.voxel.color_sum[a] += child.voxel.color_sum[a];
        }
        self.voxel.color_weight += child.voxel.color_weight;
        self.solid += child.solid;
        self.error = self.error.max(child.error);
    }
}

/// One block of any level, voxels in strictly increasing Morton order.
#[derive(Debug, Clone, PartialEq)]
pub struct LodBlock {
    pub key: BlockKey,
    pub voxels: Vec<LodVoxel>,
}

impl LodBlock {
    /// Largest voxel error: the block's geometric error in grid units.
    pub fn geometric_error(&self) -> f32 {
        self.voxels.iter().filter(|v| v.voxel.faces != 0).map(|v| v.error).fold(0.0, f32::max)
    }
}

/// Block-local position of a voxel.
pub fn local_position(v: &BuildVoxel) -> [u32; 3] {
    demorton3(v.morton)
}

/// Marks each voxel's faces whose neighbour inside the block is empty, and
/// every face on the block boundary (the skirt). Voxels buried on all six
/// sides get an empty mask and stay (their solidity counts for coverage).
pub fn mark_exposed_faces(block: &mut SparseBlock) {
    mark_faces(&mut block.voxels);
}

/// [`mark_exposed_faces`] for a level-0 block already in pyramid form.
pub fn mark_exposed_faces_lod(block: &mut LodBlock) {
    mark_faces(&mut block.voxels);
}

trait HasVoxel {
    fn build_voxel(&mut self) -> &mut BuildVoxel;
}

impl HasVoxel for BuildVoxel {
    fn build_voxel(&mut self) -> &mut BuildVoxel {
        self
    }
}

impl HasVoxel for LodVoxel {
    fn build_voxel(&mut self) -> &mut BuildVoxel {
        &mut self.voxel
    }
}

fn mark_faces<V: HasVoxel>(voxels: &mut [V]) {
    for_each_exposed_mask(voxels, |v, exposed| v.faces = exposed);
}

/// Keeps, of a coarse voxel's faces (the OR of its children's), those that face an empty voxel
/// of its own level or the block's boundary (the skirt): the rest lie against an occupied
/// neighbour's cube, which hides them. The OR holds every kept face (a child either faces the
/// empty neighbour cell itself or faces an empty octant of its own parent), so the masks become
/// what the codec predicts from occupancy alone: on coarse levels the face column was a quarter
/// of a block's bytes, and the hidden faces a share of the faces the viewer expands. A voxel
/// hidden on every side keeps its OR: it is drawn as before rather than dropped, and its coverage
/// still reaches the viewer. Level 0's masks are already exact ([`mark_exposed_faces`]).
///
/// Returns each voxel's exposed mask (the codec's prediction over the block's voxels, buried
/// ones included; at level 0, the masks themselves), for [`drop_buried`].
pub fn hide_covered_faces(block: &mut LodBlock) -> Vec<u8> {
    if block.key.level == 0 {
        return block.voxels.iter().map(|v| v.voxel.faces).collect();
    }
    let mut all = Vec::with_capacity(block.voxels.len());
    for_each_exposed_mask(&mut block.voxels, |v, exposed| {
        let kept = v.faces & exposed;
        if kept != 0 {
            v.faces = kept;
        }
        all.push(exposed);
    });
    all
}

/// Calls `set` with each voxel and its exposed-face mask: faces whose neighbour inside the
/// block is empty (buried voxels count as occupied), and every face on the block's boundary.
fn for_each_exposed_mask<V: HasVoxel>(voxels: &mut [V], mut set: impl FnMut(&mut BuildVoxel, u8)) {
    let mut occupied = vec![0u64; BLOCK_VOXELS / 64];
    for v in voxels.iter_mut() {
        let m = v.build_voxel().morton;
        occupied[m as usize / 64] |= 1 << (m % 64);
    }
    let is_set = |m: u32| occupied[m as usize / 64] & (1 << (m % 64)) != 0;
    for v in voxels {
        let v = v.build_voxel();
        let m = v.morton;
        let mut mask = 0u8;
        for a in 0..3 {
            let bit = 1u32 << a;
            let (below, above) = if m & bit == 0 {
                (neighbour_below(m, a).is_none_or(|n| !is_set(n)), !is_set(m | bit))
            } else {
                (!is_set(m & !bit), neighbour_above(m, a).is_none_or(|n| !is_set(n)))
            };
            // Face bits: 2a is the negative side of axis a, 2a + 1 the positive.
            mask |= (below as u8) << (2 * a) | (above as u8) << (2 * a + 1);
        }
        set(v, mask);
    }
}

/// Each axis's bits of a block-local Morton code.
const AXIS_MASKS: [u32; 3] = [0o111111, 0o111111 << 1, 0o111111 << 2];

/// The voxel one step down axis `a` from Morton code `m`, if inside the block.
/// The axis's lowest bit says which side shares the voxel's 2³ cell: that
/// neighbour is the bit flipped; the other lies across the cell, found by
/// decrementing the axis's bits in place (the borrow runs through the other
/// axes' bits, which are masked off and put back).
#[inline]
fn neighbour_below(m: u32, a: usize) -> Option<u32> {
    let axis = AXIS_MASKS[a];
    let along = m & axis;
    (along != 0).then(|| (along.wrapping_sub(1) & axis) | (m & !axis))
}

/// The voxel one step up axis `a` from Morton code `m`, if inside the block
/// (the carry as in [`neighbour_below`]).
#[inline]
fn neighbour_above(m: u32, a: usize) -> Option<u32> {
    let axis = AXIS_MASKS[a];
    (m & axis != axis).then(|| ((m | !axis).wrapping_add(1) & axis) | (m & !axis))
}

/// Drops `block`'s buried voxels (`faces == 0`: their part, coverage, is done)
/// and returns, for each voxel kept, the face mask the codec predicts from the
/// kept voxels alone ([`voxstream_format::predicted_face_masks`]), given
/// `exposed`, each voxel's prediction over all of them: a kept neighbour of a
/// dropped voxel now faces an empty cell. Handing it to the codec spares it
/// a second pass of neighbour lookups over the block.
pub fn drop_buried(block: &mut LodBlock, exposed: Vec<u8>) -> Vec<u8> {
    debug_assert_eq!(exposed.len(), block.voxels.len());
    let mut dropped = Vec::new();
    let mut prediction = Vec::with_capacity(block.voxels.len());
    for (v, &e) in block.voxels.iter().zip(&exposed) {
        if v.voxel.faces == 0 {
            dropped.push(v.voxel.morton);
        } else {
            prediction.push(e);
        }
    }
    drop(exposed);
    if dropped.is_empty() {
        return prediction;
    }
    block.voxels.retain(|v| v.voxel.faces != 0);
    // The kept voxels as a bitmap with each word's rank (kept voxels before it):
    // a neighbour's index is then two lookups, not a search.
    let mut kept = vec![0u64; BLOCK_VOXELS / 64];
    for v in &block.voxels {
        let m = v.voxel.morton;
        kept[m as usize / 64] |= 1 << (m % 64);
    }
    let mut rank = Vec::with_capacity(kept.len());
    let mut before = 0u32;
    for w in &kept {
        rank.push(before);
        before += w.count_ones();
    }
    let mut expose = |n: Option<u32>, face: u8| {
        if let Some(n) = n {
            let (word, bit) = (kept[n as usize / 64], n % 64);
            if word >> bit & 1 != 0 {
                let i = rank[n as usize / 64] + (word & ((1 << bit) - 1)).count_ones();
                prediction[i as usize] |= 1 << face;
            }
        }
    };
    for &d in &dropped {
        for a in 0..3 {
            // The neighbour below faces the dropped voxel with its positive side.
            expose(neighbour_below(d, a), 2 * a as u8 + 1);
            expose(neighbour_above(d, a), 2 * a as u8);
        }
    }
    prediction
}

/// For each mask of occupied octants, the largest over empty octants of the
/// distance factor (1, √2, √3) to the nearest occupied octant; 0 when full.
fn empty_octant_reach(mask: u8) -> f32 {
    let mut worst = 0f32;
    for o in 0..8u8 {
        if mask & (1 << o) != 0 {
            continue;
        }
        let nearest = (0..8u8)
            .filter(|c| mask & (1 << c) != 0)
            .map(|c| ((o ^ c).count_ones() as f32).sqrt())
            .fold(f32::INFINITY, f32::min);
        worst = worst.max(nearest);
    }
    worst
}

/// Builds the parent block `key` from its children (any may be missing).
pub fn merge_children(key: BlockKey, children: &[&LodBlock]) -> Option<LodBlock> {
    debug_assert!(key.level > 0);
    // Dense accumulator indexed by parent-local Morton; `solid == 0` marks an empty slot.
    let empty = LodVoxel { voxel: BuildVoxel::EMPTY, solid: 0, error: 0.0 };
    let mut acc = vec![(empty, 0u8); BLOCK_VOXELS];
    let mut any = false;
    for child in children {
        debug_assert_eq!(child.key.parent(), key);
        let octant = child.key.coord().map(|c| (c & 1) * (BLOCK_SIZE / 2));
        for v in &child.voxels {
            let p = demorton3(v.voxel.morton);
            let q = [0, 1, 2].map(|a| octant[a] + p[a] / 2);
            let m = morton3(q[0], q[1], q[2]);
            let (slot, mask) = &mut acc[m as usize];
            slot.voxel.morton = m;
            slot.absorb(v);
            *mask |= 1 << (v.voxel.morton & 7);
            any = true;
        }
    }
    if !any {
        return None;
    }
    let reach: [f32; 256] = std::array::from_fn(|m| empty_octant_reach(m as u8));
    let child_edge = (1u64 << (key.level - 1)) as f32;
    let diagonal = 2.0 * child_edge * 3f32.sqrt();
    // Copied out rather than `into_iter().collect()`, which could keep the multi-MB
    // accumulator as every coarse block's allocation (in-place collect).
    let voxels = acc
        .iter()
        .filter(|(v, _)| v.solid != 0)
        .map(|&(mut v, mask)| {
            v.error = (v.error + child_edge * reach[mask as usize]).min(diagonal);
            v
        })
        .collect();
    Some(LodBlock { key, voxels })
}

/// The streaming pyramid: level-0 blocks go in one at a time, in the Morton
/// order of their block coordinates ([`block_morton`]), and every block of
/// every level comes out as soon as it is complete, children before parents.
///
/// A child's voxels fall into one octant of its parent, and the 8 voxels of
/// one parent voxel are 8 consecutive child Morton codes, so each child is
/// downsampled into its parent in one linear pass as it arrives and then
/// dropped. Children of one parent arrive in octant order, so the parent's
/// voxels stay sorted. Sums run in the child's Morton order from zero, as in
/// [`merge_children`], so results are bit-identical to [`build_levels`].
///
/// Memory: one partial block per level (the front), at most 64³ voxels each.
pub struct Pyramid {
    levels: u8,
    /// `partial[l]`: the level-`l` block being filled (index 0 unused).
    partial: Vec<Option<LodBlock>>,
    last: Option<u64>,
    reach: [f32; 256],
}

/// Bytes of a full 64³ block in pyramid form: the front's unit of account.
pub const FULL_LOD_BLOCK_BYTES: usize = BLOCK_VOXELS * std::mem::size_of::<LodVoxel>();

/// Interleaves block coordinates (21 bits each) into a Morton code, x lowest.
pub fn block_morton(c: [u32; 3]) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut x = v as u64 & 0x1f_ffff;
        x = (x | x << 32) & 0x1f_0000_0000_ffff;
        x = (x | x << 16) & 0x1f_0000_ff00_00ff;
        x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
        x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
        (x | x << 2) & 0x1249_2492_4924_9249
    }
    spread(c[0]) | spread(c[1]) << 1 | spread(c[2]) << 2
}

/// The inverse of [`block_morton`].
pub fn block_coord(m: u64) -> [u32; 3] {
    fn squash(v: u64) -> u32 {
        let mut x = v & 0x1249_2492_4924_9249;
        x = (x | x >> 2) & 0x10c3_0c30_c30c_30c3;
        x = (x | x >> 4) & 0x100f_00f0_0f00_f00f;
        x = (x | x >> 8) & 0x1f_0000_ff00_00ff;
        x = (x | x >> 16) & 0x1f_0000_0000_ffff;
        ((x | x >> 32) & 0x1f_ffff) as u32
    }
    [squash(m), squash(m >> 1), squash(m >> 2)]
}

impl Pyramid {
    pub fn new(resolution: u32) -> Self {
        let levels = level_count(resolution);
        Self {
            levels,
            partial: (0..levels).map(|_| None).collect(),
            last: None,
            reach: std::array::from_fn(|m| empty_octant_reach(m as u8)),
        }
    }

    /// Heap bytes held by the front (the partial blocks).
    pub fn front_bytes(&self) -> usize {
        self.partial.iter().flatten().map(|b| b.voxels.capacity() * std::mem::size_of::<LodVoxel>()).sum()
    }

    /// Adds the next level-0 block (faces marked, buried voxels still in),
    /// after every block of smaller [`block_morton`]. Calls `emit` with each
    /// block that is now complete (buried voxels dropped; empty blocks skipped),
    /// this one included.
    pub fn push<E>(
        &mut self,
        block: LodBlock,
        emit: &mut impl FnMut(DrawnBlock) -> Result<(), E>,
    ) -> Result<(), E> {
        assert_eq!(block.key.level, 0, "the pyramid takes level-0 blocks");
        let m = block_morton(block.key.coord());
        assert!(self.last.is_none_or(|last| last < m), "level-0 blocks must come in increasing Morton order");
        self.last = Some(m);
        self.close(Some(block.key), emit)?;
        if self.levels > 1 {
            let parent = self.partial[1]
                .get_or_insert_with(|| LodBlock { key: block.key.parent(), voxels: Vec::new() });
            downsample(&block, &mut parent.voxels, &self.reach);
        }
        emit_drawn(block, emit)
    }

    /// [`Self::push`] for a level-0 block whose share of its parent was
    /// computed elsewhere ([`parent_share`], e.g. on the worker that
    /// voxelized it): emits the blocks completed before `key` and appends
    /// `share` to the parent. The caller then writes the level-0 block itself
    /// (buried voxels dropped), after what `emit` got here: that keeps post order.
    pub fn push_share<E>(
        &mut self,
        key: BlockKey,
        share: &[LodVoxel],
        emit: &mut impl FnMut(DrawnBlock) -> Result<(), E>,
    ) -> Result<(), E> {
        assert_eq!(key.level, 0, "the pyramid takes level-0 blocks");
        let m = block_morton(key.coord());
        assert!(self.last.is_none_or(|last| last < m), "level-0 blocks must come in increasing Morton order");
        self.last = Some(m);
        self.close(Some(key), emit)?;
        if self.levels > 1 && !share.is_empty() {
            let parent =
                self.partial[1].get_or_insert_with(|| LodBlock { key: key.parent(), voxels: Vec::new() });
            // Exact growth: the front is accounted by capacity.
            parent.voxels.reserve_exact(share.len());
            parent.voxels.extend_from_slice(share);
        }
        Ok(())
    }

    /// Completes and emits every block still in the front, finest first.
    pub fn finish<E>(mut self, emit: &mut impl FnMut(DrawnBlock) -> Result<(), E>) -> Result<(), E> {
        self.close(None, emit)
    }

    /// Completes the partial blocks that are not ancestors of `next`.
    fn close<E>(
        &mut self,
        next: Option<BlockKey>,
        emit: &mut impl FnMut(DrawnBlock) -> Result<(), E>,
    ) -> Result<(), E> {
        for l in 1..self.levels as usize {
            let Some(p) = &self.partial[l] else { break };
            if let Some(k) = next
                && BlockKey::new(l as u8, k.x >> l, k.y >> l, k.z >> l) == p.key
            {
                break;
            }
            let done = self.partial[l].take().expect("checked above");
            if l + 1 < self.levels as usize {
                let parent = self.partial[l + 1]
                    .get_or_insert_with(|| LodBlock { key: done.key.parent(), voxels: Vec::new() });
                downsample(&done, &mut parent.voxels, &self.reach);
            }
            emit_drawn(done, emit)?;
        }
        Ok(())
    }
}

/// A block ready to encode: covered faces hidden, buried voxels dropped.
pub struct DrawnBlock {
    pub block: LodBlock,
    /// Each voxel's face mask as the codec predicts it from the block's occupancy ([`drop_buried`]).
    pub prediction: Vec<u8>,
}

impl DrawnBlock {
    /// Hides `block`'s covered faces and drops its buried voxels (level 0: faces marked).
    pub fn new(mut block: LodBlock) -> Self {
        let exposed = hide_covered_faces(&mut block);
        let prediction = drop_buried(&mut block, exposed);
        Self { block, prediction }
    }
}

/// Emits the block drawn ([`DrawnBlock::new`]) if any voxel is left.
fn emit_drawn<E>(block: LodBlock, emit: &mut impl FnMut(DrawnBlock) -> Result<(), E>) -> Result<(), E> {
    let drawn = DrawnBlock::new(block);
    if drawn.block.voxels.is_empty() { Ok(()) } else { emit(drawn) }
}

/// A level-0 block's share of its parent (faces marked, buried voxels still
/// in): its voxels downsampled into its octant of the parent, in exact
/// capacity. Independent of the other children, so workers compute it in
/// parallel; [`Pyramid::push_share`] appends it. At most 32³ voxels.
pub fn parent_share(child: &LodBlock) -> Vec<LodVoxel> {
    static REACH: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    let reach = REACH.get_or_init(|| std::array::from_fn(|m| empty_octant_reach(m as u8)));
    let mut out = Vec::new();
    downsample(child, &mut out, reach);
    out
}

/// Merges `child` into its octant of the parent, appending to the parent's
/// voxels `parent` (the same arithmetic, in the same order, as [`merge_children`]).
fn downsample(child: &LodBlock, parent: &mut Vec<LodVoxel>, reach: &[f32; 256]) {
    let octant = (child.key.x & 1) | (child.key.y & 1) << 1 | (child.key.z & 1) << 2;
    let child_edge = (1u64 << child.key.level) as f32;
    let diagonal = 2.0 * child_edge * 3f32.sqrt();
    let same = |a: &LodVoxel, b: &LodVoxel| a.voxel.morton >> 3 == b.voxel.morton >> 3;
    // Exact growth: the front is accounted by capacity.
    let count = child.voxels.windows(2).filter(|w| !same(&w[0], &w[1])).count() + 1;
    parent.reserve_exact(count);
    for group in child.voxels.chunk_by(same) {
        let mut acc = LodVoxel { voxel: BuildVoxel::EMPTY, solid: 0, error: 0.0 };
        let mut mask = 0u8;
        for v in group {
            acc.absorb(v);
            mask |= 1 << (v.voxel.morton & 7);
        }
        acc.voxel.morton = octant << 15 | group[0].voxel.morton >> 3;
        acc.error = (acc.error + child_edge * reach[mask as usize]).min(diagonal);
        parent.push(acc);
    }
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
/// Every returned voxel has at least one exposed face; blocks without one are left out.
pub fn build_levels(mut level0: Vec<SparseBlock>, resolution: u32) -> Vec<Vec<LodBlock>> {
    level0.par_iter_mut().for_each(mark_exposed_faces);
    level0.retain(|b| !b.voxels.is_empty());
    let level0: Vec<LodBlock> = level0
        .into_iter()
        .map(|b| LodBlock {
            key: b.key,
            voxels: b.voxels.into_iter().map(|voxel| LodVoxel { voxel, solid: 1, error: 0.0 }).collect(),
        })
        .collect();
    let mut levels = vec![level0];
    for _ in 1..level_count(resolution) {
        let finer = levels.last().expect("level 0 exists");
        let mut groups: BTreeMap<BlockKey, Vec<&LodBlock>> = BTreeMap::new();
        for b in finer {
            groups.entry(b.key.parent()).or_default().push(b);
        }
        let coarser: Vec<LodBlock> =
            groups.into_par_iter().filter_map(|(key, children)| merge_children(key, &children)).collect();
        levels.push(coarser);
    }
    // Buried voxels have done their part (coverage); nothing draws them.
    for level in &mut levels {
        level.par_iter_mut().for_each(|b| {
            hide_covered_faces(b);
            b.voxels.retain(|v| v.voxel.faces != 0)
        });
        level.retain(|b| !b.voxels.is_empty());
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxstream_format::Face;

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

    /// A solid ball of radius 22 about (40, 40, 40): buried voxels inside, a skirt where it meets the block's faces.
    fn solid_ball() -> Vec<[u32; 3]> {
        (0..64u32)
            .flat_map(|z| (0..64u32).flat_map(move |y| (0..64u32).map(move |x| [x, y, z])))
            .filter(|p| p.iter().map(|&c| (c as f32 - 40.0).powi(2)).sum::<f32>() < 22.0f32.powi(2))
            .collect()
    }

    fn lod_of(key: BlockKey, points: &[[u32; 3]]) -> LodBlock {
        let mut b = block_of(key, points);
        mark_exposed_faces(&mut b);
        LodBlock {
            key,
            voxels: b.voxels.into_iter().map(|voxel| LodVoxel { voxel, solid: 1, error: 0.0 }).collect(),
        }
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
    fn faces_match_a_coordinate_reference_on_random_blocks() {
        // Dense and sparse random sets, so every axis, sign and block edge is hit.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (state >> 33) as u32
        };
        for density in [2u32, 8, 64] {
            let mut set = std::collections::BTreeSet::new();
            for _ in 0..20_000 {
                let p = [next() % BLOCK_SIZE, next() % BLOCK_SIZE, next() % BLOCK_SIZE];
                if next() % density == 0 || p.iter().any(|&c| c == 0 || c == BLOCK_SIZE - 1) {
                    set.insert(p);
                }
            }
            let points: Vec<[u32; 3]> = set.iter().copied().collect();
            let mut b = block_of(BlockKey::new(0, 0, 0, 0), &points);
            mark_exposed_faces(&mut b);
            for v in &b.voxels {
                let p = local_position(v);
                let mut want = 0u8;
                for f in Face::ALL {
                    let a = f.axis();
                    let q = p[a] as i64 + f.sign() as i64;
                    let outside = q < 0 || q >= BLOCK_SIZE as i64;
                    let mut n = p;
                    n[a] = q.clamp(0, BLOCK_SIZE as i64 - 1) as u32;
                    if outside || !set.contains(&n) {
                        want |= f.bit();
                    }
                }
                assert_eq!(v.faces, want, "voxel {p:?} at density 1/{density}");
            }
        }
    }

    fn cube(lo: u32, hi: u32) -> Vec<[u32; 3]> {
        let mut pts = Vec::new();
        for z in lo..hi {
            for y in lo..hi {
                for x in lo..hi {
                    pts.push([x, y, z]);
                }
            }
        }
        pts
    }

    #[test]
    fn buried_voxels_are_dropped_but_count_as_solid() {
        let mut b = block_of(BlockKey::new(0, 0, 0, 0), &cube(20, 23));
        mark_exposed_faces(&mut b);
        let buried: Vec<_> = b.voxels.iter().filter(|v| v.faces == 0).map(local_position).collect();
        assert_eq!(buried, vec![[21, 21, 21]]);

        // 4³ solid cube at 20..24: level 1 sees 2³ parents, each over 8 occupied voxels.
        let levels = build_levels(vec![block_of(BlockKey::new(0, 0, 0, 0), &cube(20, 24))], 128);
        assert_eq!(levels.len(), 2);
        assert_eq!(levels[0][0].voxels.len(), 64 - 8, "the 2³ core is buried");
        assert!(levels[0][0].voxels.iter().all(|v| v.voxel.faces != 0));
        let parents = &levels[1][0].voxels;
        assert_eq!(parents.len(), 8);
        assert!(parents.iter().all(|v| v.solid == 8), "buried voxels count: {parents:?}");
        assert!(parents.iter().all(|v| v.error == 0.0), "full parents are exact");
    }

    #[test]
    fn merge_ors_faces_and_places_octants() {
        let a = lod_of(BlockKey::new(0, 1, 0, 0), &[[0, 0, 0], [1, 1, 1]]);
        let b = lod_of(BlockKey::new(0, 0, 1, 0), &[[63, 63, 63]]);
        let parent = merge_children(BlockKey::new(1, 0, 0, 0), &[&a, &b]).unwrap();
        let got: Vec<([u32; 3], u8)> =
            parent.voxels.iter().map(|v| (local_position(&v.voxel), v.voxel.faces)).collect();
        // a's two voxels collapse into parent (32, 0, 0); b's lands at (31, 63, 31).
        assert_eq!(got, vec![([32, 0, 0], 63), ([31, 63, 31], 63)]);
        assert_eq!(parent.voxels[0].voxel.normal_sum, [0.0, 0.0, 2.0]);
        assert_eq!(parent.voxels[0].solid, 2);
        // Two opposite corners occupied: every empty octant shares a face with one.
        assert_eq!(parent.voxels[0].error, 1.0);
        // One child in a corner: the opposite corner octant is √3 away.
        assert!((parent.voxels[1].error - 3f32.sqrt()).abs() < 1e-6);
    }

    /// Fails if a coarse voxel keeps a face that lies against an occupied neighbour of its own
    /// level, or loses one that faces an empty neighbour or the block's boundary (a hole), or
    /// gains a face its children did not have. The control: the children's OR alone, as stored
    /// before, does hold hidden faces on these blocks.
    #[test]
    fn coarse_faces_are_those_facing_empty_voxels_or_the_boundary() {
        // A ball (solid: buried voxels inside) and a slanted plane, beside random sparse blocks.
        let ball = solid_ball();
        let plane: Vec<[u32; 3]> = (0..64u32)
            .flat_map(|y| (0..64u32).map(move |x| (x, y)))
            .filter_map(|(x, y)| {
                let z = 90 - x as i32 - y as i32;
                (0..64).contains(&z).then_some([x, y, z as u32])
            })
            .collect();
        let mut level0 =
            vec![lod_of(BlockKey::new(0, 0, 0, 0), &ball), lod_of(BlockKey::new(0, 1, 0, 0), &plane)];
        level0.extend(random_level0());
        let mut hidden_before = 0;
        for b in level0.iter_mut() {
            mark_exposed_faces_lod(b);
        }
        let mut groups: BTreeMap<BlockKey, Vec<&LodBlock>> = BTreeMap::new();
        for b in &level0 {
            groups.entry(b.key.parent()).or_default().push(b);
        }
        for (key, children) in groups {
            let merged = merge_children(key, &children).unwrap();
            let mut exposed = merged.clone();
            mark_exposed_faces_lod(&mut exposed);
            let mut kept = merged.clone();
            hide_covered_faces(&mut kept);
            for ((or, e), k) in merged.voxels.iter().zip(&exposed.voxels).zip(&kept.voxels) {
                let (or, e, k) = (or.voxel.faces, e.voxel.faces, k.voxel.faces);
                hidden_before += (or & !e).count_ones();
                assert_eq!(k & !or, 0, "no face the children lacked");
                if or == 0 {
                    assert_eq!(k, 0, "buried stays buried");
                } else if e == 0 {
                    assert_eq!(k, or, "hidden on every side: kept as it was");
                } else {
                    assert_eq!(k, e, "exactly the faces facing empty voxels or the boundary");
                }
            }
        }
        assert!(hidden_before > 1000, "the children's OR held {hidden_before} hidden faces");
    }

    #[test]
    fn octant_reach_by_adjacency() {
        assert_eq!(empty_octant_reach(0xff), 0.0);
        assert_eq!(empty_octant_reach(0b0000_1111), 1.0, "a full layer: the rest share faces");
        assert!((empty_octant_reach(0b0000_0001) - 3f32.sqrt()).abs() < 1e-6);
        assert!((empty_octant_reach(0b0000_0011) - 2f32.sqrt()).abs() < 1e-6);
    }

    #[test]
    fn error_grows_with_level_and_stays_within_the_diagonal() {
        // A slanted plane x + y + z = 100 through a 128 grid (two levels).
        let mut pts = Vec::new();
        for y in 0..64 {
            for x in 0..64 {
                let z = 100i32 - x as i32 - y as i32;
                if (0..64).contains(&z) {
                    pts.push([x, y, z as u32]);
                }
            }
        }
        let levels = build_levels(vec![block_of(BlockKey::new(0, 0, 0, 0), &pts)], 256);
        assert_eq!(levels.len(), 3);
        let errors: Vec<f32> = levels.iter().map(|l| l[0].geometric_error()).collect();
        assert_eq!(errors[0], 0.0);
        assert!(errors[1] > 0.0 && errors[1] < errors[2], "{errors:?}");
        for (l, level) in levels.iter().enumerate() {
            let diagonal = (1u32 << l) as f32 * 3f32.sqrt();
            for v in &level[0].voxels {
                assert!(v.error <= diagonal + 1e-4, "level {l}: {} > {diagonal}", v.error);
                assert!(v.solid >= 1 && v.solid <= 8u32.pow(l as u32));
            }
        }
        let solid: Vec<u32> = levels.iter().map(|l| l[0].voxels.iter().map(|v| v.solid).sum()).collect();
        assert_eq!(solid, vec![pts.len() as u32; 3], "every level accounts for every level-0 voxel");
    }

    /// Random level-0 blocks over a 512 grid (4 levels), in Morton order.
    fn random_level0() -> Vec<LodBlock> {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut keys: Vec<BlockKey> = (0..40)
            .map(|_| {
                let r = next();
                BlockKey::new(0, (r % 8) as u32, (r / 8 % 8) as u32, (r / 64 % 8) as u32)
            })
            .collect();
        keys.sort_by_key(|k| block_morton(k.coord()));
        keys.dedup();
        keys.into_iter()
            .map(|key| {
                let n = 1 + next() % 3000;
                let mut pts: Vec<[u32; 3]> = (0..n)
                    .map(|_| {
                        let r = next();
                        [(r % 64) as u32, (r / 64 % 64) as u32, (r / 4096 % 64) as u32]
                    })
                    .collect();
                pts.sort();
                pts.dedup();
                let mut b = lod_of(key, &pts);
                for (i, v) in b.voxels.iter_mut().enumerate() {
                    v.voxel.normal_sum = [i as f32 * 0.25, 1.0 / (i + 1) as f32, -0.5];
                }
                b
            })
            .collect()
    }

    /// Fails if feeding shares computed apart ([`parent_share`], as the
    /// build's workers do) emits other blocks, or in another order, than
    /// [`Pyramid::push`]; the control writes level 0 before the shares' emits.
    #[test]
    fn shares_fold_like_whole_blocks() {
        let level0 = random_level0();
        assert!(level0.len() > 20);
        let run = |shares: bool, level0_first: bool| {
            let mut out: Vec<LodBlock> = Vec::new();
            let mut p = Pyramid::new(512);
            for b in level0.clone() {
                if shares {
                    let share = parent_share(&b);
                    let mut drawn = b.clone();
                    drawn.voxels.retain(|v| v.voxel.faces != 0);
                    if level0_first {
                        out.push(drawn.clone());
                    }
                    p.push_share(b.key, &share, &mut |c| {
                        out.push(c.block);
                        Ok::<_, ()>(())
                    })
                    .unwrap();
                    if !level0_first && !drawn.voxels.is_empty() {
                        out.push(drawn);
                    }
                } else {
                    p.push(b, &mut |c| {
                        out.push(c.block);
                        Ok::<_, ()>(())
                    })
                    .unwrap();
                }
            }
            p.finish(&mut |c| {
                out.push(c.block);
                Ok::<_, ()>(())
            })
            .unwrap();
            out
        };
        let whole = run(false, false);
        assert!(whole.iter().any(|b| b.key.level == 3), "the root is emitted");
        assert_eq!(run(true, false), whole);
        assert_ne!(run(true, true), whole, "the control must differ");
    }

    /// Fails if the prediction `drop_buried` hands the codec is not what the
    /// codec would predict from the kept voxels, at level 0 (a solid ball, a
    /// slab through the block's edge) and on coarse blocks (merged children);
    /// the control, the exposure before the drop, must differ on every block.
    #[test]
    fn drop_buried_predicts_what_the_codec_would() {
        let ball = solid_ball();
        let slab: Vec<[u32; 3]> = (0..64u32)
            .flat_map(|z| (0..64u32).flat_map(move |y| (0..4u32).map(move |x| [x, y, z])))
            .collect();
        let mut blocks =
            vec![lod_of(BlockKey::new(0, 0, 0, 0), &ball), lod_of(BlockKey::new(0, 1, 0, 0), &slab)];
        let mut children: Vec<LodBlock> =
            [0, 1].map(|x| lod_of(BlockKey::new(0, x, 0, 0), &ball)).into_iter().collect();
        children.push(lod_of(BlockKey::new(0, 0, 1, 0), &slab));
        blocks.push(merge_children(BlockKey::new(1, 0, 0, 0), &children.iter().collect::<Vec<_>>()).unwrap());
        for mut b in blocks {
            let exposed = hide_covered_faces(&mut b);
            let before = b.voxels.len();
            // The control: the kept voxels' exposure with the dropped ones still counted.
            let unfixed: Vec<u8> =
                b.voxels.iter().zip(&exposed).filter(|(v, _)| v.voxel.faces != 0).map(|(_, &e)| e).collect();
            let prediction = drop_buried(&mut b, exposed);
            assert!(b.voxels.len() < before, "level {}: some voxel is buried", b.key.level);
            let morton: Vec<u32> = b.voxels.iter().map(|v| v.voxel.morton).collect();
            let codec = voxstream_format::predicted_face_masks(&morton);
            assert_eq!(prediction, codec, "level {}", b.key.level);
            assert_ne!(unfixed, codec, "level {}: the control must differ", b.key.level);
        }
    }

    #[test]
    fn axis_masks_are_each_axis_bits() {
        assert_eq!(AXIS_MASKS, [0, 1, 2].map(|a| morton3(BLOCK_SIZE - 1, 0, 0) << a));
    }

    #[test]
    fn level_counts() {
        assert_eq!(level_count(32), 1);
        assert_eq!(level_count(64), 1);
        assert_eq!(level_count(512), 4);
    }
}
