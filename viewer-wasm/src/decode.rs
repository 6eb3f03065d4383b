//! Fetched bytes → a validated block. The format crate checks the bytes
//! themselves; this checks that they are the block we asked for and agree with
//! the manifest (its voxel count and content hash), so a misrouted or stale
//! response, or the wrong slice of a pack, can never be drawn in the wrong place.

use voxstream_format::{Block, BlockEntry, BlockKey, CodecError, PackedVoxel, decode_block};

use crate::occlusion::OccupiedCells;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DecodeError {
    #[error("block {key}: {source}")]
    Codec { key: BlockKey, source: CodecError },
    #[error("asked for block {expected}, got block {got}")]
    WrongKey { expected: BlockKey, got: BlockKey },
    #[error("block {key} holds {got} voxels, the manifest says {expected}")]
    WrongCount { key: BlockKey, expected: u32, got: u32 },
    #[error("block {key}: the {bytes} bytes fetched have hash {got}, the hierarchy says {expected}")]
    WrongHash { key: BlockKey, bytes: usize, got: String, expected: String },
}

/// Decodes the bytes fetched for `key`, checking them against its manifest entry.
pub fn decode_fetched(key: BlockKey, entry: Option<&BlockEntry>, bytes: &[u8]) -> Result<Block, DecodeError> {
    decode_checked(key, entry.map(|e| e.voxels), entry.map(|e| e.hash.as_str()), bytes)
}

/// [`decode_fetched`] given only the voxel count and hash the hierarchy states (what a worker
/// knows); `None` where it states none.
pub fn decode_checked(
    key: BlockKey,
    voxels: Option<u32>,
    hash: Option<&str>,
    bytes: &[u8],
) -> Result<Block, DecodeError> {
    if let Some(expected) = hash {
        let got = voxstream_format::hierarchy::content_hash(bytes);
        if got != expected {
            return Err(DecodeError::WrongHash {
                key,
                bytes: bytes.len(),
                got,
                expected: expected.to_string(),
            });
        }
    }
    let block = decode_block(bytes).map_err(|source| DecodeError::Codec { key, source })?;
    if block.key != key {
        return Err(DecodeError::WrongKey { expected: key, got: block.key });
    }
    if let Some(expected) = voxels {
        let got = block.voxels.len() as u32;
        if got != expected {
            return Err(DecodeError::WrongCount { key, expected, got });
        }
    }
    Ok(block)
}

/// A decoded block with what the main thread needs from its voxels, worked
/// out where it was decoded (a worker, in the browser): the faces it expands
/// to and its occupied cells. The main thread then never walks the voxels.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedBlock {
    pub block: Block,
    pub faces: u32,
    pub cells: OccupiedCells,
}

impl DecodedBlock {
    /// Bytes after the voxels in a worker's answer: the cells, then the face count (u32 LE).
    pub const TRAILER_BYTES: usize = OccupiedCells::BYTES + 4;

    pub fn new(block: Block) -> Self {
        Self { faces: block.face_count(), cells: OccupiedCells::new(&block), block }
    }

    /// A worker's answer: the voxels as PackedVoxel bytes, then [`Self::TRAILER_BYTES`].
    pub fn to_message(&self) -> Vec<u8> {
        let voxels: &[u8] = bytemuck::cast_slice(&self.block.voxels);
        let mut out = Vec::with_capacity(voxels.len() + Self::TRAILER_BYTES);
        out.extend_from_slice(voxels);
        out.extend_from_slice(&self.cells.to_bytes());
        out.extend_from_slice(&self.faces.to_le_bytes());
        out
    }

    /// Splits an answer of `len` bytes into voxel bytes and trailer; an error names what is wrong.
    pub fn message_voxels(key: BlockKey, len: usize) -> Result<usize, String> {
        let voxel_bytes = len.checked_sub(Self::TRAILER_BYTES).ok_or_else(|| {
            format!(
                "block {key}: the worker's answer has {len} bytes, under the {} of its trailer",
                Self::TRAILER_BYTES
            )
        })?;
        if voxel_bytes % size_of::<PackedVoxel>() != 0 {
            return Err(format!(
                "block {key}: the worker's answer has {voxel_bytes} voxel bytes, not whole voxels"
            ));
        }
        Ok(voxel_bytes / size_of::<PackedVoxel>())
    }

