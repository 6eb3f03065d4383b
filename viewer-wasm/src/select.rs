//! Screen-space LOD selection (seed 003): start at the coarsest level and refine
//! a block into its existing children while its error ([`lod_error`]: its
//! geometric error from the manifest, how far in grid units its voxels can put
//! surface away from the level-0 voxels, capped at half its voxels' diagonal)
//! projects larger than a pixel threshold, culling blocks whose tight bounds
//! leave the frustum. The error never shrinks towards coarser levels, so
//! refinement stops exactly where the error is small enough.
//! Plus the rule that keeps a coarser block on screen until its children load.

use std::cmp::Ordering;
use std::collections::BTreeSet;

use glam::{Mat4, Vec3, Vec4};
use voxstream_format::{BlockEntry, BlockKey, Manifest, PageRef, SceneIndex};

/// What the selection needs to know about the view.
#[derive(Debug, Clone, Copy)]
pub struct ViewParams {
    pub view_proj: Mat4,
    pub eye: Vec3,
    /// Pixels per grid unit at distance 1 (viewport height / (2 tan(fov/2))).
    pub focal_pixels: f32,
}

/// Seed 003's two ways to show a view while finer blocks stream in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Refinement {
    /// A block stays drawn until every child that replaces it is ready: no holes, ever.
    #[default]
    AlwaysClosed,
    /// A ready block is drawn at once and hides its ancestor: finer sooner,
    /// with holes where siblings are still missing (an ancestor shows only
    /// while nothing below it is ready).
    HolesAllowed,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelectParams {
    /// Refine while a block's geometric error projects larger than this many pixels.
    pub max_error_pixels: f32,
    /// Stop refining once this many blocks are selected.
    pub max_blocks: usize,
    pub refinement: Refinement,
}

impl Default for SelectParams {
    fn default() -> Self {
        // Issue 10: 1 px of projected geometric error by default.
        Self { max_error_pixels: 1.0, max_blocks: 16_384, refinement: Refinement::AlwaysClosed }
    }
}

/// An axis-aligned box in grid units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn distance_to(&self, p: Vec3) -> f32 {
        let d = (self.min - p).max(p - self.max).max(Vec3::ZERO);
        d.length()
    }

    /// The common part, if the boxes overlap (touching counts).
    pub fn intersection(&self, other: &Aabb) -> Option<Aabb> {
        let b = Aabb { min: self.min.max(other.min), max: self.max.min(other.max) };
        b.min.cmple(b.max).all().then_some(b)
    }

    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.min(other.min), max: self.max.max(other.max) }
    }
}

/// Tight grid-unit bounds of a block's voxels.
pub fn entry_bounds(entry: &BlockEntry) -> Aabb {
    let (min, max) = entry.bounds.grid_units(entry.key.level);
    let v = |a: [f64; 3]| Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32);
    Aabb { min: v(min), max: v(max) }
}

/// Tight grid-unit bounds of a block's voxels, if the index knows the block.
pub fn block_bounds(index: &SceneIndex, key: &BlockKey) -> Option<Aabb> {
    index.block(key).map(entry_bounds)
}

/// Bounds of everything in the scene: the root block's.
pub fn scene_bounds(manifest: &Manifest) -> Option<Aabb> {
    Some(entry_bounds(&manifest.root))
}

/// The six planes of a wgpu (depth 0..1) frustum, as `n·p + d >= 0` inside.
#[derive(Debug, Clone, Copy)]
pub struct Frustum {
    planes: [Vec4; 6],
}

impl Frustum {
    pub fn from_view_proj(m: Mat4) -> Self {
        let (r0, r1, r2, r3) = (m.row(0), m.row(1), m.row(2), m.row(3));
        Self { planes: [r3 + r0, r3 - r0, r3 + r1, r3 - r1, r2, r3 - r2] }
    }

    pub fn intersects(&self, b: &Aabb) -> bool {
        self.planes.iter().all(|p| {
            // The box corner furthest along the plane normal.
            let corner = Vec3::select(p.truncate().cmpge(Vec3::ZERO), b.max, b.min);
            p.truncate().dot(corner) + p.w >= 0.0
        })
    }
}

