//! Per-frame traversal over the (lazily loaded) SceneIndex: from the root,
//! refine the block whose geometric error projects largest while it projects
//! above the pixel threshold, culling by frustum (tight bounds) and by
//! occlusion feedback, within a GPU byte budget. When refining a block would
//! push the wanted set past the budget, the traversal keeps it coarse: the view
//! settles for coarser levels instead of breaking the budget.

use std::collections::BinaryHeap;

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::{BlockEntry, BlockKey, PageRef, SceneIndex};

use crate::residency::block_gpu_bytes;
use crate::select::{Candidate, Frustum, ViewParams, entry_bounds, error_pixels, lod_error};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraverseParams {
    /// Refine while a block's error ([`lod_error`], or its geometric error when `strict`)
    /// projects larger than this many pixels.
    pub max_error_pixels: f32,
    /// Stop refining once this many blocks are wanted (bounds CPU work).
    pub max_blocks: usize,
    /// GPU bytes the wanted blocks and their ancestors may take together
    /// (estimated from face counts).
    pub max_bytes: u64,
    /// Refine by the build's bound alone, uncapped: no drawn point then lies further than the
    /// threshold from the level-0 voxels, at up to 4× the bytes of a fine build (docs/streaming.md).
    pub strict: bool,
}

impl Default for TraverseParams {
    fn default() -> Self {
        Self { max_error_pixels: 1.0, max_blocks: 16_384, max_bytes: u64::MAX, strict: false }
    }
}

/// What a view wants this frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Traversal {
    /// Blocks to draw, sorted by key.
    pub blocks: Vec<BlockKey>,
    /// Pages below blocks that want refining, largest projected error first.
    pub pages: Vec<PageRef>,
    /// Projected error (px) of every block the traversal visited: the wanted
    /// blocks and all their ancestors, which stand in while finer ones load.
    pub priority: HashMap<BlockKey, f32>,
    /// Children skipped because their bounds leave the frustum.
    pub culled_frustum: u32,
    /// Blocks neither refined nor fetched because feedback saw none of them.
    pub culled_occlusion: u32,
    /// Those blocks: wanted only as proxies (tested, drawn if already loaded, never requested).
    pub hidden: Vec<BlockKey>,
    /// Blocks kept coarser than the pixel rule asks because of the byte budget.
    pub held_by_budget: u32,
    /// Estimated GPU bytes of `blocks` and all their ancestors: what must be
    /// resident, since ancestors stand in while finer blocks load.
    pub bytes: u64,
}

/// Estimated GPU bytes of a block once resident.
pub fn entry_gpu_bytes(entry: &BlockEntry) -> u64 {
    if entry.faces == 0 { 0 } else { block_gpu_bytes(entry.faces) }
}

