//! The hard GPU byte budget over the face arena (viewer-wasm/src/residency.rs,
//! face_arena.rs), on a real device (lavapipe): placement, eviction by least
//! recent visibility, protected blocks, chunk reuse and the budget lowered.

use rustc_hash::FxHashSet as HashSet;
use voxstream_format::BlockKey;
use voxstream_viewer::expand::block_bind_group_layout;
use voxstream_viewer::face_arena::{PAGE_BYTES, PAGE_FACES};
use voxstream_viewer::offscreen::Gpu;
use voxstream_viewer::residency::{CHUNK_SHARE_OF_BUDGET, Residency};

fn key(i: u32) -> BlockKey {
    BlockKey::new(0, i, 0, 0)
}

#[test]
fn the_arena_holds_blocks_within_the_budget_and_evicts_the_least_recently_visible() {
    let gpu = Gpu::new().expect("a Vulkan adapter (lavapipe)");
    let layout = block_bind_group_layout(&gpu.device);
    // 64 chunks' worth of budget at the smallest chunk (64 pages), 1 MiB fixed.
    let fixed = 1 << 20;
    let budget = fixed + CHUNK_SHARE_OF_BUDGET * 64 * PAGE_BYTES;
    let mut r = Residency::new(budget);
    r.set_fixed_bytes(fixed);
    let none = HashSet::default();
    // Blocks of 10 pages each, visible at frame i.
    let faces = 10 * PAGE_FACES;
    let mut placed = Vec::new();
    let mut evicted = Vec::new();
    for i in 0..200 {
        let p = r.place(&gpu.device, &layout, key(i), faces, i as u64, &none);
        assert!(r.used_bytes() <= budget, "block {i}: {} B over the budget {budget} B", r.used_bytes());
        evicted.extend(p.evicted);
        let slot = p.slot.unwrap_or_else(|| panic!("block {i} refused with nothing protected"));
        assert_eq!(slot.pages, 10);
        placed.push(slot);
    }
    let held = r.resident_count();
    assert!(held >= 90, "the budget of {} pages held only {held} blocks of 10", CHUNK_SHARE_OF_BUDGET * 64);
    assert_eq!(held + evicted.len(), 200);
    // Evicted in the order they were last visible, oldest first.
    assert_eq!(evicted, (0..evicted.len() as u32).map(key).collect::<Vec<_>>());
    // Resident runs never overlap.
    let mut live: Vec<_> = placed[evicted.len()..].to_vec();
    live.sort_by_key(|s| (s.chunk, s.first_page));
    for w in live.windows(2) {
        assert!(w[0].chunk != w[1].chunk || w[0].first_page + w[0].pages <= w[1].first_page, "{w:?} overlap");
    }
    // A block seen again is not the next to go.
    let oldest = evicted.len() as u32;
    r.mark_visible(&key(oldest), 1000);
    let p = r.place(&gpu.device, &layout, key(500), faces, 1001, &none);
    assert!(p.slot.is_some());
    assert!(!p.evicted.contains(&key(oldest)), "evicted a block visible at frame 1000: {:?}", p.evicted);
    assert!(p.evicted.contains(&key(oldest + 1)));
    // Protected blocks stay: with all of them protected a new block is refused, nothing evicted.
    let chunks = r.arena().chunk_count();
    let all: HashSet<BlockKey> = (0..=500).map(key).filter(|k| r.is_resident(k)).collect();
    let refused = r.place(&gpu.device, &layout, key(600), faces, 1002, &all);
    assert_eq!(refused.slot, None);
    assert!(refused.evicted.is_empty());
    assert!(r.used_bytes() <= budget);
    // Control: a block larger than the whole budget is refused too, whatever may go.
    let huge =
        r.place(&gpu.device, &layout, key(601), (budget / PAGE_BYTES) as u32 * PAGE_FACES, 1003, &none);
    assert_eq!(huge.slot, None);
    assert!(r.used_bytes() <= budget, "the refused block left the budget exceeded");
    // Its evictions emptied chunks; blocks coming back reuse them instead of making new ones.
    let gone = huge.evicted.len();
    assert!(gone > 0);
    for i in 0..gone.min(20) as u32 {
        assert!(r.place(&gpu.device, &layout, key(700 + i), faces, 1004, &none).slot.is_some());
    }
    assert!(r.arena().chunk_count() <= chunks);
    // A lower budget evicts down to it, protected blocks kept.
    let keep = key(700);
    let lower = fixed + (r.used_bytes() - fixed) / 2;
    r.set_budget(lower);
    let out = r.enforce_budget(&[keep].into_iter().collect());
    assert!(r.used_bytes() <= lower, "{} B over the lowered budget {lower} B", r.used_bytes());
    assert!(!out.contains(&keep) && r.is_resident(&keep));
}
