//! The AO's occupancy clipmap built on the GPU (viewer-wasm/src/clipmap.rs,
//! shaders/clipmap_clear.wgsl and clipmap_splat.wgsl, on lavapipe) against
//! its CPU model, cell for cell:
//!
//! - a first build equals the model of its sources and regions;
//! - after the camera moves (levels scroll: only the newly exposed slabs are
//!   cleared and re-splatted) and blocks arrive and leave (splatted in and
//!   out), the clipmap equals the model built from scratch for the new state,
//!   and an unchanged state costs no work;
//! - each level's filterable texture, which the trace reads, holds every
//!   cell's opacities (clipmap_texels.wgsl) after every update: only the
//!   boxes an update changed are copied;
//! - negative controls: the same sequence with the scroll's clear skipped
//!   leaves stale cells and does not match; updates that skip the texture
//!   copy leave textures that do not match their cells.

use glam::Vec3;
use voxstream_format::{BLOCK_SIZE, Block, BlockKey, PackedVoxel, oct_encode};
use voxstream_viewer::clipmap::{ClipmapLayout, ClipmapModel, OccupancyClipmap};
use voxstream_viewer::offscreen::{Gpu, read_clipmap_cells, read_clipmap_texels};

const GRID: u32 = 512;

/// A block with a pseudo-random surface: a tilted sheet with varying coverage.
fn block(level: u8, coord: [u32; 3], seed: u32) -> Block {
    let mut voxels = Vec::new();
    let mut state = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
    for y in 0..BLOCK_SIZE {
        for x in 0..BLOCK_SIZE {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            if state.is_multiple_of(3) {
                continue;
            }
            let z = (x / 3 + y / 5 + seed) % BLOCK_SIZE;
            let coverage = if level == 0 { 255 } else { (state >> 8) as u8 | 1 };
            voxels.push(PackedVoxel::new([x, y, z], 1, oct_encode([0.0, 0.0, 1.0])).with_coverage(coverage));
        }
    }
    voxels.sort_by_key(|v| v.morton());
    Block { key: BlockKey::new(level, coord[0], coord[1], coord[2]), voxels }
}

struct State<'a> {
    eye: Vec3,
    sources: Vec<Vec<&'a Block>>,
}

fn keys(sources: &[Vec<&Block>]) -> Vec<Vec<BlockKey>> {
    sources.iter().map(|l| l.iter().map(|b| b.key).collect()).collect()
}

fn run(
    gpu: &Gpu,
    clipmap: &mut OccupancyClipmap,
    layout: ClipmapLayout,
    all: &[Block],
    state: &State,
) -> bool {
    run_on(GRID, gpu, clipmap, layout, all, state)
}

/// Runs one update; returns whether it replaced the clipmap's buffers (allocated them in the frame).
fn run_on(
    grid: u32,
    gpu: &Gpu,
    clipmap: &mut OccupancyClipmap,
    layout: ClipmapLayout,
    all: &[Block],
    state: &State,
) -> bool {
    let find = |k: &BlockKey| all.iter().find(|b| b.key == *k);
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    let replaced = clipmap.update(
        &gpu.device,
        &gpu.queue,
        &mut encoder,
        grid,
        layout,
        state.eye,
        Vec3::X,
        &keys(&state.sources),
        find,
        None,
    );
    gpu.queue.submit([encoder.finish()]);
    replaced
}

fn model(layout: ClipmapLayout, state: &State) -> ClipmapModel {
    model_on(GRID, layout, state)
}

fn model_on(grid: u32, layout: ClipmapLayout, state: &State) -> ClipmapModel {
    let origins: Vec<[i32; 3]> =
        (0..layout.levels).map(|k| layout.origin(k, state.eye, Vec3::X, grid)).collect();
    ClipmapModel::build(layout, &origins, &state.sources)
}

/// Cells that differ between the GPU and the model, over every level; the
/// level textures must hold the GPU's cells (`texel_mismatches`).
fn mismatches(gpu: &Gpu, clipmap: &OccupancyClipmap, expected: &ClipmapModel) -> usize {
    let cells = read_clipmap_cells(&gpu.device, &gpu.queue, clipmap).expect("read back the clipmap");
    assert_eq!(cells.len(), expected.levels.len());
    assert_eq!(texel_mismatches(gpu, clipmap), 0, "a level texture differs from its cells");
    cells.iter().zip(&expected.levels).map(|(a, b)| a.iter().zip(b).filter(|(x, y)| x != y).count()).sum()
}

