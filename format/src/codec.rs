//! Block wire format: a fixed little-endian header, then one lz4 block holding
//! the voxel columns (all `pos_faces` words, then all `normal` words). Columns
//! compress better than interleaved records because neighbours in Morton order
//! share high position bits and similar normals.
//!
//! ```text
//! 0  magic  "VXB1"
//! 4  level  u8, then 3 reserved zero bytes
//! 8  x, y, z  u32 each
//! 20 voxel count u32 (≤ 64³)
//! 24 lz4 block of count·8 bytes
//! ```

use crate::{BLOCK_VOXELS, Block, BlockKey, MAX_LEVEL, PackedVoxel};

pub const BLOCK_MAGIC: [u8; 4] = *b"VXB1";
pub const HEADER_LEN: usize = 24;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CodecError {
    #[error("block is {0} bytes, shorter than its {HEADER_LEN}-byte header")]
    Truncated(usize),
    #[error("block does not start with the VXB1 magic")]
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

/// Encodes a block. The voxels must be in strictly increasing Morton order
/// (what [`decode_block`] checks), which keeps encoding deterministic.
pub fn encode_block(block: &Block) -> Vec<u8> {
    debug_assert!(block.voxels.windows(2).all(|w| w[0].morton() < w[1].morton()));
    let n = block.voxels.len();
    let mut raw = Vec::with_capacity(n * 8);
    raw.extend(block.voxels.iter().flat_map(|v| v.pos_faces.to_le_bytes()));
    raw.extend(block.voxels.iter().flat_map(|v| v.normal.to_le_bytes()));
    let packed = lz4_flex::block::compress(&raw);

    let mut out = Vec::with_capacity(HEADER_LEN + packed.len());
    out.extend_from_slice(&BLOCK_MAGIC);
    out.extend_from_slice(&[block.key.level, 0, 0, 0]);
    for c in block.key.coord() {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&packed);
    out
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Decodes and validates a block. Never panics and never allocates more than
/// a full block, whatever the bytes say.
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
    if bytes[5..8] != [0, 0, 0] {
        return Err(CodecError::BadHeader("reserved bytes are not zero"));
    }
    let key = BlockKey::new(level, u32_at(bytes, 8), u32_at(bytes, 12), u32_at(bytes, 16));
    let count = u32_at(bytes, 20);
    if count as usize > BLOCK_VOXELS {
        return Err(CodecError::TooManyVoxels(count));
    }
    let n = count as usize;
    let mut raw = vec![0u8; n * 8];
    let written = lz4_flex::block::decompress_into(&bytes[HEADER_LEN..], &mut raw)
        .map_err(|e| CodecError::Corrupt(e.to_string()))?;
    if written != raw.len() {
        return Err(CodecError::Corrupt(format!(
            "payload holds {written} bytes, header implies {}",
            raw.len()
        )));
    }
    let mut voxels = Vec::with_capacity(n);
    let mut prev_morton = None;
    for i in 0..n {
        let v = PackedVoxel { pos_faces: u32_at(&raw, i * 4), normal: u32_at(&raw, (n + i) * 4) };
        if v.pos_faces >> 24 != 0 {
            return Err(CodecError::BadVoxel { index: i, why: "reserved bits set" });
        }
        if v.faces() == 0 {
            return Err(CodecError::BadVoxel { index: i, why: "no exposed face" });
        }
        let m = v.morton();
        if prev_morton.is_some_and(|p| p >= m) {
            return Err(CodecError::BadVoxel { index: i, why: "not in increasing Morton order" });
        }
        prev_morton = Some(m);
        voxels.push(v);
    }
    Ok(Block { key, voxels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{BLOCK_SIZE, morton3, oct_encode};
    use proptest::prelude::*;

    fn block_from(mut locals: Vec<([u32; 3], u8, [f32; 3])>) -> Block {
        locals.sort_by_key(|(p, _, _)| morton3(p[0], p[1], p[2]));
        locals.dedup_by_key(|(p, _, _)| morton3(p[0], p[1], p[2]));
        Block {
            key: BlockKey::new(2, 1, 0, 3),
            voxels: locals.into_iter().map(|(p, f, n)| PackedVoxel::new(p, f, oct_encode(n))).collect(),
        }
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
        let mut bad = bytes.clone();
        bad[0] = b'X';
        assert_eq!(decode_block(&bad), Err(CodecError::BadMagic));
        let mut bad = bytes.clone();
        bad[20..24].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(decode_block(&bad), Err(CodecError::TooManyVoxels(u32::MAX)));
        let mut bad = bytes.clone();
        bad[4] = 200;
        assert!(matches!(decode_block(&bad), Err(CodecError::BadHeader(_))));
    }

    proptest! {
        #[test]
        fn random_blocks_round_trip(v in prop::collection::vec(((0u32..64, 0u32..64, 0u32..64), 1u8..64, (-1f32..1.0, -1f32..1.0, -1f32..1.0)), 0..500)) {
            let b = block_from(v.into_iter().map(|((x, y, z), f, (a, b, c))| ([x, y, z], f, [a, b, c])).collect());
            prop_assert_eq!(decode_block(&encode_block(&b)).unwrap(), b);
        }

        #[test]
        fn corrupt_bytes_never_panic(flips in prop::collection::vec((0usize..4096, any::<u8>()), 1..8)) {
            let mut bytes = encode_block(&block_from((0..200).map(|i| ([i % 64, i / 64, 9], 3, [0.0, 0.0, 1.0])).collect()));
            for (at, val) in flips {
                let at = at % bytes.len();
                bytes[at] ^= val | 1;
            }
            let _ = decode_block(&bytes);
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode_block(&bytes);
        }
    }
}