/// Half a voxel's diagonal in voxel edges: how far a drawn cube's points lie from its centre.
pub const HALF_DIAGONAL: f32 = 0.866_025_4;

/// The error a block is refined by: its geometric error (the build's bound on how far its voxel
/// cubes reach from the level-0 voxels) capped at half its voxels' diagonal, `√3/2 · 2^level` grid
/// units. Why the cap: every block of a curved scan holds cubes that the surface only clips at a
/// corner, so the bound tends to √3 edges as level 0 gets finer (0.87 at level 1, 1.52 at level 3),
/// and a finer build of the same scan would refine the same view to physically finer voxels:
/// 4× the bytes from 2048 to 8192 on the dragon. Capped, a view draws the same physical level at
/// any build resolution (docs/streaming.md). It never shrinks towards coarser levels (both terms
/// grow with level), so refinement still stops where the error is small enough.
pub fn lod_error(entry: &BlockEntry) -> f32 {
    entry.geometric_error.min(HALF_DIAGONAL * (1u64 << entry.key.level) as f32)
}

/// Projected size, in pixels, of a geometric error of `error` grid units at
/// the nearest point of `bounds`. An eye inside the bounds sees any nonzero error as infinite.
pub fn error_pixels(error: f32, bounds: &Aabb, view: &ViewParams) -> f32 {
    if error <= 0.0 {
        return 0.0;
    }
    let dist = bounds.distance_to(view.eye);
    if dist <= 1e-6 {
        return f32::INFINITY;
    }
    error * view.focal_pixels / dist
}

pub(crate) struct Candidate {
    pub key: BlockKey,
    pub pixels: f32,
}

impl PartialEq for Candidate {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Candidate {}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Candidate {
    fn cmp(&self, other: &Self) -> Ordering {
        self.pixels.total_cmp(&other.pixels).then_with(|| other.key.cmp(&self.key))
    }
}

/// What a view wants: blocks to draw, and the hierarchy pages that must load
/// before some of them can be refined.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Selection {
    /// Sorted by key (coarser levels last).
    pub blocks: Vec<BlockKey>,
    /// Pages below blocks that want refining, largest projected error first.
    pub pages: Vec<PageRef>,
}

/// The blocks to show for this view: [`crate::traverse::traverse`] without
/// a byte budget or occlusion feedback.
pub fn select_blocks(
    index: &SceneIndex,
    root: &BlockKey,
    view: &ViewParams,
    params: &SelectParams,
) -> Selection {
    let params = crate::traverse::TraverseParams {
        max_error_pixels: params.max_error_pixels,
        max_blocks: params.max_blocks,
        ..Default::default()
    };
    let t = crate::traverse::traverse(index, root, view, &params, &Default::default());
    Selection { blocks: t.blocks, pages: t.pages }
}

/// [`resolve_draw_set`] for either refinement mode. Holes allowed: every
/// ready wanted block, plus the nearest ready ancestor of a missing one only
/// while no wanted block below that ancestor is ready.
pub fn resolve_draw_set_in(
    mode: Refinement,
    wanted: &[BlockKey],
    max_level: u8,
    is_ready: impl Fn(&BlockKey) -> bool,
) -> Vec<BlockKey> {
    if mode == Refinement::AlwaysClosed {
        return resolve_draw_set(wanted, max_level, is_ready);
    }
    let ready: BTreeSet<BlockKey> = wanted.iter().copied().filter(|k| is_ready(k)).collect();
    let under = |ancestor: &BlockKey| {
        ready.iter().any(|k| {
            let mut a = *k;
            while a.level < ancestor.level {
                a = a.parent();
            }
            a == *ancestor && k != ancestor
        })
    };
    let mut chosen = ready.clone();
    for key in wanted.iter().filter(|k| !ready.contains(k)) {
        let mut k = *key;
        while k.level < max_level {
            k = k.parent();
            if is_ready(&k) {
                if !under(&k) {
                    chosen.insert(k);
                }
                break;
            }
        }
    }
    chosen.into_iter().collect()
}