/// Texels that differ (beyond their 8 bits) from what the cell in their
/// slot says (its three words: each axis's opacity and their sum, clamped to
/// 1), the aprons (texel N of a level, which repeats slot 0) included.
fn texel_mismatches(gpu: &Gpu, clipmap: &OccupancyClipmap) -> usize {
    let cells = read_clipmap_cells(&gpu.device, &gpu.queue, clipmap).expect("read back the clipmap");
    let texels = read_clipmap_texels(&gpu.device, &gpu.queue, clipmap).expect("read back the textures");
    assert_eq!(cells.len(), texels.len());
    let n = clipmap.layout().expect("built").cells as usize;
    let mut wrong = 0;
    for (words, level) in cells.iter().zip(&texels) {
        assert_eq!(words.len(), n * n * n * 3);
        assert_eq!(level.len(), (n + 1).pow(3));
        for (i, t) in level.iter().enumerate() {
            let [x, y, z] = [i % (n + 1), (i / (n + 1)) % (n + 1), i / (n + 1).pow(2)].map(|c| c % n);
            let w = &words[((z * n + y) * n + x) * 3..][..3];
            let o = [0, 1, 2].map(|a| (w[a] as f32 / 4096.0).min(1.0));
            let want = [o[0], o[1], o[2], (o[0] + o[1] + o[2]).min(1.0)];
            if want.iter().zip(t).any(|(a, b)| (a - b).abs() > 0.51 / 255.0) {
                wrong += 1;
            }
        }
    }
    wrong
}

