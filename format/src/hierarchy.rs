//! The paged block hierarchy (format 4): the manifest holds the root block and
//! a reference to the root page; every other block's entry lives in a
//! [`HierarchyPage`], a binary, content-addressed file covering a subtree of
//! [`PAGE_LEVELS`] levels, fetched when a traversal reaches it (Potree 2's
//! hierarchy chunks and 3D Tiles' external tilesets do the same).
//!
//! **Page roots.** Levels `L ≥ 1` with `(coarsest − L) % page_levels == 0`.
//! The page rooted at block `R` (on a page-root level) lists the blocks
//! strictly below `R` at depths `1..=page_levels`, sorted by key; `R`'s own
//! entry lives in the page above (or the manifest). Each entry at depth
//! `page_levels` that has children is itself a page root, and the page lists a
//! [`PageRef`] to it. Pages therefore form a Merkle tree: a page's hash covers
//! its children's hashes, so they are written bottom-up ([`PageBuilder`]).
//!
//! **Packs.** The encoded bytes of blocks live in packs,
//! `packs/<blake3 of the pack>.vxp` in the scene directory: blocks' bytes
//! concatenated in the order the writer finished them (post order). A pack
//! spans several pages (the writer closes one at 256 blocks or 8 MiB), so a
//! scene is a few objects, not one per page. A page lists the packs its
//! entries lie in (hash and length each), so the page's hash covers them and
//! the Merkle chain reaches every block byte; an entry's `location.pack`
//! indexes that list, bytes `[offset, offset + bytes)`. [`NO_PACK`] means the
//! block is its own file `blocks/<key>.vxb` (no writer makes those any more;
//! the tests' unpacked pages use it).
//!
//! Binary page layout (little endian), version 4:
//!
//! ```text
//! 0  magic "VXHP"
//! 4  version u8 (4), page_levels u8, reserved 2 zero bytes
//! 8  root: level u8, x, y, z u32
//! 21 entry count u32, child page count u32, pack count u32 (at most entries + child pages)
//! 33 payload length u32 (decompressed; must equal what the counts imply)
//! 37 lz4 block of the payload:
//!    packs        count × (blake3 32, length u64)                                 = 40 bytes
//!    child pages  count × (level u8, x, y, z u32, bytes u32, blake3 32,
//!                          pack u32, offset u64)                                  = 61 bytes
//!    entries      count × (level u8, x, y, z u32, child_mask u8,
//!                          bounds min 3 × u8, max 3 × u8 (block-local, 0..=64),
//!                          voxels u32, faces u32, bytes u32, geometric_error f32,
//!                          blake3 32, pack u32, offset u64)                       = 80 bytes
//! ```
//!
//! Versions 1 and 2 (one pack per page, named in the header) belong to format-3
//! scenes and version 3 (child pages as files) to format-4 scenes, which the manifest check refuses with a rebuild message; a page of
//! another version is refused the same way.
//!
//! **Invariant:** [`HierarchyPage::decode`] never panics and never allocates
//! more than the counts imply after checking them against a hard cap; a
//! decoded page is exactly what [`HierarchyPage::encode`] would write, every
//! entry is a descendant of the root within `page_levels` levels, every
//! packed entry's range lies inside the pack it names, and every pack the page
//! lists holds at least one of its entries.

use std::collections::{BTreeMap, HashMap};

use rustc_hash::FxHashMap;
use serde::{Deserialize, Serialize};

use crate::{BLOCK_SIZE, BlockEntry, BlockKey, Manifest, VoxelBounds};

/// Levels one page spans below its root.
pub const PAGE_LEVELS: u8 = 3;
pub const PAGE_MAGIC: [u8; 4] = *b"VXHP";
const PAGE_VERSION: u8 = 4;
/// The page header, the shortest any page can be.
pub const PAGE_HEADER_LEN: usize = 37;
const PACK_REF_LEN: usize = 40;
const CHILD_PAGE_LEN: usize = 61;
const ENTRY_LEN: usize = 80;
/// A page holds at most the full subtree of `page_levels ≤ 4` levels: 8 + 64 + 512 + 4096 blocks.
pub const MAX_PAGE_ENTRIES: u32 = 8 + 64 + 512 + 4096;
/// `pack` value of a block stored as its own file `blocks/<key>.vxb`.
pub const NO_PACK: u32 = u32::MAX;

/// Where a block's bytes are: its own file, or a byte range of a pack its page
/// lists (`pack` indexes that list; `[offset, offset + bytes)`). While a page
/// is being built, `pack` is the writer's pack serial ([`PageBuilder`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BlockLocation {
    pub pack: u32,
    pub offset: u64,
}

impl BlockLocation {
    /// The block is its own file.
    pub const FILE: BlockLocation = BlockLocation { pack: NO_PACK, offset: 0 };

    pub fn is_file(&self) -> bool {
        self.pack == NO_PACK
    }
}

impl Default for BlockLocation {
    fn default() -> Self {
        Self::FILE
    }
}

/// A pack as a page (or the manifest, for the root block) names it:
/// content-addressed, `packs/<hash>.vxp`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PackRef {
    /// blake3 of the pack bytes, hex.
    pub hash: String,
    /// Length of the pack in bytes.
    pub bytes: u64,
}

/// The bytes of one block inside a pack.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PackRange {
    pub pack: PackRef,
    pub offset: u64,
    pub bytes: u32,
}

impl PackRange {
    /// One past the last byte.
    pub fn end(&self) -> u64 {
        self.offset.saturating_add(self.bytes as u64)
    }
}

/// A pack's file in a scene directory.
pub fn pack_path(hash: &str) -> String {
    format!("packs/{hash}.vxp")
}

/// Whether `[offset, offset + bytes)` lies inside a pack of `pack_bytes`.
pub fn range_in_pack(offset: u64, bytes: u32, pack_bytes: u64) -> bool {
    offset.checked_add(bytes as u64).is_some_and(|end| end <= pack_bytes)
}

/// Whether `s` is 64 lowercase hex digits (a blake3 content address).
pub fn is_content_hash(s: &str) -> bool {
    unhex(s).is_some()
}

/// A page as its parent (or the manifest) names it: content-addressed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PageRef {
    pub root: BlockKey,
    /// blake3 of the page bytes, hex.
    pub hash: String,
    pub bytes: u32,
    /// Where the page's bytes are: its own file `pages/<root>.vxh`, or `[offset, offset + bytes)`
    /// of the pack at `location.pack` in the naming page's pack list (the manifest's
    /// `root_page_pack` for the root page). Pages live in packs so a scene is one object per
    /// pack, not one per page as well.
    #[serde(default, skip_serializing_if = "BlockLocation::is_file")]
    pub location: BlockLocation,
}

#[derive(Debug, Clone, PartialEq)]
pub struct HierarchyPage {
    pub root: BlockKey,
    pub page_levels: u8,
    /// The packs holding the entries' bytes, indexed by `location.pack`, in
    /// the order the writer closed them.
    pub packs: Vec<PackRef>,
    /// Pages rooted at this page's deepest entries, sorted by root.
    pub child_pages: Vec<PageRef>,
    /// Sorted by key.
    pub entries: Vec<BlockEntry>,
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PageError {
    #[error("page is {0} bytes, shorter than its header")]
    Truncated(usize),
    #[error("page does not start with the VXHP magic")]
    BadMagic,
    #[error("page header is invalid: {0}")]
    BadHeader(String),
    #[error("page payload is corrupt: {0}")]
    Corrupt(String),
    #[error("page is inconsistent: {0}")]
    Inconsistent(String),
    #[error("page for {root} has hash {got}, expected {expected}")]
    HashMismatch { root: BlockKey, got: String, expected: String },
    #[error("pages must be added children before parents: {0}")]
    Order(String),
}

/// Whether blocks of `level` root pages, in a tree whose root is on `coarsest`.
pub fn is_page_root_level(level: u8, coarsest: u8, page_levels: u8) -> bool {
    level >= 1 && level <= coarsest && (coarsest - level).is_multiple_of(page_levels.max(1))
}

/// The root of the page that lists `key`'s entry; `None` for the tree's root.
pub fn page_root_of(key: &BlockKey, coarsest: u8, page_levels: u8) -> Option<BlockKey> {
    if key.level >= coarsest {
        return None;
    }
    let mut r = key.parent();
    while !is_page_root_level(r.level, coarsest, page_levels) {
        r = r.parent();
    }
    Some(r)
}

/// A page's file in a scene directory.
pub fn page_path(root: &BlockKey) -> String {
    format!("pages/{root}.vxh")
}

/// The `depth`-th ancestor of `key` (0 = itself).
fn ancestor(key: &BlockKey, depth: u8) -> BlockKey {
    BlockKey::new(key.level + depth, key.x >> depth, key.y >> depth, key.z >> depth)
}

fn hex(bytes: &[u8; 32]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut s = String::with_capacity(64);
    for b in bytes {
        s.push(DIGITS[(b >> 4) as usize] as char);
        s.push(DIGITS[(b & 15) as usize] as char);
    }
    s
}

fn unhex(s: &str) -> Option<[u8; 32]> {
    let b = s.as_bytes();
    if b.len() != 64 {
        return None;
    }
    let nibble = |c: u8| match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        _ => None,
    };
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = nibble(b[2 * i])? << 4 | nibble(b[2 * i + 1])?;
    }
    Some(out)
}

