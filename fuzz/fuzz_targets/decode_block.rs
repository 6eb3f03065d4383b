#![no_main]
use voxstream_format::{decode_block, encode_block};

// decode_block promises: never panics, never allocates more than a full block, and what it
// accepts is sorted by Morton code with a face on every voxel; re-encoding it round-trips.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(block) = decode_block(data) {
        assert!(block.voxels.windows(2).all(|w| w[0].morton() < w[1].morton()), "not strictly Morton-sorted");
        assert!(block.voxels.iter().all(|v| v.faces() != 0), "a voxel without faces");
        assert_eq!(
            decode_block(&encode_block(&block)).as_ref(),
            Ok(&block),
            "re-encoding does not round-trip"
        );
    }
});
