//! The paged block hierarchy (format 3): the manifest holds the root block and
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
//! **Packs.** The encoded bytes of the blocks a page lists live in one pack,
//! `packs/<blake3 of the pack>.vxp` in the scene directory: the blocks' bytes
//! concatenated (in the order the writer finished them: post order). The
//! page's header names the pack (hash and length), so the page's hash covers
//! it and the Merkle chain reaches every block byte. An entry's
//! `location.pack == 0` means "this page's pack", bytes
//! `[offset, offset + bytes)`; [`NO_PACK`] means the block is its own file
//! `blocks/<key>.vxb` (version-1 pages; no writer makes those any more).
//!
//! Binary page layout (little endian), version 2:
//!
//! ```text
//! 0  magic "VXHP"
//! 4  version u8 (2), page_levels u8, reserved 2 zero bytes
//! 8  root: level u8, x, y, z u32
//! 21 entry count u32, child page count u32, pack count u32 (0 or 1)
//! 33 payload length u32 (decompressed; must equal what the counts imply)
//! 37 pack: blake3 32 bytes, length u64 (all zero when the pack count is 0)
//! 77 lz4 block of the payload:
//!    child pages  count × (level u8, x, y, z u32, bytes u32, blake3 32)        = 49 bytes
//!    entries      count × (level u8, x, y, z u32, child_mask u8,
//!                          bounds min 3 × u8, max 3 × u8 (block-local, 0..=64),
//!                          voxels u32, faces u32, bytes u32, geometric_error f32,
//!                          blake3 32, pack u32, offset u64)                       = 80 bytes
//! ```
//!
//! Version 1 (still decoded) had a 37-byte header and the pack hashes
//! (32 bytes each, no lengths) at the start of the payload; its writers never
//! named a pack, so a version-1 page with packs is refused.
//!
//! **Invariant:** [`HierarchyPage::decode`] never panics and never allocates
//! more than the counts imply after checking them against a hard cap; a
//! decoded version-2 page is exactly what [`HierarchyPage::encode`] would
//! write, every entry is a descendant of the root within `page_levels`
//! levels, and every packed entry's range lies inside the page's pack.

use std::collections::{BTreeMap, HashMap};

use serde::{Deserialize, Serialize};

use crate::{BLOCK_SIZE, BlockEntry, BlockKey, Manifest, VoxelBounds};

/// Levels one page spans below its root.
pub const PAGE_LEVELS: u8 = 3;
pub const PAGE_MAGIC: [u8; 4] = *b"VXHP";
const PAGE_VERSION: u8 = 2;
/// The header of a version-2 page (the pack is named in it).
pub const PAGE_HEADER_LEN: usize = 77;
/// The header of a version-1 page, the shortest any page can be.
const V1_HEADER_LEN: usize = 37;
const CHILD_PAGE_LEN: usize = 49;
const ENTRY_LEN: usize = 80;
/// A page holds at most the full subtree of `page_levels ≤ 4` levels: 8 + 64 + 512 + 4096 blocks.
pub const MAX_PAGE_ENTRIES: u32 = 8 + 64 + 512 + 4096;
/// `pack` value of a block stored as its own file `blocks/<key>.vxb`.
pub const NO_PACK: u32 = u32::MAX;

/// Where a block's bytes are: its own file, or a byte range of a pack named in
/// its page (`[offset, offset + bytes)`).
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

/// A pack as its page (or the manifest, for the root block) names it:
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
}

