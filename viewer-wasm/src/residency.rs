//! GPU memory under a hard byte budget. Every buffer and texture the viewer
//! holds is counted: the frame's fixed targets (colour and depth, the AO
//! targets, the occupancy volume and clipmap, uniforms, the upload buffer)
//! and every chunk of the face arena ([`crate::face_arena`]), used or not.
//! A block is placed in a free run of pages; if none holds it, a new chunk is
//! made when the budget allows, else empty chunks are dropped and the least
//! recently visible blocks that are not protected (needed this frame) are
//! evicted, one at a time, until a run holds it. If nothing is left to evict
//! the block is refused: the budget is never exceeded.
//! No compaction: a block only needs a contiguous run within one chunk, and
//! eviction frees runs in least-recently-visible order; chunks are small
//! against the budget (at most 1/[`CHUNK_SHARE_OF_BUDGET`] of it), so a
//! fragmented chunk empties and goes before it strands much.

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::BlockKey;

use crate::face_arena::{BlockSlot, FaceArena, PAGE_BYTES, pages_for};

/// The default budget: 512 MiB.
pub const DEFAULT_BUDGET_BYTES: u64 = 512 << 20;
/// The most pages a chunk is made with (12 MiB of faces).
const MAX_CHUNK_PAGES: u32 = 4096;
/// The fewest pages a chunk is made with.
const MIN_CHUNK_PAGES: u32 = 64;
/// A chunk takes at most this share of the block budget, so a small budget
/// is not mostly rounding.
pub const CHUNK_SHARE_OF_BUDGET: u64 = 16;

/// GPU bytes a resident block of `faces` faces takes in the arena.
pub fn block_gpu_bytes(faces: u32) -> u64 {
    pages_for(faces) as u64 * PAGE_BYTES
}

struct Resident {
    slot: BlockSlot,
    last_visible: u64,
}

/// What [`Residency::place`] did.
#[derive(Debug, Default, PartialEq)]
pub struct Placement {
    /// Where the block goes; `None` when it cannot fit.
    pub slot: Option<BlockSlot>,
    /// Blocks taken off the GPU to make room (the caller forgets them).
    pub evicted: Vec<BlockKey>,
}

/// Who may hold GPU memory: the face arena's chunks and the blocks in them,
/// within the budget.
pub struct Residency {
    budget: u64,
    /// Bytes of the frame's own targets and buffers.
    fixed: u64,
    arena: FaceArena,
    resident: HashMap<BlockKey, Resident>,
    peak: u64,
}

impl Residency {
    pub fn new(budget: u64) -> Self {
        Self { budget, fixed: 0, arena: FaceArena::default(), resident: HashMap::default(), peak: 0 }
    }

    pub fn budget(&self) -> u64 {
        self.budget
    }

    pub fn set_budget(&mut self, budget: u64) {
        self.budget = budget;
    }

    /// Declares the bytes of the fixed targets (they change with the viewport).
    pub fn set_fixed_bytes(&mut self, bytes: u64) {
        self.fixed = bytes;
        self.note_peak();
    }

    pub fn fixed_bytes(&self) -> u64 {
        self.fixed
    }

    /// Everything counted now: fixed targets and every arena chunk.
    pub fn used_bytes(&self) -> u64 {
        self.fixed + self.arena.bytes()
    }

    pub fn peak_bytes(&self) -> u64 {
        self.peak
    }

    /// What blocks may take: the budget less the fixed targets.
    pub fn block_budget(&self) -> u64 {
        self.budget.saturating_sub(self.fixed)
    }

    pub fn arena(&self) -> &FaceArena {
        &self.arena
    }

    pub fn arena_mut(&mut self) -> &mut FaceArena {
        &mut self.arena
    }

    pub fn is_resident(&self, key: &BlockKey) -> bool {
        self.resident.contains_key(key)
    }

    pub fn resident_count(&self) -> usize {
        self.resident.len()
    }

    pub fn mark_visible(&mut self, key: &BlockKey, frame: u64) {
        if let Some(r) = self.resident.get_mut(key) {
            r.last_visible = frame;
        }
    }

