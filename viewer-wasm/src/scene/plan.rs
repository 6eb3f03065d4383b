//! traverse → request: what the view wants this frame ([`crate::traverse`]), and the
//! queue of pages and blocks to fetch for it ([`crate::request`]), replanned whenever the
//! traversal runs again (the view, the pages, the feedback or the budget changed), never on
//! a block's arrival.

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::{BlockKey, PageRef};

use super::Scene;
use crate::request::{NeededBlocks, Request};
use crate::select::ViewParams;
use crate::traverse::{TraverseParams, traverse};

/// Share of the block budget the needed set (wanted blocks and their
/// ancestors, counted with the pools' rounding) may take; the rest leaves
/// room for the free list and the last frame's blocks while the view changes.
const WANTED_SHARE_OF_BUDGET: f64 = 0.8;

impl Scene {
    pub(super) fn traverse_params(&self) -> TraverseParams {
        TraverseParams {
            max_error_pixels: self.select_params.max_error_pixels,
            max_blocks: self.select_params.max_blocks,
            max_bytes: (self.residency.block_budget() as f64 * WANTED_SHARE_OF_BUDGET) as u64,
            ..Default::default()
        }
    }

    /// Runs the traversal when the camera, viewport, loaded pages, parameters
    /// or budget changed, and replans the requests.
    pub(super) fn update_traversal(&mut self) {
        let now = (
            self.camera,
            self.viewport,
            self.index.pages_loaded(),
            self.select_params,
            // The block budget, not the budget: the fixed targets are counted after the first
            // traversal, whose byte cap must then shrink.
            self.residency.block_budget(),
            self.failed_pages.len(),
            self.hidden_generation,
            self.fixed_view,
        );
        if self.traversed_for.as_ref() == Some(&now) {
            return;
        }
        let view = ViewParams {
            view_proj: self.view_proj(),
            eye: self.eye(),
            focal_pixels: self
                .fixed_view
                .map_or_else(|| self.camera.focal_pixels(self.viewport.1 as f32), |v| v.focal_pixels),
        };
        let started = (self.clock)();
        let no_feedback = HashSet::default();
        let occluded = if self.occlusion_culling { &self.hidden } else { &no_feedback };
        self.traversal =
            traverse(&self.index, &self.manifest.root.key, &view, &self.traverse_params(), occluded);
        self.stats.culled_frustum = self.traversal.culled_frustum;
        self.stats.culled_occlusion = self.traversal.culled_occlusion;
        self.traversed_for = Some(now);
        self.refresh_needed();
        self.plan_requests();
        self.stats.longest_traversal_ms = self.stats.longest_traversal_ms.max((self.clock)() - started);
    }

    pub(super) fn plan_requests(&mut self) {
        let pages: Vec<PageRef> = self
            .traversal
            .pages
            .iter()
            .filter(|p| !self.failed_pages.contains_key(&p.root))
            .cloned()
            .collect();
        let (decoded, failed, empty) = (&self.decoded, &self.failed, &self.empty);
        let present = |k: &BlockKey| decoded.contains_key(k) || failed.contains_key(k) || empty.contains(k);
        let failed_pages = &self.failed_pages;
        self.requests.plan(&pages, &self.needed, |k| failed_pages.contains_key(k), present);
    }

    /// What must be loaded, with its projected error: the wanted blocks but
    /// the hidden ones, and all their ancestors (stand-ins while they load).
    /// Kept from the last [`Self::refresh_needed`].
    pub(super) fn needed(&self) -> &HashMap<BlockKey, f32> {
        &self.needed.by_key
    }

    /// Works out [`Self::needed`] again. It depends on the traversal and on which entries the
    /// index holds, so this runs after either changes, and only then: once a frame at most
    /// while the view moves, not once an arrival (at 32768³ an arrival's replan, with this
    /// recomputed, was the largest share of the viewer's own main-thread time).
    pub(super) fn refresh_needed(&mut self) {
        let hidden: HashSet<&BlockKey> = self.traversal.hidden.iter().collect();
        let max_level = self.manifest.coarsest_level();
        let mut needed = HashMap::default();
        for key in self.traversal.blocks.iter().filter(|k| !hidden.contains(k)) {
            let mut k = *key;
            loop {
                if needed.contains_key(&k) {
                    break;
                }
                if self.index.block(&k).is_some() {
                    needed.insert(k, self.traversal.priority.get(&k).copied().unwrap_or(f32::INFINITY));
                }
                if k.level >= max_level {
                    break;
                }
                k = k.parent();
            }
        }
        self.needed = NeededBlocks::new(needed);
    }