/// blake3 of `bytes`, hex: the content address of blocks, pages and packs.
pub fn content_hash(bytes: &[u8]) -> String {
    hex(blake3::hash(bytes).as_bytes())
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        // Callers check the total length first, so this never runs past the end.
        let out: [u8; N] = self.bytes[self.at..self.at + N].try_into().expect("length checked");
        self.at += N;
        out
    }
    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
    fn key(&mut self) -> BlockKey {
        let level = self.u8();
        BlockKey::new(level, self.u32(), self.u32(), self.u32())
    }
}

fn put_key(out: &mut Vec<u8>, k: &BlockKey) {
    out.push(k.level);
    for c in k.coord() {
        out.extend_from_slice(&c.to_le_bytes());
    }
}

/// Each hash is checked as 64 lowercase hex digits by [`HierarchyPage::validate`].
fn put_hash(out: &mut Vec<u8>, h: &str) {
    out.extend_from_slice(&unhex(h).unwrap_or([0; 32]));
}

impl HierarchyPage {
    /// The binary page; deterministic for equal pages.
    pub fn encode(&self) -> Vec<u8> {
        let mut raw = Vec::with_capacity(
            self.packs.len() * PACK_REF_LEN
                + self.child_pages.len() * CHILD_PAGE_LEN
                + self.entries.len() * ENTRY_LEN,
        );
        for p in &self.packs {
            put_hash(&mut raw, &p.hash);
            raw.extend_from_slice(&p.bytes.to_le_bytes());
        }
        for c in &self.child_pages {
            put_key(&mut raw, &c.root);
            raw.extend_from_slice(&c.bytes.to_le_bytes());
            put_hash(&mut raw, &c.hash);
            raw.extend_from_slice(&c.location.pack.to_le_bytes());
            raw.extend_from_slice(&c.location.offset.to_le_bytes());
        }
        for e in &self.entries {
            put_key(&mut raw, &e.key);
            raw.push(e.child_mask);
            let base = e.key.coord().map(|c| c.wrapping_mul(BLOCK_SIZE));
            for corner in [e.bounds.min, e.bounds.max] {
                for (v, b) in corner.iter().zip(base) {
                    raw.push(v.saturating_sub(b).min(255) as u8);
                }
            }
            raw.extend_from_slice(&e.voxels.to_le_bytes());
            raw.extend_from_slice(&e.faces.to_le_bytes());
            raw.extend_from_slice(&e.bytes.to_le_bytes());
            raw.extend_from_slice(&e.geometric_error.to_le_bytes());
            put_hash(&mut raw, &e.hash);
            raw.extend_from_slice(&e.location.pack.to_le_bytes());
            raw.extend_from_slice(&e.location.offset.to_le_bytes());
        }
        let mut out = Vec::with_capacity(PAGE_HEADER_LEN + raw.len() / 2);
        out.extend_from_slice(&PAGE_MAGIC);
        out.extend_from_slice(&[PAGE_VERSION, self.page_levels, 0, 0]);
        put_key(&mut out, &self.root);
        for n in [self.entries.len(), self.child_pages.len(), self.packs.len(), raw.len()] {
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        out.extend_from_slice(&lz4_flex::block::compress(&raw));
        out
    }

    /// Decodes and validates a page, checking it is the one `expected` names
    /// (root and content hash).
    pub fn decode(bytes: &[u8], expected: &PageRef) -> Result<Self, PageError> {
        let got = content_hash(bytes);
        if got != expected.hash {
            return Err(PageError::HashMismatch {
                root: expected.root,
                got,
                expected: expected.hash.clone(),
            });
        }
        let page = Self::decode_unverified(bytes)?;
        if page.root != expected.root {
            return Err(PageError::Inconsistent(format!(
                "page is rooted at {}, expected {}",
                page.root, expected.root
            )));
        }
        Ok(page)
    }

    /// Decodes and validates a page without checking its content hash.
    pub fn decode_unverified(bytes: &[u8]) -> Result<Self, PageError> {
        if bytes.len() < PAGE_HEADER_LEN {
            return Err(PageError::Truncated(bytes.len()));
        }
        if bytes[..4] != PAGE_MAGIC {
            return Err(PageError::BadMagic);
        }
        let version = bytes[4];
        if version != PAGE_VERSION {
            return Err(PageError::BadHeader(format!(
                "version {version} is not {PAGE_VERSION}: rebuild the scene from its mesh with `voxstream build`"
            )));
        }
        let mut h = Reader { bytes: &bytes[..PAGE_HEADER_LEN], at: 5 };
        let page_levels = h.u8();
        let reserved = h.take::<2>();
        if !(1..=4).contains(&page_levels) || reserved != [0, 0] {
            return Err(PageError::BadHeader(format!("page levels {page_levels} or reserved bytes")));
        }
        let root = h.key();
        let (entries, children, packs, payload) = (h.u32(), h.u32(), h.u32(), h.u32());
        if root.level == 0 || root.level > crate::MAX_LEVEL {
            return Err(PageError::BadHeader(format!("root {root} cannot root a page")));
        }
        // Each pack holds at least one of the page's blocks or child pages (`validate`), and a
        // page's blocks and child pages may each lie in a pack of their own: a page over coarse
        // levels, whose blocks close late, can name more packs than it has entries.
        if entries == 0 || entries > MAX_PAGE_ENTRIES || children > entries || packs > entries + children {
            return Err(PageError::BadHeader(format!(
                "{entries} entries, {children} child pages, {packs} packs"
            )));
        }
        let expected_len =
            packs as usize * PACK_REF_LEN + children as usize * CHILD_PAGE_LEN + entries as usize * ENTRY_LEN;
        if payload as usize != expected_len {
            return Err(PageError::BadHeader(format!(
                "payload length {payload} does not match the counts ({expected_len})"
            )));
        }
        let mut raw = vec![0u8; expected_len];
        let written = lz4_flex::block::decompress_into(&bytes[PAGE_HEADER_LEN..], &mut raw)
            .map_err(|e| PageError::Corrupt(e.to_string()))?;
        if written != expected_len {
            return Err(PageError::Corrupt(format!("payload is {written} bytes, expected {expected_len}")));
        }
        let mut r = Reader { bytes: &raw, at: 0 };
        let pack_list = (0..packs)
            .map(|_| {
                let hash = hex(&r.take::<32>());
                PackRef { hash, bytes: r.u64() }
            })
            .collect();
        let child_pages = (0..children)
            .map(|_| {
                let root = r.key();
                let bytes = r.u32();
                let hash = hex(&r.take::<32>());
                PageRef { root, bytes, hash, location: BlockLocation { pack: r.u32(), offset: r.u64() } }
            })
            .collect();
        let mut list = Vec::with_capacity(entries as usize);
        for _ in 0..entries {
            let key = r.key();
            let child_mask = r.u8();
            let lo = r.take::<3>();
            let hi = r.take::<3>();
            let base = key.coord().map(|c| c as u64 * BLOCK_SIZE as u64);
            if base.iter().any(|&b| b + BLOCK_SIZE as u64 > u32::MAX as u64) {
                return Err(PageError::Inconsistent(format!("block {key} lies outside any grid")));
            }
            let bounds = VoxelBounds {
                min: std::array::from_fn(|a| (base[a] + lo[a] as u64) as u32),
                max: std::array::from_fn(|a| (base[a] + hi[a] as u64) as u32),
            };
            let voxels = r.u32();
            let faces = r.u32();
            let bytes = r.u32();
            let geometric_error = r.f32();
            let hash = hex(&r.take::<32>());
            let location = BlockLocation { pack: r.u32(), offset: r.u64() };
            list.push(BlockEntry {
                key,
                bounds,
                voxels,
                faces,
                bytes,
                geometric_error,
                hash,
                child_mask,
                location,
            });
        }
        let page = HierarchyPage { root, page_levels, packs: pack_list, child_pages, entries: list };
        page.validate()?;
        Ok(page)
    }

    /// That `what`'s `bytes` at `location` lie inside one of this page's packs.
    fn check_pack_range(&self, what: &str, location: &BlockLocation, bytes: u32) -> Result<(), PageError> {
        let bad = |s: String| Err(PageError::Inconsistent(s));
        let Some(p) = self.packs.get(location.pack as usize) else {
            return bad(format!("{what} names pack {} of {}", location.pack, self.packs.len()));
        };
        if !range_in_pack(location.offset, bytes, p.bytes) {
            return bad(format!(
                "{what} lies at bytes {}..{} of a {}-byte pack",
                location.offset,
                location.offset as u128 + bytes as u128,
                p.bytes
            ));
        }
        Ok(())
    }

    /// The invariants a reader relies on; [`PageBuilder`] only writes pages that pass.
    pub fn validate(&self) -> Result<(), PageError> {
        let bad = |s: String| Err(PageError::Inconsistent(s));
        let depth_of = |k: &BlockKey| self.root.level.checked_sub(k.level);
        if !self.entries.windows(2).all(|w| w[0].key < w[1].key) {
            return bad("entries are not sorted and unique".into());
        }
        if !self.child_pages.windows(2).all(|w| w[0].root < w[1].root) {
            return bad("child pages are not sorted and unique".into());
        }
        // Fx, not SipHash: a viewer validates every page it loads on its main thread, and a
        // page of thousands of entries is looked up about ten times an entry.
        let keys: rustc_hash::FxHashSet<BlockKey> = self.entries.iter().map(|e| e.key).collect();
        let known = |k: &BlockKey| keys.contains(k);
        for e in &self.entries {
            let Some(depth) = depth_of(&e.key).filter(|d| (1..=self.page_levels).contains(d)) else {
                return bad(format!(
                    "block {} is not within {} levels below {}",
                    e.key, self.page_levels, self.root
                ));
            };
            if ancestor(&e.key, depth) != self.root {
                return bad(format!("block {} is not below {}", e.key, self.root));
            }
            if depth > 1 && !known(&e.key.parent()) {
                return bad(format!("block {} has no parent in the page", e.key));
            }
            if e.key.level == 0 && e.child_mask != 0 {
                return bad(format!("level-0 block {} claims children", e.key));
            }
            if e.key.level > 0 && depth < self.page_levels {
                let children = e.key.children().expect("level > 0");
                let mask = (0..8).fold(0u8, |m, i| m | ((known(&children[i]) as u8) << i));
                if mask != e.child_mask {
                    return bad(format!(
                        "block {} child mask {:#04x} disagrees with the page",
                        e.key, e.child_mask
                    ));
                }
            }
            let size = BLOCK_SIZE as u64;
            let inside = (0..3).all(|a| {
                let (lo, hi) = (e.bounds.min[a] as u64, e.bounds.max[a] as u64);
                let base = e.key.coord()[a] as u64 * size;
                base <= lo && lo < hi && hi <= base + size
            });
            if !inside {
                return bad(format!("block {} has bounds outside the block", e.key));
            }
            if !(e.geometric_error.is_finite() && e.geometric_error >= 0.0) {
                return bad(format!("block {} has geometric error {}", e.key, e.geometric_error));
            }
            if e.voxels == 0 || e.voxels > crate::BLOCK_VOXELS as u32 || e.faces == 0 || e.bytes == 0 {
                return bad(format!("block {} has counts {}/{}/{}", e.key, e.voxels, e.faces, e.bytes));
            }
            if unhex(&e.hash).is_none() {
                return bad(format!("block {} hash is not 64 hex digits", e.key));
            }
            if !e.location.is_file() {
                self.check_pack_range(&format!("block {}", e.key), &e.location, e.bytes)?;
            }
        }
        for c in self.child_pages.iter().filter(|c| !c.location.is_file()) {
            self.check_pack_range(&format!("child page {}", c.root), &c.location, c.bytes)?;
        }
        let mut used = vec![false; self.packs.len()];
        let blocks = self.entries.iter().map(|e| e.location);
        for location in blocks.chain(self.child_pages.iter().map(|c| c.location)).filter(|l| !l.is_file()) {
            used[location.pack as usize] = true;
        }
        if let Some(i) = used.iter().position(|u| !u) {
            return bad(format!("pack {i} of the page holds none of its blocks or child pages"));
        }
        let deepest: Vec<BlockKey> = self
            .entries
            .iter()
            .filter(|e| depth_of(&e.key) == Some(self.page_levels) && e.child_mask != 0)
            .map(|e| e.key)
            .collect();
        let child_roots: Vec<BlockKey> = self.child_pages.iter().map(|c| c.root).collect();
        if deepest != child_roots {
            return bad(format!(
                "{} child pages for {} deepest blocks with children",
                child_roots.len(),
                deepest.len()
            ));
        }
        for c in &self.child_pages {
            if unhex(&c.hash).is_none() || c.bytes < PAGE_HEADER_LEN as u32 {
                return bad(format!("child page {} is malformed", c.root));
            }
        }
        if self.packs.iter().any(|p| unhex(&p.hash).is_none()) {
            return bad("a pack hash is not 64 hex digits".into());
        }
        Ok(())
    }

    /// The reference naming this page's bytes.
    pub fn reference(&self, bytes: &[u8]) -> PageRef {
        PageRef {
            root: self.root,
            hash: content_hash(bytes),
            bytes: bytes.len() as u32,
            location: BlockLocation::FILE,
        }
    }
}

/// A page's entries and child pages, while its root block has not come
/// (open) or while it waits for its packs or child pages (held).
#[derive(Default)]
struct OpenPage {
    entries: Vec<BlockEntry>,
    child_pages: Vec<PageRef>,
    /// Child pages whose root block came but which are not sealed yet.
    unsealed_children: usize,
}

/// Builds pages as blocks are finished, children before parents (any such
/// order gives the same bytes).
///
/// Packed entries arrive with `location.pack` set to the writer's pack
/// *serial* (0, 1, 2, … in the order packs are closed; the pack is still open
/// when its blocks arrive). A page is content-addressed and names its packs
/// by hash, so it is sealed (encoded) only once every pack its entries lie in
/// is closed ([`Self::pack_closed`]) and every child page is sealed; until
/// then it is held. Memory: the entries of pages whose root has not come (a
/// front, one page a page layer in post order), of held pages (with one open
/// pack of at most N blocks in post order: at most one page a layer whose
/// entries came before that pack, plus pages rooted and filled within it,
/// together ≤ N entries: [`Self::held_entries`]), the child masks of blocks
/// not yet added and the hash of each closed pack.
pub struct PageBuilder {
    coarsest: u8,
    page_levels: u8,
    /// Whether sealed pages go into packs ([`Self::page_placed`]) rather than files of their own.
    pages_in_packs: bool,
    open: BTreeMap<BlockKey, OpenPage>,
    held: BTreeMap<BlockKey, OpenPage>,
    masks: HashMap<BlockKey, u8>,
    /// Closed packs by serial.
    closed_packs: Vec<PackRef>,
    root: Option<BlockEntry>,
    root_page: Option<PageRef>,
}

/// A finished page: its reference and its bytes (write them as `pages/<root>.vxh`).
pub type FinishedPage = (PageRef, Vec<u8>);

/// The hierarchy's top once every block is added: the root block's entry (a
/// packed root names pack 0, `root_pack`), the root page (in a pack: pack 0,
/// `root_page_pack`), and those packs.
#[derive(Debug, Clone, PartialEq)]
pub struct FinishedHierarchy {
    pub root: BlockEntry,
    pub root_page: Option<PageRef>,
    pub root_pack: Option<PackRef>,
    pub root_page_pack: Option<PackRef>,
}

impl PageBuilder {
    pub fn new(coarsest: u8, page_levels: u8) -> Self {
        Self {
            coarsest,
            page_levels: page_levels.clamp(1, 4),
            pages_in_packs: false,
            open: BTreeMap::new(),
            held: BTreeMap::new(),
            masks: HashMap::new(),
            closed_packs: Vec::new(),
            root: None,
            root_page: None,
        }
    }

