//! Scenes in a bucket (S3-compatible object storage, through `object_store`), as a replica reads
//! them: `<prefix>/<id>/manifest.json` (the scene's one mutable object, written last by a build),
//! `<prefix>/<id>/pages/<key>.<blake3>.vxh` and `<prefix>/<id>/packs/<blake3>.vxp`. Pages and packs
//! are content-addressed, so replacing a scene never overwrites an object that a reader of the
//! previous manifest still needs.
//!
//! Every page and block read goes through one bounded in-process cache ([`moka`], weighed in
//! bytes), keyed by content hash: a block is one ranged GET of its pack (`get_range`), checked
//! against its hash before it is cached, so the cache only ever holds verified bytes.

use axum::body::Bytes;
use futures_util::StreamExt;
use object_store::ObjectStore;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use voxstream_format::hierarchy::{HierarchyPage, PackRange, content_hash, pack_path};
use voxstream_format::{BlockEntry, BlockKey, Manifest, PageRef, SceneIndex};

use crate::objstore::Bucket;
use crate::store::{BlockReadError, StoreError, validate_id};

/// Pages fetched at once while a scene's hierarchy is loaded.
const PAGE_FETCHES: usize = 8;

/// Listing-and-deleting passes of [`BucketStore::purge_scene`] (waits 100, 200, 400 ms between).
const PURGE_PASSES: u32 = 4;

/// The bucket-side name of a hierarchy page: content-addressed, unlike the local `pages/<key>.vxh`
/// (a local scene is replaced by one directory rename; a bucket scene object by object).
pub fn bucket_page_path(root: &BlockKey, hash: &str) -> String {
    format!("pages/{root}.{hash}.vxh")
}

/// What the cache holds, by content hash (the same bytes under any scene share one entry).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
enum CacheKey {
    Page(String),
    Block(String),
}

impl CacheKey {
    fn kind(&self) -> &'static str {
        match self {
            CacheKey::Page(_) => "page",
            CacheKey::Block(_) => "block",
        }
    }
}

type Labels = Vec<(String, String)>;

/// The cache's counters, registered in the server's metrics.
#[derive(Clone, Default)]
pub struct CacheMetrics {
    /// By kind (page, block).
    pub hits: Family<Labels, Counter>,
    pub misses: Family<Labels, Counter>,
    /// The cache's bound and what it holds now, in bytes.
    pub capacity_bytes: Gauge,
    pub cached_bytes: Gauge,
}

impl CacheMetrics {
    fn count(&self, key: &CacheKey, hit: bool) {
        let labels = vec![("kind".to_string(), key.kind().to_string())];
        let family = if hit { &self.hits } else { &self.misses };
        family.get_or_create(&labels).inc();
    }
}

/// A bucket's scenes and the replica's cache of their hot pages and blocks.
pub struct BucketStore {
    pub bucket: Bucket,
    cache: moka::future::Cache<CacheKey, Bytes>,
    pub metrics: CacheMetrics,
}

/// An object under the prefix, as a listing gives it.
#[derive(Debug, Clone)]
pub struct ObjectInfo {
    /// The path relative to the prefix (`<id>/packs/<hash>.vxp`).
    pub rel: String,
    pub size: u64,
    /// Last modified, unix milliseconds (the server's clock).
    pub modified_ms: i64,
}

/// Why a bucket read failed: missing (404 from the bucket) or anything else.
#[derive(Debug, thiserror::Error)]
pub enum BucketReadError {
    #[error("{0} is not in the bucket")]
    Missing(String),
    #[error("{0}")]
    Failed(String),
}

impl BucketStore {
    /// A store over `bucket` whose cache holds at most `cache_bytes` (each entry weighs its bytes).
    pub fn new(bucket: Bucket, cache_bytes: u64) -> Self {
        let metrics = CacheMetrics::default();
        metrics.capacity_bytes.set(cache_bytes.min(i64::MAX as u64) as i64);
        let cache = moka::future::Cache::builder()
            .max_capacity(cache_bytes)
            .weigher(|_k: &CacheKey, v: &Bytes| v.len().try_into().unwrap_or(u32::MAX))
            .build();
        Self { bucket, cache, metrics }
    }