    /// The blocks to resolve the draw set from: the wanted ones, a hidden
    /// block only if it is loaded (it is invisible; its ancestor must not
    /// stand in for it and cover its visible siblings).
    pub(super) fn drawable_wanted(&self) -> Vec<BlockKey> {
        let hidden: HashSet<&BlockKey> = self.traversal.hidden.iter().collect();
        self.traversal.blocks.iter().filter(|k| !hidden.contains(k) || self.is_ready(k)).copied().collect()
    }

    /// The blocks this view wants (sorted by key).
    pub fn wanted(&mut self) -> &[BlockKey] {
        self.update_traversal();
        &self.traversal.blocks
    }

    /// The next requests to start (pages first, then blocks by projected
    /// error), within the in-flight cap; they are marked in flight.
    pub fn start_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let started = self.requests.start();
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        started
    }

    /// Like [`Scene::start_requests`], hierarchy pages only.
    pub fn start_page_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let started = self.requests.start_where(|r| matches!(r, Request::Page(_)));
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        started
    }

    /// In-flight requests this view no longer needs: abort them.
    pub fn take_stale_requests(&mut self) -> Vec<Request> {
        self.update_traversal();
        let stale = self.requests.take_stale();
        self.stats.requests_aborted += stale.len() as u32;
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        stale
    }

    pub fn in_flight(&self) -> usize {
        self.requests.in_flight()
    }
}

#[cfg(test)]
pub(super) mod tests {
    use voxstream_format::Block;

    use super::*;
    use crate::decode::DecodedBlock;
    use crate::select::tests::pyramid;

    /// Streams the default view of a loaded pyramid to the end, every started request answered
    /// at once (odd x refused, the rest arriving empty); `lose` is a block whose answer is
    /// dropped (its request finished, nothing inserted). With `replan_on_arrival` the queue is
    /// replanned after each answer, as it was before arrivals stopped replanning.
    pub(in crate::scene) fn stream(replan_on_arrival: bool, lose: Option<usize>) -> (Vec<Request>, Scene) {
        let (m, index) = pyramid(1024);
        let mut scene = Scene::new(m, (640, 480));
        scene.index = index;
        let mut started = Vec::new();
        while started.len() < 100_000 {
            let batch = scene.start_requests();
            if batch.is_empty() {
                break;
            }
            for r in &batch {
                let Request::Block(key) = *r else { panic!("a loaded index asks for no page") };
                if lose == Some(started.len()) {
                    scene.requests.finished(r);
                } else {
                    let answer = if key.x % 2 == 1 {
                        Err("refused".to_string())
                    } else {
                        Ok(DecodedBlock::new(Block { key, voxels: Vec::new() }))
                    };
                    scene.insert_worker_result(key, 0, answer);
                }
                if replan_on_arrival {
                    scene.plan_requests();
                }
                started.push(r.clone());
            }
        }
        (started, scene)
    }

    #[test]
    fn arrivals_leave_the_plan_as_a_replan_would() {
        let (without, mut scene) = stream(false, None);
        let (with, _) = stream(true, None);
        assert!(without.len() > 20, "the view streams enough to tell: {} requests", without.len());
        assert_eq!(without, with, "the same requests in the same order as replanning after each arrival");
        let unique: HashSet<BlockKey> =
            without.iter().map(|r| if let Request::Block(k) = r { *k } else { unreachable!() }).collect();
        assert_eq!(unique.len(), without.len(), "nothing asked twice");
        assert!(scene.is_settled(), "everything needed arrived or failed for good");
        // Negative control: an answer lost on the way leaves a needed block neither loaded
        // nor asked for again, and the checks above see it.
        let (_, mut lost) = stream(false, Some(without.len() / 2));
        assert!(!lost.is_settled());
    }
}
