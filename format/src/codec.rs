//! Block wire format, version 2: a fixed little-endian header, then one lz4
//! block holding the voxel columns, each laid out so that lz4 (a byte matcher,
//! not an entropy coder) finds long runs.
//!
//! ```text
//! 0  magic  "VXB2"
//! 4  level  u8
//! 5  flags  u8: bit 0 = colour column present; bit 1 = AO field column present; other bits zero
//! 6  reserved, 2 zero bytes
//! 8  x, y, z  u32 each
//! 20 voxel count u32 (≤ 64³)
//! 24 payload length u32 (decompressed; checked against the count before allocating)
//! 28 lz4 block of the payload
//! ```
//!
//! Payload columns, in this order:
//! 1. **occupancy**: the voxel positions as an octree of child masks, breadth
//!    first, one nonzero byte per occupied node from the 64³ root down to the
//!    2³ nodes above the voxels (bit `i` = child octant `i` in Morton order).
//!    Leaves come out in increasing Morton order by construction. A surface
//!    costs about 0.4 bytes per voxel here before lz4, less than a varint of
//!    the Morton delta (measured: `column_sizes`, ARCHITECTURE.md).
//! 2. **faces**: one byte per voxel, the face mask XOR the mask predicted from
//!    occupancy alone (neighbour in the block empty, or on the block boundary).
//!    The prediction is right except next to dropped buried voxels and for
//!    coarse voxels' ORed masks, so the column is mostly zeros.
//! 3. **normals**: octahedral snorm8 pairs, all x bytes then all y bytes, each
//!    stored as the wrapping difference from the previous voxel's byte.
//! 4. **coverage** (levels above 0 only; level 0 is always full): one byte per voxel, 1..=255.
//! 5. **colour** (when flagged): sRGB8, all r then all g then all b bytes,
//!    each a wrapping difference from the previous voxel's.
//! 6. **AO field** (when flagged, issue 9 item 2): one byte per voxel, the
//!    precomputed visibility `1 + round(254·V)` for the voxel's normal (0: none
//!    for this voxel), stored as the wrapping difference from the previous
//!    voxel's. Blocks without it (every scene built before it) decode as
//!    before, with no field.

use crate::{BLOCK_VOXELS, Block, BlockKey, FULL_COVERAGE, MAX_LEVEL, PackedVoxel};

pub const BLOCK_MAGIC: [u8; 4] = *b"VXB2";
pub const HEADER_LEN: usize = 28;
/// Header flag: the block has a colour column.
pub const FLAG_COLOR: u8 = 1;
/// Header flag: the block has an AO field column.
pub const FLAG_FIELD: u8 = 2;
/// Octree depth of a 64³ block: 6 levels of 2³.
pub const BLOCK_DEPTH: u32 = 6;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CodecError {
    #[error("block is {0} bytes, shorter than its {HEADER_LEN}-byte header")]
    Truncated(usize),
    #[error("block does not start with the VXB2 magic")]
    BadMagic,
    #[error("block header is invalid: {0}")]
    BadHeader(&'static str),
    #[error("block claims {0} voxels, more than a 64³ block holds")]
    TooManyVoxels(u32),
    #[error("block payload is corrupt: {0}")]
    Corrupt(String),
    #[error("voxel {index} is invalid: {why}")]
    BadVoxel { index: usize, why: &'static str },
}

/// A block's voxels as separate columns, for any octree depth (block edge
/// `2^depth`): the block codec uses depth 6; the block-size measurements in
/// `examples/block_stats.rs` use 5 and 7 with the same code.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct VoxelColumns {
    /// Octree depth: the block is `2^depth` voxels per edge (1..=7).
    pub depth: u32,
    /// Block-local Morton codes, strictly increasing, `< 8^depth`.
    pub morton: Vec<u32>,
    /// Face masks, nonzero, `< 64`.
    pub faces: Vec<u8>,
    /// Octahedral snorm8 normals (x low byte).
    pub normal: Vec<u16>,
    /// Empty = every voxel full (level 0); else one nonzero byte per voxel.
    pub coverage: Vec<u8>,
    /// Empty = no colour; else one sRGB8 triple per voxel.
    pub color: Vec<[u8; 3]>,
    /// Empty = no AO field; else one byte per voxel (`1 + round(254·V)`, 0 = none).
    pub field: Vec<u8>,
}

/// Compressed size of each column on its own, for measurements.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ColumnSizes {
    pub occupancy: usize,
    pub faces: usize,
    pub normals: usize,
    pub coverage: usize,
    pub colors: usize,
    pub field: usize,
}