/// Runs the traversal. `occluded` holds blocks the last frames' feedback found
/// hidden: a hidden block stays in `blocks` (drawn only if already loaded; its
/// bounds are tested again every frame, which tells when it shows again) but is
/// neither fetched nor refined, so nothing below it is wanted.
pub fn traverse(
    index: &SceneIndex,
    root: &BlockKey,
    view: &ViewParams,
    params: &TraverseParams,
    occluded: &HashSet<BlockKey>,
) -> Traversal {
    let frustum = Frustum::from_view_proj(view.view_proj);
    let mut out = Traversal::default();
    let candidate = |entry: &BlockEntry| Candidate {
        key: entry.key,
        pixels: error_pixels(
            if params.strict { entry.geometric_error } else { lod_error(entry) },
            &entry_bounds(entry),
            view,
        ),
    };
    let bytes_of = |key: &BlockKey| index.block(key).map_or(0, entry_gpu_bytes);
    let mut open: BinaryHeap<Candidate> = BinaryHeap::new();
    if let Some(e) = index.block(root) {
        if frustum.intersects(&entry_bounds(e)) {
            open.push(candidate(e));
            out.bytes = bytes_of(root);
        } else {
            out.culled_frustum += 1;
        }
    }
    let mut done = Vec::new();
    while let Some(c) = open.pop() {
        out.priority.insert(c.key, c.pixels);
        // A hidden block is neither refined nor fetched, whether or not its error asks for
        // refining: most bytes lie in the blocks that meet the error, so hidden ones of those
        // are the largest saving.
        if occluded.contains(&c.key) {
            out.culled_occlusion += 1;
            out.hidden.push(c.key);
        } else if let Some(entry) = index.block(&c.key).filter(|_| c.pixels > params.max_error_pixels) {
            // Each entry is looked up once: at 32768³ a traversal visits thousands of blocks
            // and the lookups were most of its time.
            if let Some(page) = index.pending_page_below(entry) {
                out.pages.push(page.clone());
            } else if entry.child_mask != 0 {
                let mut children = Vec::new();
                let mut bytes = out.bytes;
                for child in index.children_of(entry) {
                    if frustum.intersects(&entry_bounds(child)) {
                        children.push(candidate(child));
                        bytes += entry_gpu_bytes(child);
                    } else {
                        out.culled_frustum += 1;
                    }
                }
                let count = done.len() + open.len() + children.len();
                if count <= params.max_blocks && bytes <= params.max_bytes {
                    out.bytes = bytes;
                    open.extend(children);
                    continue;
                }
                out.held_by_budget += 1;
            }
        }
        done.push(c.key);
    }
    done.sort();
    out.blocks = done;
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::OrbitCamera;
    use crate::select::tests::pyramid;
    use glam::Vec3;

    fn view_of(cam: &OrbitCamera, height: f32) -> ViewParams {
        ViewParams { view_proj: cam.view_proj(1.0), eye: cam.eye(), focal_pixels: cam.focal_pixels(height) }
    }

    #[test]
    fn a_byte_budget_settles_for_coarser_levels() {
        let (m, index) = pyramid(1024);
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(1024.0));
        let view = view_of(&cam, 2000.0);
        let free = traverse(&index, &m.root.key, &view, &TraverseParams::default(), &HashSet::default());
        assert!(free.held_by_budget == 0 && free.blocks.iter().any(|k| k.level == 0));
        let budget = free.bytes / 4;
        let tight = TraverseParams { max_bytes: budget, ..Default::default() };
        let held = traverse(&index, &m.root.key, &view, &tight, &HashSet::default());
        assert!(held.bytes <= budget, "{} > {budget}", held.bytes);
        assert!(held.held_by_budget > 0 && held.blocks.len() < free.blocks.len());
        let coarsest =
            |t: &Traversal| t.blocks.iter().map(|k| k.level as f32).sum::<f32>() / t.blocks.len() as f32;
        assert!(coarsest(&held) > coarsest(&free), "the budget kept levels coarser");
        // Every visited block has a priority, ancestors larger than their children.
        for k in &held.blocks {
            let p = held.priority[k];
            if k.level < m.root.key.level {
                assert!(held.priority[&k.parent()] >= p);
            }
        }
    }

    #[test]
    fn occluded_blocks_are_not_refined() {
        let (m, index) = pyramid(512);
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        let view = view_of(&cam, 2000.0);
        let all = traverse(&index, &m.root.key, &view, &TraverseParams::default(), &HashSet::default());
        let hidden = m.root.key.children().unwrap()[0];
        let below = |t: &Traversal| {
            t.blocks
                .iter()
                .filter(|k| {
                    let mut a = **k;
                    while a.level < hidden.level {
                        a = a.parent();
                    }
                    k.level < hidden.level && a == hidden
                })
                .count()
        };
        // Control: without feedback its subtree is refined.
        assert!(below(&all) > 0);
        let occluded: HashSet<BlockKey> = [hidden].into_iter().collect();
        let t = traverse(&index, &m.root.key, &view, &TraverseParams::default(), &occluded);
        assert_eq!(below(&t), 0, "nothing below a hidden block is wanted");
        assert!(t.blocks.contains(&hidden), "the hidden block stays as its own proxy");
        assert_eq!(t.culled_occlusion, 1);
    }

    #[test]
    fn hidden_blocks_that_meet_the_error_are_not_fetched_either() {
        let (m, index) = pyramid(512);
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        let view = view_of(&cam, 2000.0);
        let params = TraverseParams::default();
        let all = traverse(&index, &m.root.key, &view, &params, &HashSet::default());
        // A block the view wants as it is: its error is met, nothing below it is visited.
        let leaf = *all
            .blocks
            .iter()
            .find(|k| all.priority[k] <= params.max_error_pixels && k.level < m.root.key.level)
            .expect("a wanted block that meets the error");
        // Control: without feedback it is wanted and not hidden.
        assert!(!all.hidden.contains(&leaf));
        let t = traverse(&index, &m.root.key, &view, &params, &[leaf].into_iter().collect());
        assert_eq!(t.hidden, vec![leaf], "a hidden block that meets the error is hidden too");
        assert!(t.blocks.contains(&leaf), "it stays wanted as its own proxy (drawn if loaded)");
        assert_eq!(t.blocks.len(), all.blocks.len(), "nothing else changes");
    }
}
