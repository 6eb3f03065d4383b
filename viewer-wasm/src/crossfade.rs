//! Level changes without popping: when refinement swaps a block for its
//! children (or coarsening swaps children for their parent), both are drawn
//! for a short while with complementary screen-door masks, the newcomers on a
//! growing share of the pixels and the leavers on the rest (seed 003 §4.6's
//! "blend between levels", done as a dither so depth testing stays exact).
//!
//! Invariant: at every pixel and every moment at most one of a leaving block
//! and the block(s) replacing it passes its mask, since both use the same
//! threshold pattern with `t` and its complement. A block entering the view
//! without replacing anything appears at once: there is nothing to fade from.

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::BlockKey;

/// Most blocks fading at once (uniform slots); beyond it level changes pop.
pub const MAX_FADES: usize = 255;
/// Bytes per fade slot: the uniform's dynamic-offset alignment.
pub const FADE_SLOT_BYTES: u64 = 256;

/// How one block is drawn this frame while fading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fade {
    /// 0..1: the share of pixels the newcomers own.
    pub t: f32,
    /// True for a newcomer (drawn where the dither is below `t`), false for a leaver.
    pub incoming: bool,
}

#[derive(Debug, Clone, Copy)]
struct Transition {
    start_ms: f64,
    incoming: bool,
}

#[derive(Debug, Default)]
pub struct Crossfade {
    /// 0 turns fading off (native renders, tests of exact coverage).
    pub duration_ms: f64,
    fading: HashMap<BlockKey, Transition>,
    previous: HashSet<BlockKey>,
}

/// Ancestors of `key` up to `max_level`, nearest first.
fn ancestors(key: BlockKey, max_level: u8) -> impl Iterator<Item = BlockKey> {
    std::iter::successors(Some(key), move |k| (k.level < max_level).then(|| k.parent())).skip(1)
}

impl Crossfade {
    pub fn new(duration_ms: f64) -> Self {
        Self { duration_ms, ..Default::default() }
    }

    /// Whether any block is still fading (another frame is needed).
    pub fn is_active(&self) -> bool {
        !self.fading.is_empty()
    }

    /// This frame's draw list: every block of `drawn`, with a fade where it
    /// replaced a block of the last frame, plus the leavers still fading
    /// (only those `resident` says are still on the GPU).
    pub fn update(
        &mut self,
        drawn: &[BlockKey],
        max_level: u8,
        now_ms: f64,
        resident: impl Fn(&BlockKey) -> bool,
    ) -> Vec<(BlockKey, Option<Fade>)> {
        let current: HashSet<BlockKey> = drawn.iter().copied().collect();
        if self.duration_ms > 0.0 {
            let departed: HashSet<BlockKey> = self.previous.difference(&current).copied().collect();
            let start = |key: BlockKey, incoming: bool, fading: &mut HashMap<BlockKey, Transition>| {
                if fading.len() < MAX_FADES || fading.contains_key(&key) {
                    fading.entry(key).or_insert(Transition { start_ms: now_ms, incoming });
                }
            };
            // Refinement: a newcomer whose ancestor just left.
            for &key in current.difference(&self.previous) {
                if let Some(a) = ancestors(key, max_level).find(|a| departed.contains(a)) {
                    start(key, true, &mut self.fading);
                    start(a, false, &mut self.fading);
                }
            }
            // Coarsening: a leaver whose ancestor just came.
            for &key in &departed {
                if let Some(a) =
                    ancestors(key, max_level).find(|a| current.contains(a) && !self.previous.contains(a))
                {
                    start(a, true, &mut self.fading);
                    start(key, false, &mut self.fading);
                }
            }
        }
        // Done, or no longer consistent with the drawn set (a leaver came back, a newcomer left): drawn plainly.
        let duration = self.duration_ms;
        self.fading.retain(|key, tr| {
            now_ms - tr.start_ms < duration
                && current.contains(key) == tr.incoming
                && (tr.incoming || resident(key))
        });
        let fade = |key: &BlockKey| {
            self.fading.get(key).map(|tr| Fade {
                t: ((now_ms - tr.start_ms) / duration).clamp(0.0, 1.0) as f32,
                incoming: tr.incoming,
            })
        };
        let mut list: Vec<(BlockKey, Option<Fade>)> = drawn.iter().map(|k| (*k, fade(k))).collect();
        let mut leavers: Vec<BlockKey> =
            self.fading.iter().filter(|(_, tr)| !tr.incoming).map(|(k, _)| *k).collect();
        leavers.sort();
        list.extend(leavers.into_iter().map(|k| (k, fade(&k))));
        self.previous = current;
        list
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k(level: u8, x: u32, y: u32, z: u32) -> BlockKey {
        BlockKey::new(level, x, y, z)
    }

    #[test]
    fn refinement_fades_the_children_in_and_the_parent_out_then_ends() {
        let parent = k(1, 0, 0, 0);
        let children: Vec<BlockKey> = (0..2).map(|x| k(0, x, 0, 0)).collect();
        let mut f = Crossfade::new(200.0);
        let first = f.update(&[parent], 1, 0.0, |_| true);
        assert_eq!(first, vec![(parent, None)], "nothing to fade from on the first frame");
        let during = f.update(&children, 1, 100.0, |_| true);
        assert_eq!(during.len(), 3, "children and the leaving parent: {during:?}");
        for (key, fade) in &during {
            let fade = fade.expect("every block of the swap fades");
            assert_eq!(fade.incoming, *key != parent);
            assert_eq!(fade.t, 0.0, "the fade starts on the frame of the swap");
        }
        let later = f.update(&children, 1, 200.0, |_| true);
        let t: Vec<f32> = later.iter().map(|(_, f)| f.unwrap().t).collect();
        assert!(t.iter().all(|&t| (t - 0.5).abs() < 1e-6), "halfway: {later:?}");
        assert!(f.is_active());
        let done = f.update(&children, 1, 400.0, |_| true);
        assert_eq!(done, children.iter().map(|c| (*c, None)).collect::<Vec<_>>());
        assert!(!f.is_active());
    }

    #[test]
    fn coarsening_fades_the_parent_in_and_the_children_out() {
        let parent = k(1, 0, 0, 0);
        let children: Vec<BlockKey> = (0..2).map(|x| k(0, x, 0, 0)).collect();
        let mut f = Crossfade::new(200.0);
        f.update(&children, 1, 0.0, |_| true);
        let list = f.update(&[parent], 1, 10.0, |_| true);
        assert_eq!(list[0], (parent, Some(Fade { t: 0.0, incoming: true })));
        assert_eq!(list.len(), 3);
        assert!(list[1..].iter().all(|(_, f)| *f == Some(Fade { t: 0.0, incoming: false })));
        // An evicted leaver is no longer drawn.
        let list = f.update(&[parent], 1, 20.0, |key| *key != children[0]);
        assert_eq!(list.len(), 2);
    }

    #[test]
    fn blocks_entering_the_view_and_disabled_fading_pop_in() {
        let a = k(0, 0, 0, 0);
        let b = k(0, 5, 0, 0);
        let mut f = Crossfade::new(200.0);
        f.update(&[a], 0, 0.0, |_| true);
        assert_eq!(f.update(&[a, b], 0, 10.0, |_| true), vec![(a, None), (b, None)]);
        // Control: the same refinement as above with fading off draws only the drawn set.
        let mut off = Crossfade::new(0.0);
        off.update(&[k(1, 0, 0, 0)], 1, 0.0, |_| true);
        assert_eq!(off.update(&[a], 1, 10.0, |_| true), vec![(a, None)]);
        assert!(!off.is_active());
    }
}