#[test]
fn the_gpu_clipmap_matches_its_model_through_scrolls_arrivals_and_departures() {
    let gpu = Gpu::new().expect("a Vulkan adapter (lavapipe)");
    // Level-0 blocks around the eye, a level-1 block and a level-2 one further out.
    let all = vec![
        block(0, [1, 1, 1], 1),
        block(0, [2, 1, 1], 2),
        block(0, [1, 2, 1], 3),
        block(0, [2, 2, 2], 4),
        block(1, [0, 0, 1], 5),
        block(2, [1, 0, 0], 6),
        // Arrive together at the end.
        block(0, [1, 1, 2], 7),
        block(0, [2, 1, 2], 8),
        block(0, [1, 2, 2], 9),
        block(0, [2, 2, 1], 10),
        block(0, [1, 2, 0], 11),
        block(0, [2, 1, 0], 12),
    ];
    let layout = ClipmapLayout { cells: 64, finest_cell: 1, levels: 4 };
    // Level k's sources: level-0 blocks in the fine levels, the coarse ones everywhere.
    let by_level = |fine: &[usize]| -> Vec<Vec<&Block>> {
        (0..layout.levels)
            .map(|k| {
                let mut v: Vec<&Block> = fine.iter().map(|&i| &all[i]).collect();
                if k >= 1 {
                    v.push(&all[4]);
                }
                v.push(&all[5]);
                v
            })
            .collect()
    };
    let first = State { eye: Vec3::new(130.0, 120.0, 110.0), sources: by_level(&[0, 1, 2]) };
    let mut clipmap = OccupancyClipmap::new(&gpu.device, layout.cells);
    run(&gpu, &mut clipmap, layout, &all, &first);
    let expected = model(layout, &first);
    let filled: usize = expected.levels.iter().map(|l| l.iter().filter(|&&v| v > 0).count()).sum();
    assert!(filled > 5000, "the test scene must fill cells: {filled}");
    assert_eq!(mismatches(&gpu, &clipmap, &expected), 0, "first build");
    let rebuild_splats = clipmap.counters.splats;

    // The eye moves by a few cells on every axis (levels 0 and 1 scroll), block 1
    // leaves and block 3 arrives.
    let second = State { eye: Vec3::new(141.5, 113.0, 117.0), sources: by_level(&[0, 2, 3]) };
    let origins_before: Vec<_> = clipmap.levels().iter().map(|l| l.origin).collect();
    run(&gpu, &mut clipmap, layout, &all, &second);
    let origins_after: Vec<_> = clipmap.levels().iter().map(|l| l.origin).collect();
    assert_ne!(origins_before[0], origins_after[0], "level 0 must scroll");
    assert_eq!(mismatches(&gpu, &clipmap, &model(layout, &second)), 0, "after a scroll and a source change");
    assert!(clipmap.counters.splats > rebuild_splats, "the update splatted nothing");
    // Incremental: the same state again does no work at all.
    let counters = clipmap.counters;
    run(&gpu, &mut clipmap, layout, &all, &second);
    assert_eq!(clipmap.counters, counters, "an unchanged state was splatted again");

    // Back to where it started: exactly the first state again.
    run(&gpu, &mut clipmap, layout, &all, &first);
    assert_eq!(mismatches(&gpu, &clipmap, &expected), 0, "after scrolling back");

    // Six blocks arrive at once, and leave. Blocks that come back after leaving
    // get new words; a batch that does not fit beside the live words moves
    // those to a larger buffer first. Every splat must find its block's words.
    let crowded = State { eye: first.eye, sources: by_level(&[0, 1, 2, 6, 7, 8, 9, 10, 11]) };
    run(&gpu, &mut clipmap, layout, &all, &crowded);
    assert_eq!(mismatches(&gpu, &clipmap, &model(layout, &crowded)), 0, "after the crowd arrived");
    run(&gpu, &mut clipmap, layout, &all, &first);
    assert_eq!(mismatches(&gpu, &clipmap, &expected), 0, "after the crowd left");
    assert!(
        clipmap.counters.word_moves >= 1,
        "the voxel words never moved: the checks above missed that case"
    );

    // Negative control: scrolls that skip clearing the exposed cells leave stale sums.
    let mut broken = OccupancyClipmap::new(&gpu.device, layout.cells);
    broken.skip_scroll_clear = true;
    run(&gpu, &mut broken, layout, &all, &first);
    run(&gpu, &mut broken, layout, &all, &second);
    let wrong = mismatches(&gpu, &broken, &model(layout, &second));
    assert!(wrong > 100, "a scroll without its clear still matched ({wrong} cells differ)");

    // Negative control: textures not copied after the first build fall behind their cells.
    let mut stale = OccupancyClipmap::new(&gpu.device, layout.cells);
    run(&gpu, &mut stale, layout, &all, &first);
    assert_eq!(texel_mismatches(&gpu, &stale), 0, "first build");
    stale.skip_texel_copy = true;
    run(&gpu, &mut stale, layout, &all, &second);
    let behind = texel_mismatches(&gpu, &stale);
    assert!(behind > 100, "textures left behind still matched their cells ({behind} texels differ)");
}

#[test]
fn a_layout_change_rebuilds_every_level() {
    let gpu = Gpu::new().expect("a Vulkan adapter (lavapipe)");
    let all = vec![block(0, [3, 3, 3], 7), block(1, [1, 1, 1], 8)];
    let fine = ClipmapLayout { cells: 64, finest_cell: 1, levels: 4 };
    let coarse = ClipmapLayout { cells: 64, finest_cell: 2, levels: 3 };
    let eye = Vec3::new(200.0, 210.0, 220.0);
    let mut clipmap = OccupancyClipmap::new(&gpu.device, 64);
    let state = |layout: ClipmapLayout| State {
        eye,
        sources: (0..layout.levels).map(|_| vec![&all[0], &all[1]]).collect(),
    };
    run(&gpu, &mut clipmap, fine, &all, &state(fine));
    assert_eq!(mismatches(&gpu, &clipmap, &model(fine, &state(fine))), 0);
    run(&gpu, &mut clipmap, coarse, &all, &state(coarse));
    assert_eq!(clipmap.counters.rebuilds, 2);
    assert_eq!(mismatches(&gpu, &clipmap, &model(coarse, &state(coarse))), 0, "after the layout change");
    // Control: the fine model is not what the coarse clipmap holds.
    let fine_as_coarse =
        ClipmapModel { layout: coarse, levels: model(fine, &state(fine)).levels[..3].to_vec() };
    assert!(mismatches(&gpu, &clipmap, &fine_as_coarse) > 100);
}