    fn note_peak(&mut self) {
        self.peak = self.peak.max(self.used_bytes());
    }

    /// Pages of a new chunk for a block of `pages`: a share of the block
    /// budget within [`MIN_CHUNK_PAGES`, `MAX_CHUNK_PAGES`], or the block's own
    /// size when it is larger.
    fn chunk_pages_for(&self, pages: u32) -> u32 {
        let share = (self.block_budget() / CHUNK_SHARE_OF_BUDGET / PAGE_BYTES) as u32;
        share.clamp(MIN_CHUNK_PAGES, MAX_CHUNK_PAGES).max(pages)
    }

    /// Unprotected resident blocks, least recently visible first.
    fn victims(&self, protected: &HashSet<BlockKey>) -> std::vec::IntoIter<(u64, BlockKey)> {
        let mut victims: Vec<(u64, BlockKey)> = self
            .resident
            .iter()
            .filter(|(k, _)| !protected.contains(k))
            .map(|(k, r)| (r.last_visible, *k))
            .collect();
        victims.sort_unstable();
        victims.into_iter()
    }

    fn evict(&mut self, key: &BlockKey) {
        if let Some(r) = self.resident.remove(key) {
            self.arena.give(r.slot);
        }
    }

    /// Places a block of `faces` faces (see the module's comment for the
    /// order of resorts). The caller must forget every evicted block.
    pub fn place(
        &mut self,
        device: &wgpu::Device,
        draw_layout: &wgpu::BindGroupLayout,
        key: BlockKey,
        faces: u32,
        frame: u64,
        protected: &HashSet<BlockKey>,
    ) -> Placement {
        let pages = pages_for(faces);
        let mut evicted = Vec::new();
        let mut victims = None;
        loop {
            if let Some(slot) = self.arena.take(pages) {
                self.resident.insert(key, Resident { slot, last_visible: frame });
                self.note_peak();
                return Placement { slot: Some(slot), evicted };
            }
            let chunk_pages = self.chunk_pages_for(pages);
            if self.used_bytes() + chunk_pages as u64 * PAGE_BYTES <= self.budget {
                self.arena.add_chunk(device, draw_layout, chunk_pages);
                continue;
            }
            // An empty chunk that cannot hold the block is worth less than room for one that can.
            if self.arena.drop_empty_chunk() {
                continue;
            }
            let victims = victims.get_or_insert_with(|| self.victims(protected));
            match victims.next() {
                Some((_, victim)) => {
                    self.evict(&victim);
                    evicted.push(victim);
                }
                None => return Placement { slot: None, evicted },
            }
        }
    }

    /// Bytes the budget has left.
    pub fn headroom(&self) -> u64 {
        self.budget.saturating_sub(self.used_bytes())
    }

    /// Makes `bytes` of headroom for a fixed target about to grow: drops
    /// empty chunks, then evicts the least recently visible unprotected
    /// blocks, until it is there or nothing is left to give; returns the
    /// blocks evicted.
    pub fn make_headroom(&mut self, bytes: u64, protected: &HashSet<BlockKey>) -> Vec<BlockKey> {
        self.evict_until(protected, |r| r.headroom() >= bytes)
    }

    /// Evicts until within the budget (after the budget or the fixed targets
    /// changed), never a protected block; returns the blocks evicted.
    pub fn enforce_budget(&mut self, protected: &HashSet<BlockKey>) -> Vec<BlockKey> {
        self.evict_until(protected, |r| r.used_bytes() <= r.budget)
    }

    /// Drops empty chunks, then evicts unprotected blocks least recently
    /// visible first, until `done` holds or nothing is left to give.
    fn evict_until(&mut self, protected: &HashSet<BlockKey>, done: impl Fn(&Self) -> bool) -> Vec<BlockKey> {
        let mut evicted = Vec::new();
        let mut victims = None;
        while !done(self) {
            if self.arena.drop_empty_chunk() {
                continue;
            }
            let victims = victims.get_or_insert_with(|| self.victims(protected));
            let Some((_, victim)) = victims.next() else { break };
            self.evict(&victim);
            evicted.push(victim);
        }
        evicted
    }
}