impl std::ops::AddAssign for ColumnSizes {
    fn add_assign(&mut self, o: Self) {
        self.occupancy += o.occupancy;
        self.faces += o.faces;
        self.normals += o.normals;
        self.coverage += o.coverage;
        self.colors += o.colors;
        self.field += o.field;
    }
}

fn axis_masks(depth: u32) -> [u32; 3] {
    let x: u32 = (0..depth).map(|i| 1 << (3 * i)).sum();
    [x, x << 1, x << 2]
}

/// The face masks the codec predicts for a 64³ block's voxels (Morton codes,
/// strictly increasing) from their occupancy alone: a face is exposed when
/// the neighbour across it is outside the block or not occupied. Bit 2a is
/// the negative side of axis a, 2a + 1 the positive.
pub fn predicted_face_masks(morton: &[u32]) -> Vec<u8> {
    predicted_faces(BLOCK_DEPTH, morton)
}

/// [`predicted_face_masks`] at any depth.
fn predicted_faces(depth: u32, morton: &[u32]) -> Vec<u8> {
    let mut occupied = vec![0u64; (1usize << (3 * depth)).div_ceil(64)];
    for &m in morton {
        occupied[m as usize / 64] |= 1 << (m % 64);
    }
    let is_set = |m: u32| occupied[m as usize / 64] & (1 << (m % 64)) != 0;
    let masks = axis_masks(depth);
    morton
        .iter()
        .map(|&m| {
            let mut faces = 0u8;
            for (axis, &mask) in masks.iter().enumerate() {
                let c = m & mask;
                let rest = m & !mask;
                // Morton-space decrement/increment of one coordinate.
                let below = c == 0 || !is_set(((c.wrapping_sub(1)) & mask) | rest);
                let above = c == mask || !is_set((((c | !mask).wrapping_add(1)) & mask) | rest);
                faces |= (below as u8) << (2 * axis) | (above as u8) << (2 * axis + 1);
            }
            faces
        })
        .collect()
}

fn octree_masks(depth: u32, morton: &[u32]) -> Vec<u8> {
    let mut out = Vec::new();
    write_octree_masks(depth, morton, &mut out);
    out
}

/// Appends the occupancy column: the octree's child masks, breadth first.
///
/// One pass over the voxels: a voxel opens a new node at every depth below
/// the first where its path leaves the previous voxel's (Morton order keeps
/// each node's voxels together), and sets its child bit in the node it shares.
/// The nodes of each depth come out in order; the depths are then concatenated.
fn write_octree_masks(depth: u32, morton: &[u32], out: &mut Vec<u8>) {
    debug_assert!((1..=7).contains(&depth) && morton.windows(2).all(|w| w[0] < w[1]));
    let Some(&first) = morton.first() else { return };
    let depth = depth as usize;
    // Masks of the nodes at each depth (0 = the root); depth d has at most
    // 8^d nodes and one per voxel, so none grows.
    let mut levels: [Vec<u8>; 7] =
        std::array::from_fn(|d| Vec::with_capacity(morton.len().min(1 << (3 * d))));
    let child_at = |m: u32, d: usize| (m >> (3 * (depth - 1 - d))) & 7;
    for (d, level) in levels.iter_mut().enumerate().take(depth) {
        level.push(1 << child_at(first, d));
    }
    let mut prev = first;
    for &m in &morton[1..] {
        // Shallowest depth whose child differs: the paths agree above it.
        let diff_bits = 32 - (m ^ prev).leading_zeros() as usize;
        let split = depth - diff_bits.div_ceil(3);
        *levels[split].last_mut().expect("the first voxel opened every depth") |= 1 << child_at(m, split);
        for (d, level) in levels.iter_mut().enumerate().take(depth).skip(split + 1) {
            level.push(1 << child_at(m, d));
        }
        prev = m;
    }
    for level in &levels[..depth] {
        out.extend_from_slice(level);
    }
}

/// Appends each value less the one before it (the first less 0), wrapping.
fn delta_plane(values: impl ExactSizeIterator<Item = u8>, out: &mut Vec<u8>) {
    let start = out.len();
    // Written in place rather than pushed: no capacity check a byte.
    out.resize(start + values.len(), 0);
    let mut prev = 0u8;
    for (o, v) in out[start..].iter_mut().zip(values) {
        *o = v.wrapping_sub(prev);
        prev = v;
    }
}