#[derive(Debug, Clone, PartialEq)]
pub struct HierarchyPage {
    pub root: BlockKey,
    pub page_levels: u8,
    /// The pack holding the bytes of the entries whose `location.pack` is 0.
    pub pack: Option<PackRef>,
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
        let mut raw =
            Vec::with_capacity(self.child_pages.len() * CHILD_PAGE_LEN + self.entries.len() * ENTRY_LEN);
        for c in &self.child_pages {
            put_key(&mut raw, &c.root);
            raw.extend_from_slice(&c.bytes.to_le_bytes());
            put_hash(&mut raw, &c.hash);
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
        for n in [self.entries.len(), self.child_pages.len(), self.pack.is_some() as usize, raw.len()] {
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        match &self.pack {
            Some(p) => {
                put_hash(&mut out, &p.hash);
                out.extend_from_slice(&p.bytes.to_le_bytes());
            }
            None => out.extend_from_slice(&[0; 40]),
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
        if bytes.len() < V1_HEADER_LEN {
            return Err(PageError::Truncated(bytes.len()));
        }
        if bytes[..4] != PAGE_MAGIC {
            return Err(PageError::BadMagic);
        }
        let version = bytes[4];
        let header_len = match version {
            1 => V1_HEADER_LEN,
            PAGE_VERSION => PAGE_HEADER_LEN,
            _ => return Err(PageError::BadHeader(format!("version {version} is not 1 or {PAGE_VERSION}"))),
        };
        if bytes.len() < header_len {
            return Err(PageError::Truncated(bytes.len()));
        }
        let mut h = Reader { bytes: &bytes[..header_len], at: 5 };
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
        if entries == 0 || entries > MAX_PAGE_ENTRIES || children > entries || packs > 1 {
            return Err(PageError::BadHeader(format!(
                "{entries} entries, {children} child pages, {packs} packs"
            )));
        }
        if version == 1 && packs != 0 {
            return Err(PageError::BadHeader("a version-1 page cannot name packs".into()));
        }
        let pack = if version == PAGE_VERSION {
            let hash = hex(&h.take::<32>());
            let length = h.u64();
            match packs {
                1 => Some(PackRef { hash, bytes: length }),
                _ if length == 0 && hash.bytes().all(|b| b == b'0') => None,
                _ => return Err(PageError::BadHeader("a page without a pack names one".into())),
            }
        } else {
            None
        };
        let expected_len = children as usize * CHILD_PAGE_LEN + entries as usize * ENTRY_LEN;
        if payload as usize != expected_len {
            return Err(PageError::BadHeader(format!(
                "payload length {payload} does not match the counts ({expected_len})"
            )));
        }
        let mut raw = vec![0u8; expected_len];
        let written = lz4_flex::block::decompress_into(&bytes[header_len..], &mut raw)
            .map_err(|e| PageError::Corrupt(e.to_string()))?;
        if written != expected_len {
            return Err(PageError::Corrupt(format!("payload is {written} bytes, expected {expected_len}")));
        }
        let mut r = Reader { bytes: &raw, at: 0 };
        let child_pages = (0..children)
            .map(|_| {
                let root = r.key();
                let bytes = r.u32();
                PageRef { root, bytes, hash: hex(&r.take::<32>()) }
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
        let page = HierarchyPage { root, page_levels, pack, child_pages, entries: list };
        page.validate()?;
        Ok(page)
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
        let known: HashMap<BlockKey, &BlockEntry> = self.entries.iter().map(|e| (e.key, e)).collect();
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
            if depth > 1 && !known.contains_key(&e.key.parent()) {
                return bad(format!("block {} has no parent in the page", e.key));
            }
            if e.key.level == 0 && e.child_mask != 0 {
                return bad(format!("level-0 block {} claims children", e.key));
            }
            if e.key.level > 0 && depth < self.page_levels {
                let children = e.key.children().expect("level > 0");
                let mask = (0..8).fold(0u8, |m, i| m | ((known.contains_key(&children[i]) as u8) << i));
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
                match &self.pack {
                    Some(p) if e.location.pack == 0 => {
                        if !range_in_pack(e.location.offset, e.bytes, p.bytes) {
                            return bad(format!(
                                "block {} lies at bytes {}..{} of a {}-byte pack",
                                e.key,
                                e.location.offset,
                                e.location.offset as u128 + e.bytes as u128,
                                p.bytes
                            ));
                        }
                    }
                    _ => {
                        return bad(format!(
                            "block {} names pack {} of {}",
                            e.key,
                            e.location.pack,
                            self.pack.is_some() as u32
                        ));
                    }
                }
            }
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
            if unhex(&c.hash).is_none() || c.bytes < V1_HEADER_LEN as u32 {
                return bad(format!("child page {} is malformed", c.root));
            }
        }
        if let Some(p) = &self.pack
            && unhex(&p.hash).is_none()
        {
            return bad("pack hash is not 64 hex digits".into());
        }
        Ok(())
    }

    /// The reference naming this page's bytes.
    pub fn reference(&self, bytes: &[u8]) -> PageRef {
        PageRef { root: self.root, hash: content_hash(bytes), bytes: bytes.len() as u32 }
    }
}

/// One page waiting for its root block.
#[derive(Default)]
struct OpenPage {
    entries: Vec<BlockEntry>,
    child_pages: Vec<PageRef>,
}

/// Builds pages as blocks are finished, children before parents (any such
/// order gives the same bytes). Memory: the entries of pages whose root has
/// not been added yet, and the child masks of blocks not yet added.
pub struct PageBuilder {
    coarsest: u8,
    page_levels: u8,
    open: BTreeMap<BlockKey, OpenPage>,
    masks: HashMap<BlockKey, u8>,
    root: Option<(BlockEntry, Option<PageRef>)>,
}

/// A finished page: its reference and its bytes (write them as `pages/<root>.vxh`).
pub type FinishedPage = (PageRef, Vec<u8>);

impl PageBuilder {
    pub fn new(coarsest: u8, page_levels: u8) -> Self {
        Self {
            coarsest,
            page_levels: page_levels.clamp(1, 4),
            open: BTreeMap::new(),
            masks: HashMap::new(),
            root: None,
        }
    }

    /// Records a finished block; `entry.child_mask` is filled in here from the
    /// children added before it. Returns the page this block completes (when
    /// it roots one). Entries naming pack 0 need [`Self::add_packed`].
    pub fn add(&mut self, entry: BlockEntry) -> Result<Option<FinishedPage>, PageError> {
        self.add_packed(entry, None)
    }

    /// [`Self::add`] for a block that roots a page whose entries are in
    /// `pack` (the page names it; `None` when its entries are own files).
    pub fn add_packed(
        &mut self,
        mut entry: BlockEntry,
        pack: Option<PackRef>,
    ) -> Result<Option<FinishedPage>, PageError> {
        let key = entry.key;
        if key.level > self.coarsest || self.root.is_some() {
            return Err(PageError::Order(format!(
                "block {key} after the root or above level {}",
                self.coarsest
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
        if pack.is_some() && !roots_page {
            return Err(PageError::Order(format!("block {key} roots no page, yet a pack was given for it")));
        }
        let finished = if roots_page {
            let open = self.open.remove(&key).unwrap_or_default();
            if open.entries.is_empty() {
                return Err(PageError::Order(format!(
                    "block {key} roots a page but none of its children came first"
                )));
            }
            let mut page = HierarchyPage {
                root: key,
                page_levels: self.page_levels,
                pack,
                child_pages: open.child_pages,
                entries: open.entries,
            };
            page.entries.sort_by_key(|e| e.key);
            page.child_pages.sort_by_key(|c| c.root);
            page.validate()?;
            let bytes = page.encode();
            Some((page.reference(&bytes), bytes))
        } else {
            None
        };
        match page_root_of(&key, self.coarsest, self.page_levels) {
            Some(r) => {
                let open = self.open.entry(r).or_default();
                open.entries.push(entry);
                if let Some((reference, _)) = &finished {
                    open.child_pages.push(reference.clone());
                }
            }
            None => self.root = Some((entry, finished.as_ref().map(|(r, _)| r.clone()))),
        }
        Ok(finished)
    }

    /// After the coarsest block: its entry and the root page's reference.
    pub fn finish(self) -> Result<(BlockEntry, Option<PageRef>), PageError> {
        if let Some(k) = self.open.keys().next() {
            return Err(PageError::Order(format!("page {k} never got its root block")));
        }
        self.root.ok_or_else(|| PageError::Order("no root block was added".into()))
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
    /// Each loaded page's pack, by page root.
    packs: HashMap<BlockKey, PackRef>,
    entries: HashMap<BlockKey, BlockEntry>,
    /// Pages named by a loaded page (or the manifest) and not loaded yet, by root.
    pending: BTreeMap<BlockKey, PageRef>,
    pages_loaded: usize,
    page_bytes_loaded: u64,
}

impl SceneIndex {
    pub fn new(manifest: &Manifest) -> Self {
        let mut entries = HashMap::new();
        entries.insert(manifest.root.key, manifest.root.clone());
        let pending = manifest.root_page.iter().map(|r| (r.root, r.clone())).collect();
        Self {
            page_levels: manifest.page_levels,
            root: manifest.root.key,
            root_pack: manifest.root_pack.clone(),
            packs: HashMap::new(),
            entries,
            pending,
            pages_loaded: 0,
            page_bytes_loaded: 0,
        }
    }

    pub fn block(&self, key: &BlockKey) -> Option<&BlockEntry> {
        self.entries.get(key)
    }

    /// Where in a pack `key`'s bytes are: the pack its page names (the
    /// manifest's `root_pack` for the root block). `None` when the block is
    /// its own file (`blocks/<key>.vxb`) or not known.
    pub fn pack_range(&self, key: &BlockKey) -> Option<PackRange> {
        let e = self.entries.get(key)?;
        if e.location.is_file() {
            return None;
        }
        let pack = if *key == self.root {
            self.root_pack.as_ref()?
        } else {
            self.packs.get(&page_root_of(key, self.root.level, self.page_levels)?)?
        };
        Some(PackRange { pack: pack.clone(), offset: e.location.offset, bytes: e.bytes })
    }

    /// Every pack named so far (each once), in no particular order.
    pub fn packs(&self) -> impl Iterator<Item = &PackRef> {
        let mut seen = std::collections::HashSet::new();
        self.root_pack.iter().chain(self.packs.values()).filter(move |p| seen.insert(p.hash.as_str()))
    }

    /// Every known entry, in no particular order.
    pub fn blocks(&self) -> impl Iterator<Item = &BlockEntry> {
        self.entries.values()
    }

    /// Known children of `key` (all of them once [`Self::pending_page_for`] is `None`).
    pub fn children(&self, key: &BlockKey) -> impl Iterator<Item = &BlockEntry> {
        let mask = self.entries.get(key).map_or(0, |e| e.child_mask);
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
        let e = self.entries.get(key)?;
        if e.child_mask == 0 {
            return None;
        }
        self.pending.get(key)
    }

    pub fn missing_pages(&self) -> impl Iterator<Item = &PageRef> {
        self.pending.values()
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
        if let Some(r) = self.pending.remove(&page.root) {
            self.page_bytes_loaded += r.bytes as u64;
        }
        for c in page.child_pages {
            self.pending.insert(c.root, c);
        }
        if let Some(p) = page.pack {
            self.packs.insert(page.root, p);
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

/// Loads every page of a scene through `read` (bytes of the page a reference names).
pub fn load_scene_index<E: std::error::Error + 'static>(
    manifest: &Manifest,
    mut read: impl FnMut(&PageRef) -> Result<Vec<u8>, E>,
) -> Result<SceneIndex, IndexError<E>> {
    let mut index = SceneIndex::new(manifest);
    loop {
        let next = index.missing_pages().next().cloned();
        let Some(r) = next else { break };
        let bytes = read(&r).map_err(|source| IndexError::Read { root: r.root, source })?;
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
        let (root, root_page) = b.finish().unwrap();
        (pages, root, root_page)
    }

    /// [`build`] as the store's writer does it: each block's bytes appended to
    /// its page's pack (the root's to its own page's), each pack named by the
    /// page it belongs to. Returns the pages, the root entry and page, and the
    /// root's pack.
    fn build_packed(
        order: &[BlockKey],
        coarsest: u8,
    ) -> (Vec<FinishedPage>, BlockEntry, Option<PageRef>, PackRef) {
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        let mut open: HashMap<BlockKey, u64> = HashMap::new();
        let mut pages = Vec::new();
        let mut root_pack = None;
        for k in order {
            let mut e = entry(*k);
            let home = page_root_of(k, coarsest, PAGE_LEVELS).unwrap_or(*k);
            let len = open.entry(home).or_default();
            e.location = BlockLocation { pack: 0, offset: *len };
            *len += e.bytes as u64;
            let roots = is_page_root_level(k.level, coarsest, PAGE_LEVELS);
            let pack = (roots || k.level == coarsest).then(|| PackRef {
                hash: content_hash(format!("pack {k}").as_bytes()),
                bytes: open.remove(k).unwrap_or(0),
            });
            if k.level == coarsest {
                root_pack = pack.clone();
            }
            pages.extend(b.add_packed(e, if roots { pack } else { None }).unwrap());
        }
        let (root, root_page) = b.finish().unwrap();
        (pages, root, root_page, root_pack.unwrap())
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
        let index = load_scene_index(&manifest, |r| {
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
    fn packed_pages_name_their_pack_and_every_range_lies_inside_it() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let order = morton_post_order(&levels);
        let (pages, root, root_page, root_pack) = build_packed(&order, coarsest);
        assert_eq!(root.location, BlockLocation { pack: 0, offset: root.location.offset });
        let store: HashMap<String, Vec<u8>> =
            pages.iter().map(|(r, b)| (r.hash.clone(), b.clone())).collect();
        let mut manifest = manifest_for(root, root_page.clone(), coarsest);
        manifest.root_pack = Some(root_pack.clone());
        manifest.validate().unwrap();
        let index = load_scene_index(&manifest, |r| {
            store.get(&r.hash).cloned().ok_or_else(|| std::io::Error::other("missing"))
        })
        .unwrap();
        // Every block resolves to a range of its page's pack; ranges of one pack tile it.
        let mut by_pack: HashMap<String, Vec<(u64, u64)>> = HashMap::new();
        for k in &order {
            let r = index.pack_range(k).unwrap_or_else(|| panic!("{k} has no pack range"));
            let e = index.block(k).unwrap();
            assert_eq!((r.offset, r.bytes), (e.location.offset, e.bytes));
            by_pack.entry(r.pack.hash.clone()).or_default().push((r.offset, r.end()));
        }
        assert_eq!(index.pack_range(&manifest.root.key).unwrap().pack, root_pack);
        assert_eq!(by_pack.len(), pages.len(), "one pack a page (the root shares the root page's)");
        assert_eq!(index.packs().count(), pages.len());
        for p in index.packs() {
            let mut ranges = by_pack[&p.hash].clone();
            ranges.sort();
            assert_eq!(ranges[0].0, 0);
            assert!(ranges.windows(2).all(|w| w[0].1 == w[1].0), "contiguous");
            assert_eq!(ranges.last().unwrap().1, p.bytes, "the pack ends at its last block");
        }

        // The page's hash covers its pack: another pack gives another page.
        let (r, bytes) = pages.iter().find(|(r, _)| Some(r) == root_page.as_ref()).unwrap();
        let page = HierarchyPage::decode(bytes, r).unwrap();
        assert_eq!(&page.encode(), bytes);
        let pack = page.pack.clone().unwrap();
        let mut other = page.clone();
        other.pack = Some(PackRef { hash: content_hash(b"another pack"), bytes: pack.bytes });
        assert_ne!(content_hash(&other.encode()), r.hash);
        // A range past the pack's end is refused, by validate and by decode.
        let last = page.entries.iter().map(|e| e.location.offset + e.bytes as u64).max().unwrap();
        assert_eq!(last, pack.bytes - manifest.root.bytes as u64, "the root comes last");
        let mut short = page.clone();
        short.pack = Some(PackRef { bytes: last - 1, ..pack.clone() });
        assert!(short.validate().is_err(), "a range one byte past the pack");
        assert!(HierarchyPage::decode_unverified(&short.encode()).is_err());
        let mut far = page.clone();
        far.entries[0].location.offset = u64::MAX - 1;
        assert!(far.validate().is_err(), "an offset that overflows");
        let mut no_pack = page.clone();
        no_pack.pack = None;
        assert!(no_pack.validate().is_err(), "pack 0 of a page without a pack");
        let mut pack1 = page.clone();
        pack1.entries[0].location.pack = 1;
        assert!(pack1.validate().is_err(), "a page has one pack");
        // Header damage in the pack fields: a truncated header, a pack count of 2.
        assert!(HierarchyPage::decode_unverified(&bytes[..PAGE_HEADER_LEN - 1]).is_err());
        let mut two = bytes.clone();
        two[29] = 2;
        assert!(HierarchyPage::decode_unverified(&two).is_err());
        let mut zero = bytes.clone();
        zero[29] = 0;
        assert!(HierarchyPage::decode_unverified(&zero).is_err(), "no pack, yet one is named");
    }

    #[test]
    fn version_1_pages_still_decode() {
        let levels = tree(&sample_level0());
        let coarsest = (levels.len() - 1) as u8;
        let (pages, _, _) = build(&levels.iter().flatten().copied().collect::<Vec<_>>(), coarsest);
        let (_, v2) = &pages[0];
        let page = HierarchyPage::decode_unverified(v2).unwrap();
        assert!(page.pack.is_none() && page.entries.iter().all(|e| e.location.is_file()));
        // Version 1: the same fields in a 37-byte header, no pack slot.
        let mut v1 = v2[..37].to_vec();
        v1[4] = 1;
        v1.extend_from_slice(&v2[PAGE_HEADER_LEN..]);
        assert_eq!(HierarchyPage::decode_unverified(&v1).unwrap(), page);
        let mut bad = v1.clone();
        bad[29] = 1;
        assert!(HierarchyPage::decode_unverified(&bad).is_err(), "version 1 named no packs");
        bad[4] = 3;
        assert!(matches!(HierarchyPage::decode_unverified(&bad), Err(PageError::BadHeader(_))));
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
        let mut b = PageBuilder::new(coarsest, PAGE_LEVELS);
        let pack = PackRef { hash: content_hash(b"p"), bytes: 1 };
        assert!(b.add_packed(entry(levels[0][0]), Some(pack)).is_err(), "a pack for a block rooting no page");
    }

    proptest! {
        #[test]
        fn mutated_pages_never_panic(flips in proptest::collection::vec((0usize..4096, any::<u8>()), 1..8), cut in 0usize..4096) {
            let levels = tree(&sample_level0());
            let coarsest = (levels.len() - 1) as u8;
            let (pages, _, _, _) = build_packed(&morton_post_order(&levels), coarsest);
            let mut bytes = pages[0].1.clone();
            for (at, x) in flips {
                let n = bytes.len();
                bytes[at % n] ^= x;
            }
            let _ = HierarchyPage::decode_unverified(&bytes);
            let _ = HierarchyPage::decode_unverified(&bytes[..cut.min(bytes.len())]);
        }
    }
}
