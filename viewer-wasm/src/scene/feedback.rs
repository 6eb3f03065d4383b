//! feedback: the boxes the occlusion pass tests, the hidden set it answers with (which
//! steers the next traversal), and the double-click pick that rides on the same readback.

use rustc_hash::FxHashSet as HashSet;

use glam::Vec3;
use voxstream_format::BlockKey;

use super::Scene;
use crate::occlusion::{Occlusion, contains_eye, proxy_bounds};
use crate::select::block_bounds;

impl Scene {
    /// Double-click at `pixel` (viewport pixels, row 0 at the top): a frame or
    /// two later the orbit centres on the surface there (none: nothing changes).
    pub fn pick(&mut self, pixel: (f32, f32)) {
        let frame = self.frame_counter + 1;
        self.occlusion.get_or_insert_with(Occlusion::default).request_pick(pixel, frame);
    }

    /// The answer to the last [`Scene::pick`], once; it has already been applied to the camera.
    pub fn take_picked(&mut self) -> Option<Option<Vec3>> {
        self.picked.take()
    }

    /// Blocks whose visibility decides what is fetched: every visited block
    /// (coarsest first, they prune most), those that meet the error too, but
    /// those around the eye, which are always visible. Each box is grown by a
    /// voxel of the level drawn for it last frame: a coarse stand-in's voxels
    /// stick out of the finer block's bounds by up to one of their edges, and
    /// must not hide the block they stand in for.
    pub(super) fn occlusion_tests(&self) -> Vec<(BlockKey, crate::select::Aabb)> {
        let eye = self.eye();
        let drawn: HashSet<&BlockKey> = self.drawn.iter().collect();
        let max_level = self.manifest.coarsest_level();
        // Nothing drawn over it (its region is drawn by finer blocks, or not at all): its own.
        let drawn_level = |key: &BlockKey| {
            let mut k = *key;
            loop {
                if drawn.contains(&k) {
                    return k.level;
                }
                if k.level >= max_level {
                    return key.level;
                }
                k = k.parent();
            }
        };
        // Coarsest first, then by key: sorting the keys, not the boxes (up to
        // eight a key), gives the same order at an eighth of the work.
        let mut keys: Vec<&BlockKey> = self.traversal.priority.keys().collect();
        keys.sort_unstable_by(|a, b| b.level.cmp(&a.level).then(a.cmp(b)));
        let mut tests: Vec<(BlockKey, crate::select::Aabb)> = Vec::with_capacity(keys.len());
        for k in keys {
            let Some(tight) = block_bounds(&self.index, k) else { continue };
            let level = drawn_level(k);
            let grown = |b: &crate::select::Aabb| proxy_bounds(b, level);
            if contains_eye(&grown(&tight), eye) {
                continue;
            }
            // The tightest boxes the loaded data gives: the block's own cells, else its parent's.
            let cells_of = |k: &BlockKey| self.decoded.get(k).map(|c| &c.cells);
            let cells =
                cells_of(k).or_else(|| (k.level < max_level).then(|| k.parent()).and_then(|p| cells_of(&p)));
            match cells.and_then(|c| c.boxes_for(k)).filter(|b| !b.is_empty()) {
                Some(boxes) => {
                    tests.extend(boxes.iter().filter_map(|b| b.intersection(&tight)).map(|b| (*k, grown(&b))))
                }
                None => tests.push((*k, grown(&tight))),
            }
        }
        tests
    }

    /// Takes the newest occlusion feedback, if any arrived.
    pub(super) fn take_feedback(&mut self) {
        let Some(v) = self.occlusion.as_mut().and_then(Occlusion::take_results) else {
            self.take_pick_answer();
            return;
        };
        self.take_pick_answer();
        if v.hidden != self.hidden {
            self.hidden = v.hidden;
            self.hidden_generation += 1;
            self.feedback_changed_frame = self.frame_counter;
        }
    }

    pub(super) fn take_pick_answer(&mut self) {
        if let Some(answer) = self.occlusion.as_mut().and_then(Occlusion::take_picked) {
            if let Some(point) = answer.filter(|_| self.fixed_view.is_none()) {
                self.camera.recentre(point);
            }
            self.picked = Some(answer);
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::scene::plan::tests::stream;

    #[test]
    fn occlusion_tests_run_coarsest_first_then_by_key() {
        let (_, scene) = stream(false, None);
        let tests = scene.occlusion_tests();
        assert!(tests.len() > 20, "enough boxes to tell: {}", tests.len());
        let mut sorted = tests.clone();
        // The order the pass had when the boxes themselves were sorted (stable).
        sorted.sort_by(|a, b| b.0.level.cmp(&a.0.level).then(a.0.cmp(&b.0)));
        assert_eq!(tests, sorted);
        // Control: the traversal's own (hash) order is not that order, so the sort is what gives it.
        let raw: Vec<_> = scene.traversal.priority.keys().copied().collect();
        let mut keys = raw.clone();
        keys.sort_by(|a, b| b.level.cmp(&a.level).then(a.cmp(b)));
        assert_ne!(raw, keys);
    }
}