    /// Pages are placed in packs: each page [`Self::add`] or [`Self::pack_closed`] returns must
    /// be appended to the open pack and reported with [`Self::page_placed`]; its parent is then
    /// sealed once that pack is closed too.
    pub fn with_pages_in_packs(mut self) -> Self {
        self.pages_in_packs = true;
        self
    }

    /// The sealed page rooted at `root` lies at `offset` of pack `serial` (still open).
    pub fn page_placed(&mut self, root: BlockKey, serial: u32, offset: u64) -> Result<(), PageError> {
        if !self.pages_in_packs || serial == NO_PACK || (serial as usize) < self.closed_packs.len() {
            return Err(PageError::Order(format!("page {root} placed in pack {serial}, which is not open")));
        }
        let slot = match page_root_of(&root, self.coarsest, self.page_levels) {
            Some(parent) => self
                .open
                .get_mut(&parent)
                .or_else(|| self.held.get_mut(&parent))
                .and_then(|p| p.child_pages.iter_mut().find(|c| c.root == root)),
            None => self.root_page.as_mut().filter(|r| r.root == root),
        };
        let Some(reference) = slot.filter(|r| r.location.is_file()) else {
            return Err(PageError::Order(format!("page {root} was not sealed or was placed twice")));
        };
        reference.location = BlockLocation { pack: serial, offset };
        Ok(())
    }