/// The cells and textures are allocated once, for the most levels the scene
/// can have: a reserved clipmap (as the renderer makes it, before streaming)
/// changes layout as the finest drawn level falls without allocating in a
/// frame, and the first update of an unreserved one allocates for every
/// later layout too. Each state still matches its model.
#[test]
fn layout_changes_allocate_nothing_after_the_reserve() {
    let gpu = Gpu::new().expect("a Vulkan adapter (lavapipe)");
    let all = vec![block(0, [3, 3, 3], 7), block(1, [1, 1, 1], 8)];
    let layouts = [
        ClipmapLayout::for_scene(GRID, 4, 64),
        ClipmapLayout::for_scene(GRID, 2, 64),
        ClipmapLayout::for_scene(GRID, 1, 64),
    ];
    assert_eq!(layouts.map(|l| l.levels), [3, 4, 5], "coarse to fine, one level more each");
    let eye = Vec3::new(200.0, 210.0, 220.0);
    let state = |layout: ClipmapLayout| State {
        eye,
        sources: (0..layout.levels).map(|_| vec![&all[0], &all[1]]).collect(),
    };
    let mut reserved = OccupancyClipmap::new(&gpu.device, 64);
    assert!(reserved.reserve(&gpu.device, GRID), "the reserve allocates");
    assert!(!reserved.reserve(&gpu.device, GRID), "once");
    // Control: without the reserve the first update allocates, then never again.
    let mut lazy = OccupancyClipmap::new(&gpu.device, 64);
    for (i, layout) in layouts.into_iter().enumerate() {
        assert!(!run(&gpu, &mut reserved, layout, &all, &state(layout)), "layout {i} allocated");
        assert_eq!(mismatches(&gpu, &reserved, &model(layout, &state(layout))), 0, "layout {i}");
        assert_eq!(run(&gpu, &mut lazy, layout, &all, &state(layout)), i == 0, "layout {i}, unreserved");
        assert_eq!(mismatches(&gpu, &lazy, &model(layout, &state(layout))), 0, "layout {i}, unreserved");
    }
    assert_eq!(reserved.counters.rebuilds, 3);
}

/// A 32768³ scene with level-0 blocks resident takes all 8 levels of 128³ cells: 192 MiB of
/// cells, past the 128 MiB WebGPU allows one storage binding (lavapipe's device has the
/// default). Each pass binds its level's range; when the passes bound the whole buffer, the
/// first update of every scene from 4096³ on failed validation (a panic in `voxstream render`,
/// no AO in the browser). Every level must match the model, the coarse ones too: a pass
/// binding the wrong level's range leaves its own level empty.
#[test]
fn a_full_size_clipmap_binds_each_level_within_the_storage_limit() {
    let gpu = Gpu::new().expect("a Vulkan adapter (lavapipe)");
    let grid = 32768;
    let layout = ClipmapLayout::for_scene(grid, 1, 128);
    assert_eq!((layout.cells, layout.levels), (128, 8));
    let cells_bytes = layout.levels as u64 * layout.level_words() * 4;
    let limit = gpu.device.limits().max_storage_buffer_binding_size;
    assert!(cells_bytes > limit, "the levels together ({cells_bytes} B) must pass the limit ({limit} B)");
    // Each level's sources at about its cell size: level-0 blocks for the fine levels, then a
    // level-3 block, then levels 6 and 7.
    let all = vec![
        block(0, [1, 1, 1], 1),
        block(0, [2, 1, 1], 2),
        block(3, [0, 0, 0], 3),
        block(6, [0, 0, 0], 4),
        block(7, [1, 0, 0], 5),
    ];
    let sources = (0..layout.levels)
        .map(|k| match k {
            0..=2 => vec![&all[0], &all[1]],
            3..=5 => vec![&all[2]],
            _ => vec![&all[3], &all[4]],
        })
        .collect();
    let state = State { eye: Vec3::new(130.0, 120.0, 110.0), sources };
    let mut clipmap = OccupancyClipmap::new(&gpu.device, layout.cells);
    run_on(grid, &gpu, &mut clipmap, layout, &all, &state);
    let expected = model_on(grid, layout, &state);
    for (k, level) in expected.levels.iter().enumerate() {
        assert!(level.iter().any(|&v| v > 0), "the test must fill level {k}");
    }
    assert_eq!(mismatches(&gpu, &clipmap, &expected), 0, "a level differs from its model");
}