impl VoxelColumns {
    /// The columns of a decoded 64³ block; coverage is dropped on level 0
    /// (always full there) and colour when no voxel has any.
    pub fn from_block(block: &Block) -> Self {
        let v = &block.voxels;
        let has_color = v.iter().any(|v| v.color().is_some());
        let has_field = v.iter().any(|v| v.field().is_some());
        Self {
            depth: BLOCK_DEPTH,
            morton: v.iter().map(PackedVoxel::morton).collect(),
            faces: v.iter().map(PackedVoxel::faces).collect(),
            normal: v.iter().map(|v| v.normal as u16).collect(),
            coverage: if block.key.level == 0 {
                Vec::new()
            } else {
                v.iter().map(|v| v.coverage()).collect()
            },
            color: if has_color {
                v.iter().map(|v| v.color().unwrap_or([0; 3])).collect()
            } else {
                Vec::new()
            },
            field: if has_field { v.iter().map(|v| v.field().unwrap_or(0)).collect() } else { Vec::new() },
        }
    }

    pub fn len(&self) -> usize {
        self.morton.len()
    }

    pub fn is_empty(&self) -> bool {
        self.morton.is_empty()
    }

    /// The six payload sections, uncompressed.
    fn sections(&self) -> [Vec<u8>; 6] {
        let n = self.len();
        let occupancy = octree_masks(self.depth, &self.morton);
        let mut faces = Vec::with_capacity(n);
        self.write_faces(None, &mut faces);
        let mut normals = Vec::with_capacity(2 * n);
        self.write_normals(&mut normals);
        let mut colors = Vec::with_capacity(3 * self.color.len());
        self.write_colors(&mut colors);
        let mut field = Vec::with_capacity(self.field.len());
        delta_plane(self.field.iter().copied(), &mut field);
        [occupancy, faces, normals, self.coverage.clone(), colors, field]
    }

    /// The faces column: each mask XOR the mask predicted from occupancy.
    /// `prediction`: the caller's copy of that prediction (one mask a voxel,
    /// as [`predicted_face_masks`] gives), which spares the codec the
    /// neighbour lookups; `None`: the codec predicts.
    fn write_faces(&self, prediction: Option<&[u8]>, out: &mut Vec<u8>) {
        let own;
        let p = match prediction {
            Some(p) => {
                assert_eq!(p.len(), self.len(), "one predicted mask a voxel");
                debug_assert_eq!(p, predicted_faces(self.depth, &self.morton), "not the prediction");
                p
            }
            None => {
                own = predicted_faces(self.depth, &self.morton);
                &own
            }
        };
        out.extend(self.faces.iter().zip(p).map(|(f, p)| f ^ p));
    }

    fn write_normals(&self, out: &mut Vec<u8>) {
        delta_plane(self.normal.iter().map(|n| *n as u8), out);
        delta_plane(self.normal.iter().map(|n| (n >> 8) as u8), out);
    }

    fn write_colors(&self, out: &mut Vec<u8>) {
        for c in 0..3 {
            delta_plane(self.color.iter().map(|rgb| rgb[c]), out);
        }
    }

    /// Appends the uncompressed payload (the sections in order) to `out`;
    /// `prediction` as in [`Self::write_faces`].
    fn write_payload(&self, prediction: Option<&[u8]>, out: &mut Vec<u8>) {
        let n = self.len();
        out.reserve(
            n * (4 + self.coverage.len().min(1) + 3 * self.color.len().min(1) + self.field.len().min(1)),
        );
        write_octree_masks(self.depth, &self.morton, out);
        self.write_faces(prediction, out);
        self.write_normals(out);
        out.extend_from_slice(&self.coverage);
        self.write_colors(out);
        delta_plane(self.field.iter().copied(), out);
    }

    /// The uncompressed payload.
    pub fn payload(&self) -> Vec<u8> {
        let mut out = Vec::new();
        self.write_payload(None, &mut out);
        out
    }

    /// Each column lz4-compressed on its own (the sum is a little more than
    /// the one lz4 block the codec writes).
    pub fn column_sizes(&self) -> ColumnSizes {
        let s = self.sections().map(|c| if c.is_empty() { 0 } else { lz4_flex::block::compress(&c).len() });
        ColumnSizes { occupancy: s[0], faces: s[1], normals: s[2], coverage: s[3], colors: s[4], field: s[5] }
    }

    /// Inverse of [`VoxelColumns::payload`] for columns without an AO field.
    pub fn from_payload(
        depth: u32,
        count: usize,
        has_coverage: bool,
        has_color: bool,
        raw: &[u8],
    ) -> Result<Self, CodecError> {
        Self::from_payload_with_field(depth, count, has_coverage, has_color, false, raw)
    }