    /// Records a finished block; `entry.child_mask` is filled in here from the
    /// children added before it. A packed entry names its pack by serial (see
    /// the type's notes). Returns the pages that can be sealed now.
    pub fn add(&mut self, mut entry: BlockEntry) -> Result<Vec<FinishedPage>, PageError> {
        let key = entry.key;
        if key.level > self.coarsest || self.root.is_some() {
            return Err(PageError::Order(format!(
                "block {key} after the root or above level {}",
                self.coarsest
            )));
        }
        if !entry.location.is_file() && (entry.location.pack as usize) < self.closed_packs.len() {
            return Err(PageError::Order(format!(
                "block {key} names pack {}, which is already closed",
                entry.location.pack
            )));
        }
        entry.child_mask = self.masks.remove(&key).unwrap_or(0);
        if key.level < self.coarsest {
            let p = key.parent();
            let bit = 1u8 << ((key.x & 1) | (key.y & 1) << 1 | (key.z & 1) << 2);
            let m = self.masks.entry(p).or_insert(0);
            if *m & bit != 0 {
                return Err(PageError::Order(format!("block {key} added twice")));
            }
            *m |= bit;
        }
        let roots_page = is_page_root_level(key.level, self.coarsest, self.page_levels);
        if roots_page {
            let open = self.open.remove(&key).unwrap_or_default();
            if open.entries.is_empty() {
                return Err(PageError::Order(format!(
                    "block {key} roots a page but none of its children came first"
                )));
            }
            self.held.insert(key, open);
        }
        match page_root_of(&key, self.coarsest, self.page_levels) {
            Some(r) => {
                let open = self.open.entry(r).or_default();
                open.entries.push(entry);
                open.unsealed_children += roots_page as usize;
            }
            None => self.root = Some(entry),
        }
        if roots_page { self.seal_ready() } else { Ok(Vec::new()) }
    }

    /// Pack `serial` (the next one: packs close in serial order) is closed
    /// as `pack`. Returns the pages that can be sealed now.
    pub fn pack_closed(&mut self, serial: u32, pack: PackRef) -> Result<Vec<FinishedPage>, PageError> {
        if serial as usize != self.closed_packs.len() || serial == crate::hierarchy::NO_PACK {
            return Err(PageError::Order(format!(
                "pack {serial} closed, expected pack {}",
                self.closed_packs.len()
            )));
        }
        self.closed_packs.push(pack);
        self.seal_ready()
    }

    /// Entries of the pages held for a pack or a child page.
    pub fn held_entries(&self) -> usize {
        self.held.values().map(|p| p.entries.len()).sum()
    }

    fn sealable(&self, page: &OpenPage) -> bool {
        let closed = |l: &BlockLocation| l.is_file() || (l.pack as usize) < self.closed_packs.len();
        let placed = |c: &PageRef| !self.pages_in_packs || (!c.location.is_file() && closed(&c.location));
        page.unsealed_children == 0
            && page.entries.iter().all(|e| closed(&e.location))
            && page.child_pages.iter().all(placed)
    }

    /// Seals every held page whose packs are closed and whose child pages are
    /// sealed (children first, so a parent may follow in the same call).
    fn seal_ready(&mut self) -> Result<Vec<FinishedPage>, PageError> {
        let mut finished = Vec::new();
        loop {
            let ready: Vec<BlockKey> =
                self.held.iter().filter(|(_, p)| self.sealable(p)).map(|(k, _)| *k).collect();
            if ready.is_empty() {
                return Ok(finished);
            }
            for key in ready {
                let open = self.held.remove(&key).expect("listed as held");
                let (reference, bytes) = self.seal(key, open)?;
                match page_root_of(&key, self.coarsest, self.page_levels) {
                    Some(parent) => {
                        let p =
                            self.open.get_mut(&parent).or_else(|| self.held.get_mut(&parent)).ok_or_else(
                                || PageError::Order(format!("page {parent} above {key} is gone")),
                            )?;
                        p.child_pages.push(reference.clone());
                        p.unsealed_children -= 1;
                    }
                    None => self.root_page = Some(reference.clone()),
                }
                finished.push((reference, bytes));
            }
        }
    }

    /// Encodes a page, its pack serials mapped to indices into its pack list.
    fn seal(&self, root: BlockKey, open: OpenPage) -> Result<FinishedPage, PageError> {
        let locations =
            open.entries.iter().map(|e| e.location).chain(open.child_pages.iter().map(|c| c.location));
        let mut serials: Vec<u32> = locations.filter(|l| !l.is_file()).map(|l| l.pack).collect();
        serials.sort_unstable();
        serials.dedup();
        let mut page = HierarchyPage {
            root,
            page_levels: self.page_levels,
            packs: serials.iter().map(|&s| self.closed_packs[s as usize].clone()).collect(),
            child_pages: open.child_pages,
            entries: open.entries,
        };
        for e in page.entries.iter_mut().filter(|e| !e.location.is_file()) {
            e.location.pack = serials.binary_search(&e.location.pack).expect("collected above") as u32;
        }
        for c in page.child_pages.iter_mut().filter(|c| !c.location.is_file()) {
            c.location.pack = serials.binary_search(&c.location.pack).expect("collected above") as u32;
        }
        page.entries.sort_by_key(|e| e.key);
        page.child_pages.sort_by_key(|c| c.root);
        page.validate()?;
        let bytes = page.encode();
        Ok((page.reference(&bytes), bytes))
    }

    /// After the coarsest block and the last pack: the hierarchy's top.
    pub fn finish(self) -> Result<FinishedHierarchy, PageError> {
        if let Some(k) = self.open.keys().next() {
            return Err(PageError::Order(format!("page {k} never got its root block")));
        }
        if let Some(k) = self.held.keys().next() {
            return Err(PageError::Order(format!("page {k} still waits for a pack that was never closed")));
        }
        let mut root = self.root.ok_or_else(|| PageError::Order("no root block was added".into()))?;
        let root_pack = if root.location.is_file() {
            None
        } else {
            let pack = self.closed_packs.get(root.location.pack as usize).cloned().ok_or_else(|| {
                PageError::Order(format!("the root block's pack {} was never closed", root.location.pack))
            })?;
            root.location.pack = 0;
            Some(pack)
        };
        let mut root_page = self.root_page;
        let root_page_pack = match root_page.as_mut() {
            Some(page) if self.pages_in_packs => {
                let pack = self.closed_packs.get(page.location.pack as usize).cloned().ok_or_else(|| {
                    PageError::Order(format!("the root page's pack {} was never closed", page.location.pack))
                })?;
                page.location.pack = 0;
                Some(pack)
            }
            _ => None,
        };
        Ok(FinishedHierarchy { root, root_page, root_pack, root_page_pack })
    }
}

/// What a reader knows of a scene's hierarchy: every entry of the pages
/// loaded so far, and the pages it has been told of but not loaded.
#[derive(Debug, Clone)]
pub struct SceneIndex {
    page_levels: u8,
    root: BlockKey,
    /// The pack holding the root block (the manifest's `root_pack`).
    root_pack: Option<PackRef>,
    /// The pack holding the root page (the manifest's `root_page_pack`).
    root_page_pack: Option<PackRef>,
    /// Each loaded page's packs, by page root.
    packs: FxHashMap<BlockKey, Vec<PackRef>>,
    /// The viewer looks blocks up here many times a frame: FxHash, not SipHash.
    entries: FxHashMap<BlockKey, BlockEntry>,
    /// Pages named by a loaded page (or the manifest) and not loaded yet, by root, each with the
    /// pack its bytes lie in (`None`: its own file).
    pending: BTreeMap<BlockKey, (PageRef, Option<PackRef>)>,
    /// Pages loaded, by root, with their pack (a server answers page URLs from these).
    loaded: FxHashMap<BlockKey, (PageRef, Option<PackRef>)>,
    pages_loaded: usize,
    page_bytes_loaded: u64,
}

impl SceneIndex {
    pub fn new(manifest: &Manifest) -> Self {
        let mut entries = FxHashMap::default();
        entries.insert(manifest.root.key, manifest.root.clone());
        let pending = manifest
            .root_page
            .iter()
            .map(|r| {
                let pack = if r.location.is_file() { None } else { manifest.root_page_pack.clone() };
                (r.root, (r.clone(), pack))
            })
            .collect();
        Self {
            page_levels: manifest.page_levels,
            root: manifest.root.key,
            root_pack: manifest.root_pack.clone(),
            root_page_pack: manifest.root_page_pack.clone(),
            packs: FxHashMap::default(),
            entries,
            pending,
            loaded: FxHashMap::default(),
            pages_loaded: 0,
            page_bytes_loaded: 0,
        }
    }

    pub fn block(&self, key: &BlockKey) -> Option<&BlockEntry> {
        self.entries.get(key)
    }

    /// Where in a pack `key`'s bytes are: the pack its page lists at
    /// `location.pack` (the manifest's `root_pack` for the root block). `None` when the block is
    /// its own file (`blocks/<key>.vxb`) or not known.
    pub fn pack_range(&self, key: &BlockKey) -> Option<PackRange> {
        let e = self.entries.get(key)?;
        if e.location.is_file() {
            return None;
        }
        let pack = if *key == self.root {
            self.root_pack.as_ref()?
        } else {
            self.packs
                .get(&page_root_of(key, self.root.level, self.page_levels)?)?
                .get(e.location.pack as usize)?
        };
        Some(PackRange { pack: pack.clone(), offset: e.location.offset, bytes: e.bytes })
    }