    /// The block from its voxels and the answer's trailer ([`Self::to_message`]).
    pub fn from_message(block: Block, trailer: &[u8]) -> Result<Self, String> {
        let key = block.key;
        let bad = || format!("block {key}: the worker's answer has a malformed trailer");
        if trailer.len() != Self::TRAILER_BYTES {
            return Err(bad());
        }
        let (cells, faces) = trailer.split_at(OccupiedCells::BYTES);
        let cells = OccupiedCells::from_bytes(key, cells).ok_or_else(bad)?;
        let faces = u32::from_le_bytes(faces.try_into().map_err(|_| bad())?);
        Ok(Self { block, faces, cells })
    }

    /// [`Self::from_message`] from the whole answer held in `bytes`.
    #[cfg(test)]
    fn from_message_bytes(key: BlockKey, bytes: &[u8]) -> Result<Self, String> {
        let n = Self::message_voxels(key, bytes.len())?;
        let (voxels, trailer) = bytes.split_at(n * size_of::<PackedVoxel>());
        let voxels =
            voxels.chunks_exact(size_of::<PackedVoxel>()).map(bytemuck::pod_read_unaligned).collect();
        Self::from_message(Block { key, voxels }, trailer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxstream_format::{PackedVoxel, VoxelBounds, encode_block};

    fn sample() -> (Block, BlockEntry) {
        let key = BlockKey::new(1, 0, 1, 0);
        let block = Block { key, voxels: vec![PackedVoxel::new([1, 2, 3], 0b11, 0)] };
        let entry = BlockEntry {
            key,
            hash: voxstream_format::hierarchy::content_hash(&encode_block(&block)),
            bounds: VoxelBounds { min: [1, 66, 3], max: [2, 67, 4] },
            voxels: 1,
            faces: 2,
            bytes: 0,
            geometric_error: 1.0,
            child_mask: 0,
            location: Default::default(),
        };
        (block, entry)
    }

    #[test]
    fn good_bytes_decode() {
        let (block, entry) = sample();
        assert_eq!(decode_fetched(block.key, Some(&entry), &encode_block(&block)), Ok(block));
    }

    #[test]
    fn wrong_key_count_and_garbage_are_errors() {
        let (block, mut entry) = sample();
        let bytes = encode_block(&block);
        let other = BlockKey::new(0, 0, 0, 0);
        assert!(matches!(decode_fetched(other, None, &bytes), Err(DecodeError::WrongKey { .. })));
        // The wrong slice of a pack (one byte short) fails its hash before decoding.
        assert!(matches!(
            decode_fetched(block.key, Some(&entry), &bytes[..bytes.len() - 1]),
            Err(DecodeError::WrongHash { .. })
        ));
        entry.hash = voxstream_format::hierarchy::content_hash(&bytes);
        entry.voxels = 7;
        assert!(matches!(
            decode_fetched(block.key, Some(&entry), &bytes),
            Err(DecodeError::WrongCount { .. })
        ));
        let err = decode_fetched(block.key, None, b"<html>not found</html>").unwrap_err();
        assert!(err.to_string().contains("1-0-1-0"), "{err}");
    }

    /// What a worker sends is what the main thread would have computed itself.
    #[test]
    fn a_workers_answer_carries_the_blocks_faces_and_cells() {
        let key = BlockKey::new(1, 0, 1, 0);
        let voxels = (0..40u32).map(|i| PackedVoxel::new([i, 63 - i, i / 2], 0b10_0101, 0)).collect();
        let decoded = DecodedBlock::new(Block { key, voxels });
        assert_eq!(decoded.faces, 40 * 3);
        let message = decoded.to_message();
        assert_eq!(message.len(), 40 * 12 + DecodedBlock::TRAILER_BYTES);
        assert_eq!(DecodedBlock::from_message_bytes(key, &message), Ok(decoded.clone()));
        // Control: a cut or padded answer is an error that names the block, never a panic.
        for bad in [&message[..message.len() - 1], &message[..10]] {
            let err = DecodedBlock::from_message_bytes(key, bad).unwrap_err();
            assert!(err.contains("1-0-1-0"), "{err}");
        }
        let other = DecodedBlock::new(Block { key, voxels: vec![PackedVoxel::new([5, 5, 5], 1, 0)] });
        assert_ne!(DecodedBlock::from_message_bytes(key, &other.to_message()), Ok(decoded));
    }
}