/// What to draw now for the `wanted` selection: each wanted block if it is
/// ready, else its nearest ready ancestor, and no block together with one of
/// its ancestors (the ancestor already covers that space). This keeps the
/// coarser block on screen until all of the children that replace it are ready,
/// so nothing pops to empty while streaming.
pub fn resolve_draw_set(
    wanted: &[BlockKey],
    max_level: u8,
    is_ready: impl Fn(&BlockKey) -> bool,
) -> Vec<BlockKey> {
    let mut chosen = BTreeSet::new();
    for key in wanted {
        let mut k = *key;
        loop {
            if is_ready(&k) {
                chosen.insert(k);
                break;
            }
            if k.level >= max_level {
                break;
            }
            k = k.parent();
        }
    }
    let has_chosen_ancestor = |key: &BlockKey| {
        let mut k = *key;
        while k.level < max_level {
            k = k.parent();
            if chosen.contains(&k) {
                return true;
            }
        }
        false
    };
    chosen.iter().copied().filter(|k| !has_chosen_ancestor(k)).collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::camera::OrbitCamera;
    use voxstream_format::{BLOCK_SIZE, LevelInfo, PAGE_LEVELS, PageBuilder, VoxelBounds, load_scene_index};

    /// A full pyramid over a `res`³ grid where every block is filled edge to
    /// edge, as a fully loaded index (pages built and read back as a viewer would).
    fn pyramid_with(res: u32, error: impl Fn(&BlockKey) -> f32) -> (Manifest, SceneIndex) {
        let mut levels = Vec::new();
        let mut all = Vec::new();
        let mut level = 0u8;
        loop {
            let level_res = res >> level;
            let per_edge = level_res.div_ceil(BLOCK_SIZE);
            levels.push(LevelInfo {
                level,
                resolution: level_res,
                blocks: per_edge.pow(3),
                voxels: 0,
                bytes: 0,
            });
            for z in 0..per_edge {
                for y in 0..per_edge {
                    for x in 0..per_edge {
                        let key = BlockKey::new(level, x, y, z);
                        let min = key.coord().map(|c| c * BLOCK_SIZE);
                        let max = key.coord().map(|c| ((c + 1) * BLOCK_SIZE).min(level_res));
                        all.push(BlockEntry {
                            key,
                            bounds: VoxelBounds { min, max },
                            voxels: 1,
                            faces: 1,
                            bytes: 1,
                            hash: "0".repeat(64),
                            geometric_error: error(&key),
                            child_mask: 0,
                            location: Default::default(),
                        });
                    }
                }
            }
            if per_edge == 1 {
                break;
            }
            level += 1;
        }
        let mut builder = PageBuilder::new(level, PAGE_LEVELS);
        let mut pages = std::collections::HashMap::new();
        for e in all {
            for (r, bytes) in builder.add(e).unwrap() {
                pages.insert(r.hash.clone(), bytes);
            }
        }
        let top = builder.finish().unwrap();
        let (root, root_page) = (top.root, top.root_page);
        let m = voxstream_format::test_support::manifest("pyramid", res, levels, root, root_page);
        m.validate().unwrap();
        let index = load_scene_index(&m, |r, _| {
            pages.get(&r.hash).cloned().ok_or_else(|| std::io::Error::other("missing page"))
        })
        .unwrap();
        (m, index)
    }

    /// The bound for a diagonal surface (lod.rs): √3 per halving.
    pub(crate) fn pyramid(res: u32) -> (Manifest, SceneIndex) {
        pyramid_with(res, |k| ((1u32 << k.level) - 1) as f32 * 3f32.sqrt())
    }

    fn select(m: &(Manifest, SceneIndex), view: &ViewParams, params: &SelectParams) -> Vec<BlockKey> {
        let sel = select_blocks(&m.1, &m.0.root.key, view, params);
        assert!(sel.pages.is_empty(), "a loaded index needs no page");
        sel.blocks
    }

    fn view_of(cam: &OrbitCamera, height: f32) -> ViewParams {
        ViewParams { view_proj: cam.view_proj(1.0), eye: cam.eye(), focal_pixels: cam.focal_pixels(height) }
    }

    #[test]
    fn frustum_culls_boxes_behind_and_beside() {
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(256.0));
        let f = Frustum::from_view_proj(cam.view_proj(1.0));
        let around = |c: Vec3| Aabb { min: c - 1.0, max: c + 1.0 };
        assert!(f.intersects(&around(cam.target)));
        assert!(!f.intersects(&around(cam.eye() - cam.forward() * 10.0)), "behind the eye");
        assert!(!f.intersects(&around(cam.target + Vec3::new(0.0, 10_000.0, 0.0))), "far above");
    }

    #[test]
    fn far_view_selects_only_the_root_and_near_view_refines() {
        let m = pyramid(512);
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        cam.distance *= 20.0;
        cam.scene_radius *= 20.0;
        let far = select(&m, &view_of(&cam, 400.0), &SelectParams::default());
        assert_eq!(far, vec![BlockKey::new(3, 0, 0, 0)]);

        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        let near = select(&m, &view_of(&cam, 2000.0), &SelectParams::default());
        assert!(near.iter().any(|k| k.level == 0), "a 2000 px view of a 512 grid needs level 0: {near:?}");
        // The selection tiles space: no block together with its ancestor.
        for k in &near {
            let mut p = *k;
            while p.level < 3 {
                p = p.parent();
                assert!(!near.contains(&p), "{k} and its ancestor {p} both selected");
            }
        }
    }

    #[test]
    fn selection_respects_the_pixel_rule_and_budget() {
        let m = pyramid(512);
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        let view = view_of(&cam, 700.0);
        let params = SelectParams::default();
        let sel = select(&m, &view, &params);
        for k in &sel {
            let error = lod_error(m.1.block(k).unwrap());
            let px = error_pixels(error, &block_bounds(&m.1, k).unwrap(), &view);
            assert!(k.level == 0 || px <= params.max_error_pixels, "{k} left at {px} px");
        }
        let tight = select(&m, &view, &SelectParams { max_blocks: 10, ..params });
        assert!(tight.len() <= 10 && !tight.is_empty());
    }

    #[test]
    fn blocks_with_small_error_are_not_refined() {
        // Same view, same level: the block whose measured error is small stays
        // coarse, the one with a large error is refined.
        let m = pyramid_with(512, |k| match k.level {
            0 => 0.0,
            3 => 1e3,
            _ => 1e-3,
        });
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        let view = view_of(&cam, 700.0);
        let sel = select(&m, &view, &SelectParams::default());
        assert!(sel.iter().all(|k| k.level == 2), "{sel:?}");
        assert_eq!(sel.len(), 8);
        let px = error_pixels(2.0, &Aabb { min: Vec3::ZERO, max: Vec3::ONE }, &view);
        assert!(px > 0.0 && px.is_finite());
        assert_eq!(error_pixels(0.0, &Aabb { min: Vec3::ZERO, max: Vec3::ONE }, &view), 0.0);
    }

    #[test]
    fn culled_blocks_are_not_selected() {
        let m = pyramid(512);
        let mut cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(512.0));
        // Look closely at one corner: most level-0 blocks are off screen.
        cam.target = Vec3::splat(32.0);
        cam.distance = 60.0;
        let view = view_of(&cam, 600.0);
        let sel = select(&m, &view, &SelectParams::default());
        let f = Frustum::from_view_proj(view.view_proj);
        assert!(sel.iter().all(|k| f.intersects(&block_bounds(&m.1, k).unwrap())));
        assert!(sel.len() < 100, "{} blocks for a corner view", sel.len());
    }

    #[test]
    fn refinement_waits_for_the_page_below() {
        // A 4096 grid has 7 levels: the root page spans levels 5..3, pages below root at level 3.
        let m = pyramid_with(4096, |k| ((1u32 << k.level) - 1) as f32 * 3f32.sqrt());
        let cam = OrbitCamera::framing(Vec3::ZERO, Vec3::splat(4096.0));
        let view = view_of(&cam, 2000.0);
        let mut index = SceneIndex::new(&m.0);
        let first = select_blocks(&index, &m.0.root.key, &view, &SelectParams::default());
        assert_eq!(first.blocks, vec![m.0.root.key], "only the root is known");
        assert_eq!(first.pages, m.0.root_page.iter().cloned().collect::<Vec<_>>());
        // Load just the root page: selection descends to level 3 and asks for pages there.
        let full = &m.1;
        let root_page = m.0.root_page.clone().unwrap();
        let entries: Vec<BlockEntry> =
            full.blocks().filter(|e| e.key.level >= 3 && e.key.level < 6).cloned().collect();
        let mut page = voxstream_format::HierarchyPage {
            root: root_page.root,
            page_levels: PAGE_LEVELS,
            packs: vec![],
            child_pages: vec![],
            entries,
        };
        page.entries.sort_by_key(|e| e.key);
        page.child_pages = page
            .entries
            .iter()
            .filter(|e| e.key.level == 3)
            .map(|e| PageRef { root: e.key, hash: "1".repeat(64), bytes: 64, location: Default::default() })
            .collect();
        index.insert_page(page).unwrap();
        let second = select_blocks(&index, &m.0.root.key, &view, &SelectParams::default());
        assert!(second.blocks.iter().all(|k| k.level >= 3), "{:?}", second.blocks);
        assert!(!second.pages.is_empty() && second.pages.iter().all(|p| p.root.level == 3));
        // Control: the fully loaded index refines below level 3.
        assert!(select(&m, &view, &SelectParams::default()).iter().any(|k| k.level < 3));
    }

    #[test]
    fn holes_allowed_draws_ready_children_at_once() {
        let root = BlockKey::new(1, 0, 0, 0);
        let children = root.children().unwrap();
        let ready = |k: &BlockKey| *k == root || *k == children[0];
        // Holes allowed: the ready child shows, the root goes (holes where siblings are).
        assert_eq!(resolve_draw_set_in(Refinement::HolesAllowed, &children, 1, ready), vec![children[0]]);
        // Control: always closed keeps the root until all children are ready.
        assert_eq!(resolve_draw_set_in(Refinement::AlwaysClosed, &children, 1, ready), vec![root]);
        // Nothing below ready yet: both show the root first.
        assert_eq!(resolve_draw_set_in(Refinement::HolesAllowed, &children, 1, |k| *k == root), vec![root]);
    }

    #[test]
    fn draw_set_falls_back_to_ready_ancestors() {
        let root = BlockKey::new(2, 0, 0, 0);
        let mids = root.children().unwrap();
        let fines = mids[0].children().unwrap();
        let mut wanted: Vec<BlockKey> = fines.to_vec();
        wanted.extend_from_slice(&mids[1..]);

        // Nothing ready: nothing drawn.
        assert!(resolve_draw_set(&wanted, 2, |_| false).is_empty());
        // Only the root ready: the root stands in for everything.
        assert_eq!(resolve_draw_set(&wanted, 2, |k| *k == root), vec![root]);
        // Everything but one fine block ready: its parent stands in for it and its
        // siblings, the other mids draw themselves.
        let missing = fines[3];
        let ready = |k: &BlockKey| *k != missing;
        let set = resolve_draw_set(&wanted, 2, ready);
        let mut expect: Vec<BlockKey> = vec![mids[0]];
        expect.extend_from_slice(&mids[1..]);
        expect.sort();
        assert_eq!(set, expect);
        // All ready: exactly the wanted set.
        let mut all = wanted.clone();
        all.sort();
        assert_eq!(resolve_draw_set(&wanted, 2, |_| true), all);
    }
}