    /// Every pack named so far (each once), in no particular order.
    pub fn packs(&self) -> impl Iterator<Item = &PackRef> {
        let mut seen = std::collections::HashSet::new();
        self.root_pack
            .iter()
            .chain(self.root_page_pack.iter())
            .chain(self.packs.values().flatten())
            .filter(move |p| seen.insert(p.hash.as_str()))
    }

    /// Every known entry, in no particular order.
    pub fn blocks(&self) -> impl Iterator<Item = &BlockEntry> {
        self.entries.values()
    }

    /// Known children of `key` (all of them once [`Self::pending_page_for`] is `None`).
    pub fn children(&self, key: &BlockKey) -> impl Iterator<Item = &BlockEntry> {
        let mask = self.entries.get(key).map_or(0, |e| e.child_mask);
        self.children_by_mask(key, mask)
    }

    /// [`Self::children`] of an entry already at hand (one lookup fewer: the
    /// viewer's traversal visits thousands of blocks a run).
    pub fn children_of<'a>(&'a self, entry: &BlockEntry) -> impl Iterator<Item = &'a BlockEntry> + use<'a> {
        self.children_by_mask(&entry.key, entry.child_mask)
    }

    fn children_by_mask(&self, key: &BlockKey, mask: u8) -> impl Iterator<Item = &BlockEntry> + use<'_> {
        key.children()
            .into_iter()
            .flatten()
            .enumerate()
            .filter(move |(i, _)| mask & (1 << i) != 0)
            .filter_map(|(_, c)| self.entries.get(&c))
    }

    /// The page to load before `key`'s children are known; `None` when they are
    /// (or it has none).
    pub fn pending_page_for(&self, key: &BlockKey) -> Option<&PageRef> {
        self.pending_page_below(self.entries.get(key)?)
    }

    /// [`Self::pending_page_for`] of an entry already at hand.
    pub fn pending_page_below(&self, entry: &BlockEntry) -> Option<&PageRef> {
        if entry.child_mask == 0 {
            return None;
        }
        self.pending.get(&entry.key).map(|(r, _)| r)
    }

    pub fn missing_pages(&self) -> impl Iterator<Item = &PageRef> {
        self.pending.values().map(|(r, _)| r)
    }

    /// Where in a pack a page named but not loaded yet lies; `None` when it is its own file
    /// (`pages/<root>.vxh`) or not named.
    pub fn page_range(&self, root: &BlockKey) -> Option<PackRange> {
        let (r, pack) = self.pending.get(root)?;
        Some(PackRange { pack: pack.clone()?, offset: r.location.offset, bytes: r.bytes })
    }

    /// Every loaded page's reference and, when it lies in a pack, its range there.
    pub fn loaded_pages(&self) -> impl Iterator<Item = (&PageRef, Option<PackRange>)> {
        self.loaded.values().map(|(r, pack)| {
            (r, pack.clone().map(|pack| PackRange { pack, offset: r.location.offset, bytes: r.bytes }))
        })
    }

    /// A loaded page's reference and, when it lies in a pack, its range there.
    pub fn loaded_page(&self, root: &BlockKey) -> Option<(&PageRef, Option<PackRange>)> {
        let (r, pack) = self.loaded.get(root)?;
        let range = pack.clone().map(|pack| PackRange { pack, offset: r.location.offset, bytes: r.bytes });
        Some((r, range))
    }

    /// A page named so far, loaded or not, and its range when it lies in a pack.
    pub fn page(&self, root: &BlockKey) -> Option<(&PageRef, Option<PackRange>)> {
        self.loaded_page(root).or_else(|| {
            let (r, pack) = self.pending.get(root)?;
            Some((r, pack.clone().map(|pack| PackRange { pack, offset: r.location.offset, bytes: r.bytes })))
        })
    }

    /// Whether `root`'s page is named and not loaded yet.
    pub fn is_pending(&self, root: &BlockKey) -> bool {
        self.pending.contains_key(root)
    }

    /// The next page to load before `key`'s entry is known: the topmost page on the path from the
    /// tree's root down to `key` that is named but not loaded. `None` once every page on the path
    /// is loaded (then [`Self::block`] answers for good), or when the path leaves the named
    /// pages (then no page can list `key`, and it is not in the scene).
    ///
    /// A reader that loads what this returns until it is `None` fetches only the pages on one
    /// path: a lookup costs at most `levels / page_levels` pages, whatever the scene's size.
    pub fn page_toward(&self, key: &BlockKey) -> Option<&PageRef> {
        let coarsest = self.root.level;
        let mut path = Vec::new();
        let mut k = *key;
        while let Some(r) = page_root_of(&k, coarsest, self.page_levels) {
            path.push(r);
            k = r;
        }
        if k != self.root {
            return None;
        }
        for r in path.iter().rev() {
            if !self.loaded.contains_key(r) {
                return self.pending.get(r).map(|(p, _)| p);
            }
        }
        None
    }

    pub fn pages_loaded(&self) -> usize {
        self.pages_loaded
    }

    /// Bytes of the pages loaded so far, as their references state them.
    pub fn page_bytes_loaded(&self) -> u64 {
        self.page_bytes_loaded
    }

    pub fn is_complete(&self) -> bool {
        self.pending.is_empty()
    }

    /// Adds a decoded page the index is waiting for.
    pub fn insert_page(&mut self, page: HierarchyPage) -> Result<(), PageError> {
        if !self.pending.contains_key(&page.root) {
            return Err(PageError::Inconsistent(format!("page {} was not asked for", page.root)));
        }
        if page.page_levels != self.page_levels {
            return Err(PageError::Inconsistent(format!(
                "page {} spans {} levels, the manifest says {}",
                page.root, page.page_levels, self.page_levels
            )));
        }
        let root_mask = self.entries.get(&page.root).map_or(0, |e| e.child_mask);
        let mask = page
            .entries
            .iter()
            .filter(|e| e.key.level + 1 == page.root.level)
            .fold(0u8, |m, e| m | 1 << ((e.key.x & 1) | (e.key.y & 1) << 1 | (e.key.z & 1) << 2));
        if mask != root_mask {
            return Err(PageError::Inconsistent(format!(
                "page {} children {mask:#04x} disagree with its root's mask {root_mask:#04x}",
                page.root
            )));
        }
        if let Some((r, pack)) = self.pending.remove(&page.root) {
            self.page_bytes_loaded += r.bytes as u64;
            self.loaded.insert(page.root, (r, pack));
        }
        for c in page.child_pages {
            // `validate` checked the index against the page's pack list.
            let pack = (!c.location.is_file()).then(|| page.packs[c.location.pack as usize].clone());
            self.pending.insert(c.root, (c, pack));
        }
        if !page.packs.is_empty() {
            self.packs.insert(page.root, page.packs);
        }
        for e in page.entries {
            self.entries.insert(e.key, e);
        }
        self.pages_loaded += 1;
        Ok(())
    }
}

/// Why a whole index could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum IndexError<E: std::error::Error + 'static> {
    #[error("hierarchy page {root}: {source}")]
    Read { root: BlockKey, source: E },
    #[error(transparent)]
    Page(#[from] PageError),
}