    /// Inverse of [`VoxelColumns::payload`], validating everything. `count`
    /// must already be bounded by the caller (it sizes the output).
    pub fn from_payload_with_field(
        depth: u32,
        count: usize,
        has_coverage: bool,
        has_color: bool,
        has_field: bool,
        raw: &[u8],
    ) -> Result<Self, CodecError> {
        let corrupt = |s: &str| CodecError::Corrupt(s.to_string());
        // Occupancy: expand the octree breadth first.
        let mut at = 0;
        let mut nodes: Vec<u32> = if count == 0 { Vec::new() } else { vec![0] };
        for _ in 0..depth {
            let mut next = Vec::with_capacity(count.min(nodes.len() * 8));
            for &p in &nodes {
                let Some(&mask) = raw.get(at) else {
                    return Err(corrupt("occupancy octree is truncated"));
                };
                at += 1;
                if mask == 0 {
                    return Err(corrupt("occupancy octree has an empty node"));
                }
                for bit in 0..8 {
                    if mask & (1 << bit) != 0 {
                        next.push(p << 3 | bit);
                    }
                }
            }
            // Every node has a child, so a level never shrinks: too many is final.
            if next.len() > count {
                return Err(corrupt("occupancy octree holds more voxels than the header says"));
            }
            nodes = next;
        }
        if nodes.len() != count {
            return Err(CodecError::Corrupt(format!(
                "occupancy octree holds {} voxels, the header says {count}",
                nodes.len()
            )));
        }
        let per_voxel = 3 + has_coverage as usize + 3 * has_color as usize + has_field as usize;
        if raw.len() - at != count * per_voxel {
            return Err(CodecError::Corrupt(format!(
                "payload holds {} bytes after the octree, {count} voxels need {}",
                raw.len() - at,
                count * per_voxel
            )));
        }
        let morton = nodes;
        let mut rest = &raw[at..];
        let mut take = |len: usize| {
            let (head, tail) = rest.split_at(len);
            rest = tail;
            head
        };
        let predicted = predicted_faces(depth, &morton);
        let mut faces = Vec::with_capacity(count);
        for (i, (stored, p)) in take(count).iter().zip(predicted).enumerate() {
            let f = stored ^ p;
            if f >= 64 {
                return Err(CodecError::BadVoxel { index: i, why: "reserved face bits set" });
            }
            if f == 0 {
                return Err(CodecError::BadVoxel { index: i, why: "no exposed face" });
            }
            faces.push(f);
        }
        let undelta = |plane: &[u8]| -> Vec<u8> {
            let mut prev = 0u8;
            plane
                .iter()
                .map(|d| {
                    prev = prev.wrapping_add(*d);
                    prev
                })
                .collect()
        };
        let nx = undelta(take(count));
        let ny = undelta(take(count));
        let normal = nx.iter().zip(&ny).map(|(&x, &y)| x as u16 | (y as u16) << 8).collect();
        let coverage = if has_coverage { take(count).to_vec() } else { Vec::new() };
        if let Some(i) = coverage.iter().position(|&c| c == 0) {
            return Err(CodecError::BadVoxel { index: i, why: "zero coverage" });
        }
        let color = if has_color {
            let (r, g, b) = (undelta(take(count)), undelta(take(count)), undelta(take(count)));
            (0..count).map(|i| [r[i], g[i], b[i]]).collect()
        } else {
            Vec::new()
        };
        let field = if has_field { undelta(take(count)) } else { Vec::new() };
        Ok(Self { depth, morton, faces, normal, coverage, color, field })
    }
}

/// Most payload bytes a block of `count` voxels can have: a full octree above
/// the voxels (bounded by both the tree and 6 nodes per voxel) plus the columns.
fn max_payload(count: usize, has_coverage: bool, has_color: bool, has_field: bool) -> usize {
    let tree: usize = (0..BLOCK_DEPTH).map(|d| 1usize << (3 * d)).sum();
    tree.min(BLOCK_DEPTH as usize * count)
        + count * (3 + has_coverage as usize + 3 * has_color as usize + has_field as usize)
}

/// Encodes a block. The voxels must be in strictly increasing Morton order
/// (what [`decode_block`] checks), which keeps encoding deterministic. The
/// block has a colour column when any voxel has colour (an uncoloured voxel
/// in it then decodes as black); coverage is stored above level 0 only.
pub fn encode_block(block: &Block) -> Vec<u8> {
    debug_assert!(block.voxels.windows(2).all(|w| w[0].morton() < w[1].morton()));
    debug_assert!(block.key.level > 0 || block.voxels.iter().all(|v| v.coverage() == FULL_COVERAGE));
    encode_columns(block.key, &VoxelColumns::from_block(block), None)
}