    /// `s3://bucket/prefix`, for messages.
    pub fn url(&self) -> String {
        if self.bucket.prefix.is_empty() {
            format!("s3://{}", self.bucket.bucket)
        } else {
            format!("s3://{}/{}", self.bucket.bucket, self.bucket.prefix)
        }
    }

    fn describe(&self, rel: &str) -> String {
        format!("s3://{}/{} at {}", self.bucket.bucket, self.bucket.path(rel), self.bucket.endpoint)
    }

    fn failed(&self, rel: &str, e: object_store::Error) -> BucketReadError {
        match e {
            object_store::Error::NotFound { .. } => BucketReadError::Missing(self.describe(rel)),
            e => BucketReadError::Failed(format!("reading {}: {e}", self.describe(rel))),
        }
    }

    /// The scene ids under the prefix (folders named like a scene id), sorted. Whether each has a
    /// manifest yet is for [`BucketStore::manifest`] to say.
    pub async fn list_ids(&self) -> Result<Vec<String>, String> {
        let prefix = (!self.bucket.prefix.is_empty())
            .then(|| object_store::path::Path::from(self.bucket.prefix.as_str()));
        let listing = self
            .bucket
            .store
            .list_with_delimiter(prefix.as_ref())
            .await
            .map_err(|e| format!("listing {} at {}: {e}", self.url(), self.bucket.endpoint))?;
        let mut ids: Vec<String> = listing
            .common_prefixes
            .iter()
            .filter_map(|p| p.filename().map(str::to_string))
            .filter(|id| validate_id(id).is_ok())
            .collect();
        ids.sort();
        Ok(ids)
    }

