//! Fetched bytes → a validated block. The format crate checks the bytes
//! themselves; this checks that they are the block we asked for and agree with
//! the manifest (its voxel count and content hash), so a misrouted or stale
//! response, or the wrong slice of a pack, can never be drawn in the wrong place.

use voxstream_format::{Block, BlockEntry, BlockKey, CodecError, decode_block};

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
}
