//! decode → the CPU cache: fetched pages into the index, fetched or worker-decoded blocks
//! into the decoded cache (failures recorded, never asked for again), and the cache trimmed
//! to its byte cap, least recently needed first.

use voxstream_format::{BlockKey, HierarchyPage, PageRef};

use super::{CachedBlock, Scene};
use crate::decode::{DecodedBlock, decode_fetched};
use crate::fetch::FetchError;
use crate::request::Request;

/// Decoded blocks kept on the CPU (voxel bytes), so a block evicted from the
/// GPU comes back without a refetch.
const DECODED_CACHE_BYTES: u64 = 256 << 20;

impl Scene {
    /// Takes a fetched page. A page that fails is not asked for again; the
    /// blocks above it stay drawn as they are.
    pub fn insert_page(&mut self, page: &PageRef, result: Result<Vec<u8>, FetchError>) {
        self.requests.finished(&Request::Page(page.clone()));
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
        // An answer for a page loaded meanwhile (or aborted and answered anyway).
        if !self.index.missing_pages().any(|p| p.root == page.root) {
            return;
        }
        let outcome = result.map_err(|e| e.to_string()).and_then(|bytes| {
            self.stats.bytes_fetched += bytes.len() as u64;
            let decoded = HierarchyPage::decode(&bytes, page).map_err(|e| e.to_string())?;
            self.index.insert_page(decoded).map_err(|e| e.to_string())
        });
        match outcome {
            Ok(()) => self.stats.pages_loaded += 1,
            Err(e) => {
                self.stats.record_error(format!("hierarchy page {}: {e}", page.root));
                self.failed_pages.insert(page.root, e);
            }
        }
        // No replan here: a loaded or failed page changes what `update_traversal` keys on
        // (`pages_loaded`, `failed_pages`), so the next read of the plan traverses again and
        // replans then, with the new entries.
    }

    pub fn record_bytes_fetched(&mut self, bytes: u64) {
        self.stats.bytes_fetched += bytes;
    }

    /// Takes fetched block bytes: decodes them and keeps them for upload.
    /// Failures are recorded (stats) and the block is not asked for again;
    /// its ancestor keeps standing in for it.
    pub fn insert_fetched(
        &mut self,
        results: impl IntoIterator<Item = (BlockKey, Result<Vec<u8>, FetchError>)>,
    ) {
        for (key, result) in results {
            self.requests.finished(&Request::Block(key));
            let bytes = match result {
                Ok(bytes) => bytes,
                Err(e) => {
                    self.fail(key, e.to_string());
                    continue;
                }
            };
            self.stats.bytes_fetched += bytes.len() as u64;
            match decode_fetched(key, self.index.block(&key), &bytes) {
                Ok(block) => self.insert_decoded(DecodedBlock::new(block)),
                Err(e) => self.fail(key, e.to_string()),
            }
        }
        // No replan: an arrival settles a request the queue no longer holds (it left the queue
        // when it started), and what is needed has not changed.
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
    }

    /// Takes a worker's answer for block `key`: `fetched` response bytes and
    /// the decoded block, or why it failed for good.
    pub fn insert_worker_result(&mut self, key: BlockKey, fetched: u64, block: Result<DecodedBlock, String>) {
        self.requests.finished(&Request::Block(key));
        self.stats.bytes_fetched += fetched;
        match block {
            Ok(decoded) if decoded.block.key == key => self.insert_decoded(decoded),
            Ok(decoded) => self.fail(key, format!("asked for block {key}, got block {}", decoded.block.key)),
            Err(e) => self.fail(key, e),
        }
        // No replan: an arrival settles a request the queue no longer holds (it left the queue
        // when it started), and what is needed has not changed.
        self.stats.requests_in_flight = self.requests.in_flight() as u32;
    }

    /// Takes a decoded block.
    pub fn insert_decoded(&mut self, decoded: DecodedBlock) {
        let DecodedBlock { block, faces, cells } = decoded;
        let key = block.key;
        self.stats.blocks_loaded += 1;
        if faces == 0 {
            self.empty.insert(key);
            return;
        }
        self.decoded_bytes += std::mem::size_of_val(block.voxels.as_slice()) as u64;
        let cached = CachedBlock { block, faces, cells, needed_frame: self.frame_counter };
        if let Some(old) = self.decoded.insert(key, cached) {
            self.decoded_bytes -= std::mem::size_of_val(old.block.voxels.as_slice()) as u64;
        }
    }

    pub(super) fn fail(&mut self, key: BlockKey, message: String) {
        self.stats.record_error(message);
        self.stats.blocks_failed += 1;
        self.failed.insert(key, self.stats.last_error.clone().unwrap_or_default());
    }

    pub fn failures(&self) -> impl Iterator<Item = (&BlockKey, &String)> {
        self.failed.iter()
    }

    /// Drops decoded CPU copies beyond [`DECODED_CACHE_BYTES`], least recently
    /// needed first, never one on the GPU or needed now.
    pub(super) fn trim_decoded(&mut self) {
        if self.decoded_bytes <= DECODED_CACHE_BYTES {
            return;
        }
        let mut victims: Vec<(u64, BlockKey)> = self
            .decoded
            .iter()
            .filter(|(k, _)| !self.gpu.contains_key(k) && !self.traversal.priority.contains_key(k))
            .map(|(k, c)| (c.needed_frame, *k))
            .collect();
        victims.sort();
        for (_, key) in victims {
            if self.decoded_bytes <= DECODED_CACHE_BYTES {
                break;
            }
            if let Some(c) = self.decoded.remove(&key) {
                self.decoded_bytes -= std::mem::size_of_val(c.block.voxels.as_slice()) as u64;
            }
        }
    }
}