    /// The manifest object of scene `id`, or `None` when it has none (never published, being
    /// published for the first time, or deleted).
    pub async fn manifest(&self, id: &str) -> Result<Option<Bytes>, String> {
        let rel = format!("{id}/manifest.json");
        match self.bucket.store.get(&self.bucket.path(&rel)).await {
            Ok(r) => match r.bytes().await {
                Ok(b) => Ok(Some(b)),
                Err(e) => Err(self.failed(&rel, e).to_string()),
            },
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.failed(&rel, e).to_string()),
        }
    }

    /// The manifest of scene `id` and when it was written (unix ms), or `None` when it has none.
    pub async fn manifest_with_time(&self, id: &str) -> Result<Option<(Bytes, i64)>, String> {
        let rel = format!("{id}/manifest.json");
        match self.bucket.store.get(&self.bucket.path(&rel)).await {
            Ok(r) => {
                let modified = r.meta.last_modified.timestamp_millis();
                match r.bytes().await {
                    Ok(b) => Ok(Some((b, modified))),
                    Err(e) => Err(self.failed(&rel, e).to_string()),
                }
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.failed(&rel, e).to_string()),
        }
    }

    /// A small object (`<id>/scene.json`), or `None` when absent.
    pub async fn optional(&self, rel: &str) -> Result<Option<Bytes>, String> {
        match self.get(rel).await {
            Ok(b) => Ok(Some(b)),
            Err(BucketReadError::Missing(_)) => Ok(None),
            Err(e) => Err(e.to_string()),
        }
    }

    /// Every object under `<prefix>/<rel_dir>/` (a whole path segment: `a` does not list `ab/`).
    pub async fn list_under(&self, rel_dir: &str) -> Result<Vec<ObjectInfo>, String> {
        let dir = self.bucket.path(rel_dir.trim_end_matches('/'));
        let strip =
            if self.bucket.prefix.is_empty() { String::new() } else { format!("{}/", self.bucket.prefix) };
        let mut listing = self.bucket.store.list(Some(&dir));
        let mut out = Vec::new();
        while let Some(item) = listing.next().await {
            let meta = item.map_err(|e| format!("listing {}: {e}", self.describe(rel_dir)))?;
            let full = meta.location.to_string();
            let rel = full.strip_prefix(&strip).unwrap_or(&full).to_string();
            out.push(ObjectInfo { rel, size: meta.size, modified_ms: meta.last_modified.timestamp_millis() });
        }
        Ok(out)
    }

    /// Deletes one object (absent already is fine).
    pub async fn delete(&self, rel: &str) -> Result<(), String> {
        match self.bucket.store.delete(&self.bucket.path(rel)).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(format!("deleting {}: {e}", self.describe(rel))),
        }
    }

    /// Deletes `objects`, [`PAGE_FETCHES`] at once; returns how many and their bytes, or the first
    /// error (after trying every object).
    pub async fn delete_all(&self, objects: &[ObjectInfo]) -> Result<(u64, u64), String> {
        // Owned items: a closure over borrowed ones makes the future's Send higher-ranked, which
        // rustc cannot prove inside a spawned task.
        let owned: Vec<(String, u64)> = objects.iter().map(|o| (o.rel.clone(), o.size)).collect();
        let results: Vec<_> = futures_util::stream::iter(owned)
            .map(|(rel, size)| async move { self.delete(&rel).await.map(|()| size) })
            .buffer_unordered(PAGE_FETCHES)
            .collect()
            .await;
        let (mut n, mut bytes, mut first_error) = (0, 0, None);
        for r in results {
            match r {
                Ok(size) => {
                    n += 1;
                    bytes += size;
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
        match first_error {
            Some(e) => Err(e),
            None => Ok((n, bytes)),
        }
    }

    /// Deletes every object under `<id>/` once the scene's manifest is gone: `listed` first, then
    /// whatever a fresh listing still shows, for up to [`PURGE_PASSES`] passes. A listing taken right
    /// after a build's last writes can miss an object (seen with Garage on a loaded machine), and a
    /// delete can fail transiently; either would leave garbage that only the collector removes an
    /// hour later. Returns how many objects and bytes went, or the last error with what remains.
    pub async fn purge_scene(&self, id: &str, listed: &[ObjectInfo]) -> Result<(u64, u64), String> {
        let (mut n, mut bytes, mut last_error) = (0, 0, None);
        let mut pending = listed.to_vec();
        for pass in 0..PURGE_PASSES {
            if pass > 0 {
                tokio::time::sleep(std::time::Duration::from_millis(50 << pass)).await;
            }
            if !pending.is_empty() {
                match self.delete_all(&pending).await {
                    Ok((k, b)) => {
                        n += k;
                        bytes += b;
                    }
                    Err(e) => last_error = Some(e),
                }
            }
            pending = self.list_under(id).await?;
            if pending.is_empty() {
                return Ok((n, bytes));
            }
            tracing::info!(scene = %id, pass, left = pending.len(), "objects remain after deleting; listing again");
        }
        let left = pending.len();
        Err(match last_error {
            Some(e) => format!("{e}; {left} objects remain under {id}/"),
            None => format!("{left} objects remain under {id}/ after {PURGE_PASSES} passes"),
        })
    }

    /// A server-side copy (S3 CopyObject): the bytes never pass through this process.
    pub async fn copy(&self, from: &str, to: &str) -> Result<(), String> {
        self.bucket
            .store
            .copy(&self.bucket.path(from), &self.bucket.path(to))
            .await
            .map_err(|e| format!("copying {} to {}: {e}", self.describe(from), self.describe(to)))
    }

    /// Reads every hierarchy page of a scene (several at once, through the cache), checking
    /// each as the local store does, so a listed scene's hierarchy is whole.
    pub async fn load_index(&self, id: &str, manifest: &Manifest) -> Result<SceneIndex, StoreError> {
        let damaged = |message: String| StoreError::Damaged { id: id.to_string(), message };
        let mut index = SceneIndex::new(manifest);
        loop {
            let wanted: Vec<(PageRef, Option<PackRange>)> =
                index.missing_pages().map(|r| (r.clone(), index.page_range(&r.root))).collect();
            if wanted.is_empty() {
                break;
            }
            let pages: Vec<_> = futures_util::stream::iter(wanted)
                .map(|(r, range)| async move {
                    let bytes = self.page(id, &r, range).await;
                    (r, bytes)
                })
                .buffer_unordered(PAGE_FETCHES)
                .collect()
                .await;
            for (r, bytes) in pages {
                let bytes = bytes.map_err(|e| damaged(format!("hierarchy page {}: {e}", r.root)))?;
                let page = HierarchyPage::decode(&bytes, &r)
                    .map_err(|e| damaged(format!("hierarchy page {}: {e}", r.root)))?;
                index.insert_page(page).map_err(|e| damaged(format!("hierarchy page {}: {e}", r.root)))?;
            }
        }
        Ok(index)
    }

    /// A hierarchy page's bytes, checked against `hash` (a page named by a hash it does not have is
    /// missing: the scene was replaced).
    pub async fn page(
        &self,
        id: &str,
        page: &PageRef,
        range: Option<PackRange>,
    ) -> Result<Bytes, BucketReadError> {
        let hash = &page.hash;
        let key = CacheKey::Page(hash.to_string());
        if let Some(bytes) = self.cache.get(&key).await {
            self.metrics.count(&key, true);
            return Ok(bytes);
        }
        self.metrics.count(&key, false);
        let (rel, bytes) = match range {
            // Pages live in packs: one ranged GET, like a block.
            Some(r) => {
                let rel = format!("{id}/{}", pack_path(&r.pack.hash));
                let bytes = self
                    .bucket
                    .store
                    .get_range(&self.bucket.path(&rel), r.offset..r.end())
                    .await
                    .map_err(|e| self.failed(&rel, e))?;
                (rel, bytes)
            }
            None => {
                let rel = format!("{id}/{}", bucket_page_path(&page.root, hash));
                let bytes = self.get(&rel).await?;
                (rel, bytes)
            }
        };
        if content_hash(&bytes) != *hash {
            return Err(BucketReadError::Missing(format!("{} with hash {hash}", self.describe(&rel))));
        }
        self.insert(key, bytes.clone()).await;
        Ok(bytes)
    }

    /// A block's bytes: one ranged GET of its pack (or the whole object of a block stored as its
    /// own file), checked against the entry's hash before it is cached.
    /// `range` is where the block lies in its pack (`SceneIndex::pack_range`); `None` for a block
    /// stored as its own object.
    pub async fn block(
        &self,
        id: &str,
        range: Option<PackRange>,
        entry: &BlockEntry,
    ) -> Result<Bytes, BlockReadError> {
        let key = CacheKey::Block(entry.hash.clone());
        if let Some(bytes) = self.cache.get(&key).await {
            self.metrics.count(&key, true);
            return Ok(bytes);
        }
        self.metrics.count(&key, false);
        let unreadable = |detail: String| BlockReadError::Unreadable { key: entry.key, detail };
        let bytes = match range {
            None => self
                .get(&format!("{id}/blocks/{}.vxb", entry.key))
                .await
                .map_err(|e| unreadable(e.to_string()))?,
            Some(r) => {
                let rel = format!("{id}/{}", pack_path(&r.pack.hash));
                match self.bucket.store.get_range(&self.bucket.path(&rel), r.offset..r.end()).await {
                    Ok(bytes) => bytes,
                    // The scene was deleted, renamed, or replaced and collected since this replica
                    // listed it: a 404 that says to fetch the manifest again, as for changed bytes
                    // (until the next listing drops or reloads the scene).
                    Err(object_store::Error::NotFound { .. }) => {
                        return Err(BlockReadError::Changed { key: entry.key });
                    }
                    Err(e) => {
                        return Err(unreadable(format!(
                            "pack {}: bytes {}..{}: {}",
                            self.describe(&rel),
                            r.offset,
                            r.end(),
                            self.failed(&rel, e)
                        )));
                    }
                }
            }
        };
        if blake3::hash(&bytes).to_hex().as_str() != entry.hash {
            return Err(BlockReadError::Changed { key: entry.key });
        }
        self.insert(key, bytes.clone()).await;
        Ok(bytes)
    }

    async fn get(&self, rel: &str) -> Result<Bytes, BucketReadError> {
        let path = self.bucket.path(rel);
        let result = self.bucket.store.get(&path).await.map_err(|e| self.failed(rel, e))?;
        result.bytes().await.map_err(|e| self.failed(rel, e))
    }

    async fn insert(&self, key: CacheKey, bytes: Bytes) {
        self.cache.insert(key, bytes).await;
        self.metrics.cached_bytes.set(self.cache.weighted_size().min(i64::MAX as u64) as i64);
    }
}