/// Loads every page of a scene through `read` (bytes of the page a reference names: the pack
/// range given, or its own file when `None`).
pub fn load_scene_index<E: std::error::Error + 'static>(
    manifest: &Manifest,
    mut read: impl FnMut(&PageRef, Option<PackRange>) -> Result<Vec<u8>, E>,
) -> Result<SceneIndex, IndexError<E>> {
    let mut index = SceneIndex::new(manifest);
    loop {
        let next = index.missing_pages().next().cloned();
        let Some(r) = next else { break };
        let range = index.page_range(&r.root);
        let bytes = read(&r, range).map_err(|source| IndexError::Read { root: r.root, source })?;
        index.insert_page(HierarchyPage::decode(&bytes, &r)?)?;
    }
    Ok(index)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use proptest::prelude::*;

    use super::*;
    use crate::{LevelInfo, morton3};

    fn entry(key: BlockKey) -> BlockEntry {
        let base = key.coord().map(|c| c * BLOCK_SIZE);
        BlockEntry {
            key,
            bounds: VoxelBounds { min: base.map(|b| b + 1), max: base.map(|b| b + 3 + (key.x % 7)) },
            voxels: 10 + key.x,
            faces: 20 + key.y,
            bytes: 100 + key.z,
            geometric_error: key.level as f32 * 1.5,
            hash: content_hash(&key.to_string().into_bytes()),
            child_mask: 0,
            location: BlockLocation::FILE,
        }
    }

    /// Every block of a tree over `level0` keys up to a single root, finest level first.
    fn tree(level0: &[[u32; 3]]) -> Vec<Vec<BlockKey>> {
        let mut levels =
            vec![level0.iter().map(|c| BlockKey::new(0, c[0], c[1], c[2])).collect::<BTreeSet<_>>()];
        while levels.last().unwrap().len() > 1
            || levels.last().unwrap().iter().next().unwrap().coord() != [0; 3]
        {
            let next = levels.last().unwrap().iter().map(|k| k.parent()).collect();
            levels.push(next);
        }
        levels.into_iter().map(|l| l.into_iter().collect()).collect()
    }

    fn build(order: &[BlockKey], coarsest: u8) -> (Vec<FinishedPage>, BlockEntry, Option<PageRef>) {
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        let mut pages = Vec::new();
        for k in order {
            pages.extend(b.add(entry(*k)).unwrap());
        }
        let top = b.finish().unwrap();
        assert!(top.root_pack.is_none());
        (pages, top.root, top.root_page)
    }

    /// What [`build_packed`] made.
    struct Packed {
        pages: Vec<FinishedPage>,
        top: FinishedHierarchy,
        /// Every pack closed, in order.
        packs: Vec<PackRef>,
        /// The most entries held at once for a pack or a child page.
        most_held: usize,
    }

    /// [`build`] as the store's writer does it: each block's bytes appended to
    /// the one open pack, which closes after `per_pack` blocks and at the end.
    fn build_packed(order: &[BlockKey], coarsest: u8, per_pack: usize) -> Packed {
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        let (mut serial, mut len, mut in_pack) = (0u32, 0u64, 0usize);
        let mut out = Packed {
            pages: Vec::new(),
            top: FinishedHierarchy {
                root: entry(order[0]),
                root_page: None,
                root_pack: None,
                root_page_pack: None,
            },
            packs: Vec::new(),
            most_held: 0,
        };
        let close = |b: &mut PageBuilder, serial: &mut u32, len: &mut u64, out: &mut Packed| {
            let pack = PackRef { hash: content_hash(format!("pack {serial}").as_bytes()), bytes: *len };
            out.packs.push(pack.clone());
            out.pages.extend(b.pack_closed(*serial, pack).unwrap());
            (*serial, *len) = (*serial + 1, 0);
        };
        for k in order {
            let mut e = entry(*k);
            e.location = BlockLocation { pack: serial, offset: len };
            len += e.bytes as u64;
            in_pack += 1;
            out.pages.extend(b.add(e).unwrap());
            out.most_held = out.most_held.max(b.held_entries());
            if in_pack == per_pack {
                close(&mut b, &mut serial, &mut len, &mut out);
                in_pack = 0;
            }
        }
        if in_pack > 0 {
            close(&mut b, &mut serial, &mut len, &mut out);
        }
        out.top = b.finish().unwrap();
        out
    }

    /// A writer that puts blocks and pages into packs: each sealed page is appended to the open
    /// pack (which closes after `per_pack` items), as the store's writer will.
    struct PagePackWriter {
        b: PageBuilder,
        packs: Vec<(PackRef, Vec<u8>)>,
        open: Vec<u8>,
        items: usize,
        pages: usize,
    }

    impl PagePackWriter {
        fn serial(&self) -> u32 {
            self.packs.len() as u32
        }

        fn place(&mut self, sealed: Vec<FinishedPage>) {
            for (r, bytes) in sealed {
                self.b.page_placed(r.root, self.serial(), self.open.len() as u64).unwrap();
                self.open.extend(bytes);
                self.items += 1;
                self.pages += 1;
            }
        }

        fn close(&mut self) {
            let bytes = std::mem::take(&mut self.open);
            let pack = PackRef { hash: content_hash(&bytes), bytes: bytes.len() as u64 };
            self.packs.push((pack.clone(), bytes));
            self.items = 0;
            let sealed = self.b.pack_closed(self.serial() - 1, pack).unwrap();
            self.place(sealed);
        }

        /// The manifest naming `top` (with its root block's and root page's packs), and the
        /// packs' bytes by hash.
        fn manifest_and_packs(
            &self,
            top: &FinishedHierarchy,
            coarsest: u8,
        ) -> (Manifest, HashMap<String, Vec<u8>>) {
            let mut manifest = manifest_for(top.root.clone(), top.root_page.clone(), coarsest);
            manifest.root_pack = top.root_pack.clone();
            manifest.root_page_pack = top.root_page_pack.clone();
            (manifest, self.packs.iter().map(|(p, b)| (p.hash.clone(), b.clone())).collect())
        }

        fn run(order: &[BlockKey], coarsest: u8, per_pack: usize) -> (Self, FinishedHierarchy) {
            let b = PageBuilder::new(coarsest, PAGE_LEVELS).with_pages_in_packs();
            let mut w = Self { b, packs: Vec::new(), open: Vec::new(), items: 0, pages: 0 };
            for k in order {
                let mut e = entry(*k);
                e.location = BlockLocation { pack: w.serial(), offset: w.open.len() as u64 };
                w.open.extend(std::iter::repeat_n(k.level, e.bytes as usize));
                w.items += 1;
                let sealed = w.b.add(e).unwrap();
                w.place(sealed);
                // A close can seal pages into the next pack and fill it too (one item a pack).
                while w.items >= per_pack {
                    w.close();
                }
            }
            // Each close may seal the next page layer into a new pack; the root page ends it.
            while !w.open.is_empty() {
                w.close();
            }
            let top = std::mem::replace(&mut w.b, PageBuilder::new(coarsest, PAGE_LEVELS)).finish().unwrap();
            (w, top)
        }
    }

    /// A page's bytes from `packs` (by hash) at the range the index gives for it.
    fn read_page(
        packs: &HashMap<String, Vec<u8>>,
        r: &PageRef,
        range: Option<PackRange>,
    ) -> std::io::Result<Vec<u8>> {
        let range =
            range.ok_or_else(|| std::io::Error::other(format!("page {} is not in a pack", r.root)))?;
        let pack = packs.get(&range.pack.hash).ok_or_else(|| std::io::Error::other("no such pack"))?;
        Ok(pack[range.offset as usize..range.end() as usize].to_vec())
    }

    /// Fails if a page can be sealed before the pack holding a child page is closed, if any
    /// page is left as a file of its own, or if the index cannot read pages by range; the
    /// control reads one page from a pack with a byte changed.
    #[test]
    fn pages_in_packs_are_read_by_range() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let order = morton_post_order(&levels);
        let (w, top) = PagePackWriter::run(&order, coarsest, 256);
        let all: BTreeSet<BlockKey> = levels.iter().flatten().copied().collect();
        assert_eq!(w.pages, 1 + levels[2].len());
        // One object per pack: blocks and pages together, 256 items a pack but for the last
        // page layers' packs at the end.
        let items = all.len() + w.pages;
        assert!(w.packs.len() <= items / 256 + 3, "{} packs for {items} items", w.packs.len());
        let (manifest, by_hash) = w.manifest_and_packs(&top, coarsest);
        manifest.validate().unwrap();
        let index = load_scene_index(&manifest, |r, range| read_page(&by_hash, r, range)).unwrap();
        assert!(index.is_complete());
        assert_eq!(index.pages_loaded(), w.pages);
        let known: BTreeSet<BlockKey> = index.blocks().map(|e| e.key).collect();
        assert_eq!(known, all, "every block is reachable through pages read from packs");
        for k in &all {
            let r = index.pack_range(k).expect("every block is packed");
            let pack = &by_hash[&r.pack.hash];
            assert!(pack[r.offset as usize..r.end() as usize].iter().all(|&b| b == k.level), "block {k}");
        }
        // Control: a page's bytes changed inside its pack no longer match the reference.
        let (root_page_pack, root_page) = (top.root_page_pack.unwrap(), top.root_page.unwrap());
        let mut broken = by_hash.clone();
        broken.get_mut(&root_page_pack.hash).unwrap()[root_page.location.offset as usize + 40] ^= 1;
        let err = load_scene_index(&manifest, |r, range| read_page(&broken, r, range)).unwrap_err();
        assert!(err.to_string().contains("hash"), "{err}");
    }

    /// A page may name more packs than it has entries: its blocks and its child pages can each
    /// lie in a pack of their own (a page over coarse levels, whose blocks close late, in a
    /// scene of many packs: the conference room at 32768 has pages of 104 entries, 88 child
    /// pages and 172 packs). Here packs of two items put a page rooted at a block in the pack
    /// after that block's (the page waits for its last entries' pack to close), so the top page
    /// names 208 packs for 165 entries; every page must decode and the whole index load (the
    /// old bound, packs ≤ entries, fails here). Control: the page with the most packs past its
    /// entries, its pack count in the header raised one past its entries and child pages, is
    /// refused.
    #[test]
    fn a_page_can_name_more_packs_than_entries() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let order = morton_post_order(&levels);
        let (w, top) = PagePackWriter::run(&order, coarsest, 2);
        let (manifest, by_hash) = w.manifest_and_packs(&top, coarsest);
        let mut widest: Option<(PageRef, Vec<u8>, HierarchyPage)> = None;
        let index = load_scene_index(&manifest, |r, range| {
            let bytes = read_page(&by_hash, r, range)?;
            let page = HierarchyPage::decode(&bytes, r).map_err(std::io::Error::other)?;
            let surplus = |p: &HierarchyPage| p.packs.len() as i64 - p.entries.len() as i64;
            if widest.as_ref().is_none_or(|(_, _, w)| surplus(&page) > surplus(w)) {
                widest = Some((r.clone(), bytes.clone(), page));
            }
            Ok::<_, std::io::Error>(bytes)
        })
        .unwrap();
        assert!(index.is_complete());
        let all: BTreeSet<BlockKey> = levels.iter().flatten().copied().collect();
        assert_eq!(index.blocks().map(|e| e.key).collect::<BTreeSet<_>>(), all);
        let (r, bytes, page) = widest.unwrap();
        assert!(
            page.packs.len() > page.entries.len(),
            "a page names more packs ({}) than entries ({})",
            page.packs.len(),
            page.entries.len()
        );
        assert!(HierarchyPage::decode(&bytes, &r).is_ok());
        let mut many = bytes.clone();
        let most = (page.entries.len() + page.child_pages.len()) as u32;
        many[29..33].copy_from_slice(&(most + 1).to_le_bytes());
        assert!(matches!(HierarchyPage::decode_unverified(&many), Err(PageError::BadHeader(_))));
    }

    /// Placing a page in a pack that is already closed, or a page twice, is an order error.
    #[test]
    fn pages_are_placed_once_in_the_open_pack() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS).with_pages_in_packs();
        let mut sealed = Vec::new();
        for k in morton_post_order(&levels) {
            let mut e = entry(k);
            e.location = BlockLocation { pack: 0, offset: 0 };
            if k.level == coarsest {
                sealed.extend(b.pack_closed(0, PackRef { hash: "ab".repeat(32), bytes: 1 << 20 }).unwrap());
                e.location.pack = 1;
            }
            sealed.extend(b.add(e).unwrap());
        }
        let (first, _) = sealed.first().cloned().expect("pages sealed once pack 0 closed");
        assert!(matches!(b.page_placed(first.root, 0, 0), Err(PageError::Order(_))), "pack 0 is closed");
        b.page_placed(first.root, 1, 0).unwrap();
        assert!(matches!(b.page_placed(first.root, 1, 0), Err(PageError::Order(_))), "placed twice");
    }

    /// Post-order by Morton code of the level-0 descendants: the out-of-core pyramid's order.
    fn morton_post_order(levels: &[Vec<BlockKey>]) -> Vec<BlockKey> {
        let mut all: Vec<BlockKey> = levels.iter().flatten().copied().collect();
        // A block sorts after every block in its subtree: by the Morton code of its
        // subtree's last level-0 corner, then finer first.
        all.sort_by_key(|k| {
            let s = 1u32 << k.level;
            let last = k.coord().map(|c| c * s + s - 1);
            (morton3(last[0], last[1], last[2]), k.level)
        });
        all
    }

    fn manifest_for(root: BlockEntry, root_page: Option<PageRef>, coarsest: u8) -> Manifest {
        let res = 64u32 << coarsest;
        let levels = (0..=coarsest)
            .map(|l| LevelInfo { level: l, resolution: res >> l, blocks: 0, voxels: 0, bytes: 0 })
            .collect();
        crate::test_support::manifest("t", res, levels, root, root_page)
    }

    fn sample_level0() -> Vec<[u32; 3]> {
        // A slanted surface through a 32³-block grid (6 levels: two page layers).
        let mut v = Vec::new();
        for x in 0..32u32 {
            for y in 0..32u32 {
                let z = (x + y) / 2;
                v.push([x, y, z]);
                if x % 5 == 0 {
                    v.push([x, y, (z + 3).min(31)]);
                }
            }
        }
        v.sort();
        v.dedup();
        v
    }

    #[test]
    fn pages_cover_every_block_and_do_not_depend_on_order() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        assert_eq!(coarsest, 5);
        let level_order: Vec<BlockKey> = levels.iter().flatten().copied().collect();
        let (pages_a, root_a, ref_a) = build(&level_order, coarsest);
        let (pages_b, root_b, ref_b) = build(&morton_post_order(&levels), coarsest);
        let sorted = |p: &[FinishedPage]| {
            let mut p = p.to_vec();
            p.sort_by_key(|(r, _)| r.root);
            p
        };
        assert_eq!(sorted(&pages_a), sorted(&pages_b), "pages depend on the order blocks came in");
        assert_eq!((root_a.clone(), ref_a.clone()), (root_b, ref_b));
        // Page roots on levels 5 and 2: one page for the root, one per level-2 block with children.
        assert_eq!(pages_a.len(), 1 + levels[2].len());

        let store: HashMap<String, Vec<u8>> =
            pages_a.iter().map(|(r, b)| (r.hash.clone(), b.clone())).collect();
        let manifest = manifest_for(root_a, ref_a, coarsest);
        let index = load_scene_index(&manifest, |r, _| {
            store.get(&r.hash).cloned().ok_or_else(|| std::io::Error::other("missing"))
        })
        .unwrap();
        assert!(index.is_complete());
        assert_eq!(index.pages_loaded(), pages_a.len());
        let all: BTreeSet<BlockKey> = levels.iter().flatten().copied().collect();
        let known: BTreeSet<BlockKey> = index.blocks().map(|e| e.key).collect();
        assert_eq!(known, all, "every block is reachable from the manifest through pages");
        for k in &all {
            let e = index.block(k).unwrap();
            assert_eq!(e, &BlockEntry { child_mask: e.child_mask, ..entry(*k) });
            let children: BTreeSet<BlockKey> = index.children(k).map(|c| c.key).collect();
            let expected: BTreeSet<BlockKey> =
                k.children().into_iter().flatten().filter(|c| all.contains(c)).collect();
            assert_eq!(children, expected, "children of {k}");
        }
        // Compact: well under the 180 bytes of JSON a block cost in format 2.
        let page_bytes: usize = pages_a.iter().map(|(_, b)| b.len()).sum();
        assert!(page_bytes < 90 * all.len(), "{page_bytes} bytes for {} blocks", all.len());
    }

    #[test]
    fn lazy_index_asks_for_the_page_below_a_block() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let (pages, root, root_page) = build(&levels.iter().flatten().copied().collect::<Vec<_>>(), coarsest);
        let manifest = manifest_for(root, root_page.clone(), coarsest);
        let mut index = SceneIndex::new(&manifest);
        let root_key = manifest.root.key;
        assert_eq!(index.pending_page_for(&root_key), root_page.as_ref());
        assert_eq!(index.children(&root_key).count(), 0);
        let bytes = &pages.iter().find(|(r, _)| Some(r) == root_page.as_ref()).unwrap().1;
        index.insert_page(HierarchyPage::decode(bytes, root_page.as_ref().unwrap()).unwrap()).unwrap();
        assert!(index.pending_page_for(&root_key).is_none());
        assert!(index.children(&root_key).count() > 0);
        let level2 = levels[2][0];
        assert!(index.block(&level2).is_some());
        assert!(index.pending_page_for(&level2).is_some(), "level-2 blocks root the next pages");
        // The same page twice is refused (it is no longer pending).
        assert!(
            index.insert_page(HierarchyPage::decode(bytes, root_page.as_ref().unwrap()).unwrap()).is_err()
        );
    }

    #[test]
    fn a_lookup_loads_only_the_pages_on_its_path() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let (pages, root, root_page) = build(&levels.iter().flatten().copied().collect::<Vec<_>>(), coarsest);
        let store: HashMap<String, Vec<u8>> =
            pages.iter().map(|(r, b)| (r.hash.clone(), b.clone())).collect();
        let manifest = manifest_for(root, root_page, coarsest);
        let full = load_scene_index(&manifest, |r, _| {
            store.get(&r.hash).cloned().ok_or_else(|| std::io::Error::other("missing"))
        })
        .unwrap();
        let lookup = |index: &mut SceneIndex, key: &BlockKey| {
            let mut loads = 0;
            while let Some(r) = index.page_toward(key).cloned() {
                index.insert_page(HierarchyPage::decode(&store[&r.hash], &r).unwrap()).unwrap();
                loads += 1;
            }
            loads
        };
        // Every block of the scene, each from a fresh index: the same entry as the full load,
        // after at most one page per page layer (two here: levels 5 and 2 root pages).
        for k in levels.iter().flatten() {
            let mut index = SceneIndex::new(&manifest);
            let loads = lookup(&mut index, k);
            assert!(loads <= 2, "{k}: {loads} pages");
            assert_eq!(index.block(k), full.block(k), "{k}");
            assert_eq!(index.pack_range(k), full.pack_range(k), "{k}");
        }
        // Keys the scene lacks: at most the path's pages, then a definite no.
        let level0: BTreeSet<BlockKey> = levels[0].iter().copied().collect();
        let absent = (0..32).map(|x| BlockKey::new(0, x, 31, 0)).find(|k| !level0.contains(k)).unwrap();
        let mut index = SceneIndex::new(&manifest);
        assert!(lookup(&mut index, &absent) <= 2);
        assert!(index.block(&absent).is_none());
        assert!(index.pages_loaded() < full.pages_loaded(), "a lookup loaded the whole index");
        for outside in [
            BlockKey::new(0, 5000, 0, 0),
            BlockKey::new(coarsest, 1, 0, 0),
            BlockKey::new(coarsest + 1, 0, 0, 0),
        ] {
            assert!(SceneIndex::new(&manifest).page_toward(&outside).is_none(), "{outside}");
        }
        // Control: with nothing loaded, a level-0 block is unknown.
        let k = levels[0][0];
        assert!(SceneIndex::new(&manifest).block(&k).is_none());
        assert!(SceneIndex::new(&manifest).page_toward(&k).is_some());
    }

    #[test]
    fn a_wrong_or_damaged_page_is_an_error() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let (pages, _, _) = build(&levels.iter().flatten().copied().collect::<Vec<_>>(), coarsest);
        let (r, bytes) = &pages[0];
        assert!(HierarchyPage::decode(bytes, r).is_ok());
        let mut other = r.clone();
        other.hash = content_hash(b"else");
        assert!(matches!(HierarchyPage::decode(bytes, &other), Err(PageError::HashMismatch { .. })));
        for cut in [0, 10, PAGE_HEADER_LEN, bytes.len() - 1] {
            assert!(HierarchyPage::decode_unverified(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        // Re-encoding a decoded page gives the same bytes.
        let page = HierarchyPage::decode(bytes, r).unwrap();
        assert_eq!(&page.encode(), bytes);
        // An entry moved out of the subtree is refused even with a matching hash.
        let mut bad = page.clone();
        bad.entries[0].key.x += 1 << 10;
        assert!(HierarchyPage::decode_unverified(&bad.encode()).is_err());
    }

    #[test]
    fn packs_span_pages_and_every_range_lies_inside_its_pack() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let order = morton_post_order(&levels);
        let per_pack = 64;
        let Packed { pages, top, packs, most_held } = build_packed(&order, coarsest, per_pack);
        assert_eq!(packs.len(), order.len().div_ceil(per_pack), "a pack every {per_pack} blocks");
        assert!(pages.len() > packs.len(), "{} pages, {} packs: packs span pages", pages.len(), packs.len());
        assert_eq!(top.root.location.pack, 0);
        assert_eq!(top.root_pack.as_ref(), packs.last(), "the root comes last, in the last pack");
        let store: HashMap<String, Vec<u8>> =
            pages.iter().map(|(r, b)| (r.hash.clone(), b.clone())).collect();
        let mut manifest = manifest_for(top.root.clone(), top.root_page.clone(), coarsest);
        manifest.root_pack = top.root_pack.clone();
        manifest.validate().unwrap();
        let index = load_scene_index(&manifest, |r, _| {
            store.get(&r.hash).cloned().ok_or_else(|| std::io::Error::other("missing"))
        })
        .unwrap();
        // Every block resolves to a range of the pack it was written to; the ranges tile each pack.
        let mut by_pack: HashMap<String, Vec<(u64, u64)>> = HashMap::new();
        for (i, k) in order.iter().enumerate() {
            let r = index.pack_range(k).unwrap_or_else(|| panic!("{k} has no pack range"));
            assert_eq!(r.pack, packs[i / per_pack], "block {k} (number {i})");
            let e = index.block(k).unwrap();
            assert_eq!((r.offset, r.bytes), (e.location.offset, e.bytes));
            by_pack.entry(r.pack.hash.clone()).or_default().push((r.offset, r.end()));
        }
        assert_eq!(index.packs().count(), packs.len());
        for p in &packs {
            let mut ranges = by_pack[&p.hash].clone();
            ranges.sort();
            assert_eq!(ranges[0].0, 0);
            assert!(ranges.windows(2).all(|w| w[0].1 == w[1].0), "contiguous");
            assert_eq!(ranges.last().unwrap().1, p.bytes, "the pack ends at its last block");
        }
        // Held pages stay a front: one page a layer filled before the open pack, plus what the
        // pack itself holds. Control: one pack for the whole scene holds every page to the end.
        let biggest =
            pages.iter().map(|(r, b)| HierarchyPage::decode(b, r).unwrap().entries.len()).max().unwrap();
        assert!(most_held <= per_pack + 2 * biggest, "{most_held} entries held");
        let whole = build_packed(&order, coarsest, usize::MAX);
        assert_eq!(whole.packs.len(), 1);
        assert_eq!(whole.most_held, order.len() - 1, "every entry but the root's, held for the one pack");

        // A page that spans packs lists them in order; its hash covers them.
        let (r, bytes) = pages
            .iter()
            .find(|(r, b)| HierarchyPage::decode(b, r).unwrap().packs.len() > 1)
            .expect("a page spanning two packs");
        let page = HierarchyPage::decode(bytes, r).unwrap();
        assert_eq!(&page.encode(), bytes);
        let mut other = page.clone();
        other.packs[1].hash = content_hash(b"another pack");
        assert_ne!(content_hash(&other.encode()), r.hash);
        // A range past its pack's end, an overflowing offset, a pack index past the list and a
        // listed pack no entry uses are refused, by validate and by decode.
        let in_first = page.entries.iter().filter(|e| e.location.pack == 0);
        let last = in_first.map(|e| e.location.offset + e.bytes as u64).max().unwrap();
        let mut short = page.clone();
        short.packs[0].bytes = last - 1;
        assert!(short.validate().is_err(), "a range one byte past the pack");
        assert!(HierarchyPage::decode_unverified(&short.encode()).is_err());
        let mut far = page.clone();
        far.entries[0].location.offset = u64::MAX - 1;
        assert!(far.validate().is_err(), "an offset that overflows");
        let mut beyond = page.clone();
        beyond.entries[0].location.pack = page.packs.len() as u32;
        assert!(beyond.validate().is_err(), "a pack the page does not list");
        let mut unused = page.clone();
        unused.packs.push(PackRef { hash: content_hash(b"unused"), bytes: 1 << 30 });
        assert!(unused.validate().is_err(), "a listed pack holding none of the page's blocks");
        assert!(HierarchyPage::decode_unverified(&unused.encode()).is_err());
        // Header damage: a pack count past the entries and child pages, a truncated header.
        let mut many = bytes.clone();
        let most = (page.entries.len() + page.child_pages.len()) as u32;
        many[29..33].copy_from_slice(&(most + 1).to_le_bytes());
        assert!(matches!(HierarchyPage::decode_unverified(&many), Err(PageError::BadHeader(_))));
        assert!(HierarchyPage::decode_unverified(&bytes[..PAGE_HEADER_LEN - 1]).is_err());
    }

    #[test]
    fn pages_of_older_versions_ask_for_a_rebuild() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let (pages, _, _) = build(&levels.iter().flatten().copied().collect::<Vec<_>>(), coarsest);
        let (_, bytes) = &pages[0];
        assert!(HierarchyPage::decode_unverified(bytes).is_ok(), "control: the page as written");
        for version in [1u8, 2, 3, 5] {
            let mut old = bytes.clone();
            old[4] = version;
            let err = HierarchyPage::decode_unverified(&old).unwrap_err();
            assert!(err.to_string().contains("rebuild the scene"), "version {version}: {err}");
        }
    }

    #[test]
    fn a_builder_fed_out_of_order_refuses() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        // A page root before its children.
        assert!(b.add(entry(levels[2][0])).is_err());
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        b.add(entry(levels[0][0])).unwrap();
        assert!(b.add(entry(levels[0][0])).is_err(), "twice");
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        b.add(entry(levels[0][0])).unwrap();
        assert!(b.finish().is_err(), "no root");
        // Packs close in serial order, and a block cannot name a closed pack.
        let pack = PackRef { hash: content_hash(b"p"), bytes: 1 };
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        assert!(b.pack_closed(1, pack.clone()).is_err(), "pack 1 before pack 0");
        b.pack_closed(0, pack.clone()).unwrap();
        let mut e = entry(levels[0][0]);
        e.location = BlockLocation { pack: 0, offset: 0 };
        assert!(b.add(e).is_err(), "a block in a closed pack");
        // A page waiting for a pack that never closes.
        let order = morton_post_order(&levels);
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        for k in &order {
            let mut e = entry(*k);
            e.location = BlockLocation { pack: 0, offset: 0 };
            assert!(b.add(e).unwrap().is_empty(), "no page can be sealed before its pack closes");
        }
        let err = b.finish().unwrap_err().to_string();
        assert!(err.contains("never closed"), "{err}");
    }

    proptest! {
        #[test]
        fn mutated_pages_never_panic(flips in proptest::collection::vec((0usize..4096, any::<u8>()), 1..8), cut in 0usize..4096) {
            let levels = tree(&sample_level0());
            let coarsest = (levels.len() - 1) as u8;
            let packed = build_packed(&morton_post_order(&levels), coarsest, 64);
            let mut bytes = packed.pages[0].1.clone();
            for (at, x) in flips {
                let n = bytes.len();
                bytes[at % n] ^= x;
            }
            let _ = HierarchyPage::decode_unverified(&bytes);
            let _ = HierarchyPage::decode_unverified(&bytes[..cut.min(bytes.len())]);
        }
    }
}