/// Encodes a 64³ block given as columns: the bytes of [`encode_block`] for
/// the block whose [`VoxelColumns::from_block`] they are (Morton codes
/// strictly increasing, coverage present iff `key.level > 0`, colour empty
/// or one per voxel). `prediction`: the face masks predicted from these
/// voxels' occupancy ([`predicted_face_masks`]), when the caller has them
/// from marking the faces; the codec otherwise works them out itself.
pub fn encode_columns(key: BlockKey, columns: &VoxelColumns, prediction: Option<&[u8]>) -> Vec<u8> {
    let n = columns.len();
    assert!(columns.depth == BLOCK_DEPTH && n <= BLOCK_VOXELS, "not a 64³ block's columns");
    assert_eq!(
        columns.coverage.is_empty(),
        key.level == 0 || n == 0,
        "coverage is stored above level 0 only"
    );
    assert!(
        columns.faces.len() == n
            && columns.normal.len() == n
            && (columns.color.is_empty() || columns.color.len() == n)
            && (columns.field.is_empty() || columns.field.len() == n)
    );
    let mut raw = Vec::new();
    columns.write_payload(prediction, &mut raw);
    let packed = lz4_flex::block::compress(&raw);
    let flags = if columns.color.is_empty() { 0 } else { FLAG_COLOR }
        | if columns.field.is_empty() { 0 } else { FLAG_FIELD };

    let mut out = Vec::with_capacity(HEADER_LEN + packed.len());
    out.extend_from_slice(&BLOCK_MAGIC);
    out.extend_from_slice(&[key.level, flags, 0, 0]);
    for c in key.coord() {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
    out.extend_from_slice(&packed);
    out
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Decodes and validates a block. Never panics and never allocates more than
/// a full block's payload, whatever the bytes say.
pub fn decode_block(bytes: &[u8]) -> Result<Block, CodecError> {
    if bytes.len() < HEADER_LEN {
        return Err(CodecError::Truncated(bytes.len()));
    }
    if bytes[..4] != BLOCK_MAGIC {
        return Err(CodecError::BadMagic);
    }
    let level = bytes[4];
    if level > MAX_LEVEL {
        return Err(CodecError::BadHeader("level too deep"));
    }
    let flags = bytes[5];
    if flags & !(FLAG_COLOR | FLAG_FIELD) != 0 {
        return Err(CodecError::BadHeader("unknown flag bits set"));
    }
    if bytes[6..8] != [0, 0] {
        return Err(CodecError::BadHeader("reserved bytes are not zero"));
    }
    let key = BlockKey::new(level, u32_at(bytes, 8), u32_at(bytes, 12), u32_at(bytes, 16));
    let count = u32_at(bytes, 20);
    if count as usize > BLOCK_VOXELS {
        return Err(CodecError::TooManyVoxels(count));
    }
    let n = count as usize;
    let (has_coverage, has_color, has_field) = (level > 0, flags & FLAG_COLOR != 0, flags & FLAG_FIELD != 0);
    let raw_len = u32_at(bytes, 24) as usize;
    if raw_len > max_payload(n, has_coverage, has_color, has_field) {
        return Err(CodecError::BadHeader("payload length is too large for the voxel count"));
    }
    let mut raw = vec![0u8; raw_len];
    let written = lz4_flex::block::decompress_into(&bytes[HEADER_LEN..], &mut raw)
        .map_err(|e| CodecError::Corrupt(e.to_string()))?;
    if written != raw.len() {
        return Err(CodecError::Corrupt(format!("payload holds {written} bytes, header says {raw_len}")));
    }
    let c = VoxelColumns::from_payload_with_field(BLOCK_DEPTH, n, has_coverage, has_color, has_field, &raw)?;
    let mut voxels = Vec::with_capacity(n);
    for i in 0..n {
        let [x, y, z] = crate::demorton3(c.morton[i]);
        let mut v = PackedVoxel::new([x, y, z], c.faces[i], c.normal[i] as u32);
        if has_coverage {
            v = v.with_coverage(c.coverage[i]);
        }
        if has_color {
            v = v.with_color(c.color[i]);
        }
        if has_field {
            v = v.with_field(c.field[i]);
        }
        voxels.push(v);
    }
    Ok(Block { key, voxels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{BLOCK_SIZE, morton3, oct_encode};
    use proptest::prelude::*;

    type Spec = ([u32; 3], u8, [f32; 3]);

    fn block_at(key: BlockKey, mut locals: Vec<Spec>) -> Block {
        locals.sort_by_key(|(p, _, _)| morton3(p[0], p[1], p[2]));
        locals.dedup_by_key(|(p, _, _)| morton3(p[0], p[1], p[2]));
        Block {
            key,
            voxels: locals.into_iter().map(|(p, f, n)| PackedVoxel::new(p, f, oct_encode(n))).collect(),
        }
    }

    /// The breadth-first octree as first written (one pass per depth): the
    /// reference for the one-pass `write_octree_masks`.
    fn octree_masks_by_depth(depth: u32, morton: &[u32]) -> Vec<u8> {
        let mut out = Vec::new();
        for d in 0..depth {
            let shift = 3 * (depth - 1 - d);
            let (mut parent, mut last_child) = (None, None);
            for &m in morton {
                let child = m >> shift;
                if last_child == Some(child) {
                    continue;
                }
                last_child = Some(child);
                if parent != Some(child >> 3) {
                    parent = Some(child >> 3);
                    out.push(0);
                }
                *out.last_mut().expect("pushed") |= 1 << (child & 7);
            }
        }
        out
    }

    proptest! {
        /// Fails if the one-pass octree differs from the per-depth one at any depth.
        #[test]
        fn one_pass_octree_matches_the_per_depth_one(depth in 1u32..=7, raw in proptest::collection::vec(any::<u32>(), 0..600)) {
            let mut morton: Vec<u32> = raw.iter().map(|m| m % (1 << (3 * depth))).collect();
            morton.sort_unstable();
            morton.dedup();
            prop_assert_eq!(octree_masks(depth, &morton), octree_masks_by_depth(depth, &morton));
        }
    }

    /// Fails if `encode_columns` given the prediction differs from
    /// `encode_block`, on a block whose faces are the prediction and on one whose are not.
    #[test]
    fn predicted_faces_encode_the_same_bytes() {
        // A one-voxel-thick plane: no voxel is buried, so every predicted mask is a valid one.
        let locals: Vec<Spec> =
            (0..400u32).map(|i| ([i % 20 + 20, i / 20, 30], 0, [0.3, -0.2, 0.9])).collect();
        let mut block = block_from(locals);
        let morton: Vec<u32> = block.voxels.iter().map(PackedVoxel::morton).collect();
        for (v, f) in block.voxels.iter_mut().zip(predicted_faces(BLOCK_DEPTH, &morton)) {
            *v = PackedVoxel::new(v.local(), f, v.normal);
        }
        let columns = VoxelColumns::from_block(&block);
        let prediction = predicted_face_masks(&morton);
        assert_eq!(encode_columns(block.key, &columns, Some(&prediction)), encode_block(&block));
        assert_eq!(decode_block(&encode_block(&block)), Ok(block.clone()));
        // Masks that differ from the prediction round-trip through the given one too.
        for (i, v) in block.voxels.iter_mut().enumerate() {
            *v = PackedVoxel::new(v.local(), (i % 63 + 1) as u8, v.normal);
        }
        let columns = VoxelColumns::from_block(&block);
        let bytes = encode_columns(block.key, &columns, Some(&prediction));
        assert_eq!(bytes, encode_block(&block));
        assert_eq!(decode_block(&bytes), Ok(block));
    }

    fn block_from(locals: Vec<Spec>) -> Block {
        block_at(BlockKey::new(0, 1, 0, 3), locals)
    }

    fn full_block() -> Block {
        let mut all = Vec::new();
        for z in 0..BLOCK_SIZE {
            for y in 0..BLOCK_SIZE {
                for x in 0..BLOCK_SIZE {
                    all.push(([x, y, z], ((x + y + z) % 63 + 1) as u8, [x as f32, y as f32 - 30.0, 1.0]));
                }
            }
        }
        block_from(all)
    }

    #[test]
    fn empty_block_round_trips() {
        let b = block_from(vec![]);
        let bytes = encode_block(&b);
        assert_eq!(bytes.len(), HEADER_LEN + 1);
        assert_eq!(decode_block(&bytes).unwrap(), b);
    }

    #[test]
    fn full_block_round_trips() {
        let b = full_block();
        assert_eq!(b.voxels.len(), crate::BLOCK_VOXELS);
        let bytes = encode_block(&b);
        assert_eq!(decode_block(&bytes).unwrap(), b);
    }

    #[test]
    fn ao_field_column_round_trips_and_is_flagged() {
        let plain = block_at(
            BlockKey::new(1, 0, 1, 0),
            (0..300).map(|i| ([i % 64, i / 64, 5], 1 + (i % 63) as u8, [1.0, 0.0, i as f32])).collect(),
        );
        let mut b = plain.clone();
        for (i, v) in b.voxels.iter_mut().enumerate() {
            // 0 (no value for this voxel) must survive too.
            *v = v.with_field((i % 256) as u8);
        }
        let bytes = encode_block(&b);
        assert_eq!(bytes[5], FLAG_FIELD);
        let back = decode_block(&bytes).unwrap();
        assert_eq!(back, b);
        assert_eq!(back.voxels[7].field(), Some(7));
        assert_eq!(back.voxels[0].field(), None);
        // The field costs one byte a voxel before lz4 and changes nothing else.
        let without = encode_block(&plain);
        assert_eq!(without[5], 0);
        assert_eq!(u32_at(&bytes, 24) - u32_at(&without, 24), 300);
        assert!(decode_block(&without).unwrap().voxels.iter().all(|v| v.field().is_none()));
        // Control: the same bytes with the flag cleared no longer decode (the payload is a byte a voxel too long).
        let mut unflagged = bytes.clone();
        unflagged[5] = 0;
        assert!(decode_block(&unflagged).is_err());
        // Unknown flag bits are still refused.
        let mut unknown = bytes;
        unknown[5] |= 4;
        assert_eq!(decode_block(&unknown), Err(CodecError::BadHeader("unknown flag bits set")));
    }

    #[test]
    fn coverage_and_colour_round_trip() {
        let mut b = block_at(
            BlockKey::new(3, 0, 1, 0),
            (0..500).map(|i| ([i % 64, i / 64, 3], 1 + (i % 63) as u8, [0.0, 1.0, i as f32])).collect(),
        );
        for (i, v) in b.voxels.iter_mut().enumerate() {
            *v = v.with_coverage(1 + (i % 255) as u8).with_color([i as u8, 7, (i * 3) as u8]);
        }
        let bytes = encode_block(&b);
        assert_eq!(bytes[5], FLAG_COLOR);
        assert_eq!(decode_block(&bytes).unwrap(), b);
    }

    #[test]
    fn predicted_faces_match_exposure() {
        // Two neighbours along x in the middle, one voxel on the -x boundary.
        let m = |p: [u32; 3]| morton3(p[0], p[1], p[2]);
        let mut pts = [m([10, 10, 10]), m([11, 10, 10]), m([0, 5, 5])];
        pts.sort();
        let f = predicted_faces(6, &pts);
        let at = |p| f[pts.iter().position(|&q| q == m(p)).unwrap()];
        assert_eq!(at([10, 10, 10]), 63 & !2);
        assert_eq!(at([11, 10, 10]), 63 & !1);
        assert_eq!(at([0, 5, 5]), 63);
        // On a 64³ edge, increments must not wrap into the next coordinate.
        let edge = [m([63, 0, 0]), m([0, 1, 0])];
        assert_eq!(predicted_faces(6, &edge), vec![63, 63]);
    }

    #[test]
    fn octree_masks_count_nodes() {
        // One voxel: one mask per depth.
        assert_eq!(octree_masks(6, &[morton3(63, 0, 0)]).len(), 6);
        // A full block: 1 + 8 + … + 8^5 nodes.
        let all: Vec<u32> = (0..(1 << 18)).collect();
        let masks = octree_masks(6, &all);
        assert_eq!(masks.len(), 37449);
        assert!(masks.iter().all(|&m| m == 255));
    }

    #[test]
    fn every_truncation_is_an_error() {
        let b = block_from(
            (0..300).map(|i| ([i % 64, i / 64, 7], 1 + (i % 63) as u8, [0.0, 1.0, 0.0])).collect(),
        );
        let bytes = encode_block(&b);
        for len in 0..bytes.len() {
            assert!(decode_block(&bytes[..len]).is_err(), "truncated to {len} decoded");
        }
    }

    #[test]
    fn header_damage_is_named() {
        let bytes = encode_block(&block_from(vec![([1, 2, 3], 1, [1.0, 0.0, 0.0])]));
        assert!(decode_block(&bytes).is_ok());
        let mut bad = bytes.clone();
        bad[0] = b'X';
        assert_eq!(decode_block(&bad), Err(CodecError::BadMagic));
        let mut bad = bytes.clone();
        bad[20..24].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(decode_block(&bad), Err(CodecError::TooManyVoxels(u32::MAX)));
        let mut bad = bytes.clone();
        bad[4] = 200;
        assert!(matches!(decode_block(&bad), Err(CodecError::BadHeader(_))));
        let mut bad = bytes.clone();
        bad[5] = 4;
        assert_eq!(decode_block(&bad), Err(CodecError::BadHeader("unknown flag bits set")));
        // A payload length the count cannot need is refused before allocating.
        let mut bad = bytes.clone();
        bad[24..28].copy_from_slice(&(1u32 << 30).to_le_bytes());
        assert!(matches!(decode_block(&bad), Err(CodecError::BadHeader(_))));
        // Claiming two voxels for a one-voxel octree.
        let mut bad = bytes.clone();
        bad[20..24].copy_from_slice(&2u32.to_le_bytes());
        assert!(decode_block(&bad).is_err());
    }

    #[test]
    fn payload_damage_is_found() {
        let b = block_from(vec![([1, 2, 3], 1, [1.0, 0.0, 0.0]), ([5, 2, 3], 2, [1.0, 0.0, 0.0])]);
        let mut cols = VoxelColumns::from_block(&b);
        let good = cols.payload();
        assert!(VoxelColumns::from_payload(6, 2, false, false, &good).is_ok());
        // An empty octree node.
        let mut bad = good.clone();
        bad[0] = 0;
        assert!(VoxelColumns::from_payload(6, 2, false, false, &bad).is_err());
        // A face mask that XORs to zero (the voxel would have no face).
        cols.faces[0] = 0;
        let bad = cols.payload();
        assert_eq!(
            VoxelColumns::from_payload(6, 2, false, false, &bad),
            Err(CodecError::BadVoxel { index: 0, why: "no exposed face" })
        );
        // One byte too many or too few after the octree.
        let mut long = good.clone();
        long.push(0);
        assert!(VoxelColumns::from_payload(6, 2, false, false, &long).is_err());
        assert!(VoxelColumns::from_payload(6, 2, false, false, &good[..good.len() - 1]).is_err());
    }

    fn arb_block() -> impl Strategy<Value = Block> {
        (
            0u8..4,
            prop::collection::vec(
                ((0u32..64, 0u32..64, 0u32..64), 1u8..64, any::<u16>(), 1u8..=255, any::<[u8; 3]>()),
                0..600,
            ),
            any::<bool>(),
        )
            .prop_map(|(level, v, colored)| {
                let mut v: Vec<_> =
                    v.into_iter().map(|((x, y, z), f, n, c, rgb)| (morton3(x, y, z), f, n, c, rgb)).collect();
                v.sort_by_key(|t| t.0);
                v.dedup_by_key(|t| t.0);
                let voxels = v
                    .into_iter()
                    .map(|(m, f, n, c, rgb)| {
                        let mut p = PackedVoxel::new(crate::demorton3(m), f, n as u32);
                        if level > 0 {
                            p = p.with_coverage(c);
                        }
                        if colored {
                            p = p.with_color(rgb);
                        }
                        p
                    })
                    .collect();
                Block { key: BlockKey::new(level, 2, 0, 5), voxels }
            })
    }

    proptest! {
        #[test]
        fn random_blocks_round_trip(b in arb_block()) {
            prop_assert_eq!(decode_block(&encode_block(&b)).unwrap(), b);
        }

        #[test]
        fn corrupt_bytes_never_panic(flips in prop::collection::vec((0usize..4096, any::<u8>()), 1..8)) {
            let mut bytes = encode_block(&block_from((0..200).map(|i| ([i % 64, i / 64, 9], 3, [0.0, 0.0, 1.0])).collect()));
            for (at, val) in flips {
                let at = at % bytes.len();
                bytes[at] ^= val | 1;
            }
            if let Ok(b) = decode_block(&bytes) {
                prop_assert!(b.voxels.windows(2).all(|w| w[0].morton() < w[1].morton()));
                prop_assert!(b.voxels.iter().all(|v| v.faces() != 0));
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode_block(&bytes);
        }

        #[test]
        fn arbitrary_payloads_never_panic(
            count in 0usize..40, cov in any::<bool>(), col in any::<bool>(),
            raw in prop::collection::vec(any::<u8>(), 0..400),
        ) {
            if let Ok(c) = VoxelColumns::from_payload(6, count, cov, col, &raw) {
                prop_assert_eq!(c.len(), count);
                prop_assert!(c.morton.windows(2).all(|w| w[0] < w[1]));
            }
        }
    }
}
