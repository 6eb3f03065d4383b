//! The read side of the store: published scenes as the server lists and
//! serves them. Scenes are written by [`crate::pipeline::write`].
//!
//! Layout: `<store>/<id>/manifest.json`, `<store>/<id>/pages/<key>.vxh` and
//! `<store>/<id>/packs/<blake3>.vxp` (256 blocks a pack, a pack spanning
//! pages; each page lists the packs its blocks lie in; `blocks/<key>.vxb` for
//! a block stored as its own file); directories starting with `.` (temp, trash,
//! builds) are never listed.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::body::Bytes;
use futures_util::{StreamExt, TryStreamExt};
use voxstream_format::hierarchy::{HierarchyPage, PackRange, content_hash, pack_path, page_path};
use voxstream_format::{BlockEntry, BlockKey, Manifest, PageRef, SceneIndex, load_scene_index};

use crate::bucket_store::{BucketReadError, BucketStore};

/// Blocks of one batch request fetched from a bucket at once.
const BUCKET_BATCH_FETCHES: usize = 8;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    #[error(
        "scene id {0:?} is invalid: use 1–64 characters from a-z, 0-9, '-' and '_', not starting with '-' or '_'"
    )]
    BadId(String),
    #[error("scene {id} is damaged: {message}")]
    Damaged { id: String, message: String },
    /// Part of the scene vanished under a reader that listed it: deleted, renamed or replaced.
    #[error("scene {id} changed since it was listed ({message}): fetch the manifest again")]
    Gone { id: String, message: String },
}

pub(crate) fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io { action, path: path.to_path_buf(), source }
}

/// Scene ids are safe path components and URL segments by construction.
pub fn validate_id(id: &str) -> Result<(), StoreError> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
        && !id.starts_with(['-', '_']);
    if ok { Ok(()) } else { Err(StoreError::BadId(id.to_string())) }
}

/// Derives a valid id from a file name: `Koala Scan.OBJ` → `koala-scan`.
pub fn id_from_file_stem(path: &Path) -> String {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let mut id: String = stem
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '_' { c.to_ascii_lowercase() } else { '-' })
        .collect();
    id = id.trim_matches(['-', '_']).chars().take(64).collect();
    if id.is_empty() { "scene".to_string() } else { id }
}

/// Why a block's bytes could not be read.
#[derive(Debug, thiserror::Error)]
pub enum BlockReadError {
    /// The file or pack holding it is missing, unreadable or too short: a damaged store.
    #[error("block {key} cannot be read: {detail}")]
    Unreadable { key: BlockKey, detail: String },
    /// Bytes were read but are not the ones the hierarchy's hash names.
    #[error("block {key}: its bytes differ from the hash in the hierarchy")]
    Changed { key: BlockKey },
}

/// Where a scene's pages and packs are.
#[derive(Clone)]
pub enum SceneFiles {
    /// `<store>/<id>`, a local folder.
    Dir(PathBuf),
    /// `<prefix>/<id>/` in a bucket, read through the replica's cache.
    Bucket(Arc<BucketStore>),
}

impl std::fmt::Debug for SceneFiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SceneFiles::Dir(dir) => write!(f, "Dir({})", dir.display()),
            SceneFiles::Bucket(b) => write!(f, "Bucket({})", b.url()),
        }
    }
}

/// A published scene, as the server reads it: its manifest, and its hierarchy as far as it has
/// been read ([`PagedIndex`]).
#[derive(Debug, Clone)]
pub struct StoredScene {
    pub id: String,
    pub files: SceneFiles,
    pub manifest: Manifest,
    pub index: Arc<PagedIndex>,
}

/// A scene's hierarchy as far as it has been read. [`open_scene`] reads every page (the CLI,
/// publish and thumbnails of old scenes want them all); a server lists a scene from its
/// manifest alone and reads the pages on a block's path when the block is first asked for
/// ([`StoredScene::entry`]), so listing a scene of millions of blocks costs one object, and a
/// lookup at most one page per page layer.
#[derive(Debug)]
pub struct PagedIndex(std::sync::RwLock<SceneIndex>);

impl PagedIndex {
    pub fn new(index: SceneIndex) -> Self {
        Self(std::sync::RwLock::new(index))
    }

    /// What is loaded so far. Never held across an await.
    pub fn read(&self) -> std::sync::RwLockReadGuard<'_, SceneIndex> {
        self.0.read().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, SceneIndex> {
        self.0.write().unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

impl StoredScene {
    /// The scene's folder in a local store; `None` in a bucket.
    pub fn local_dir(&self) -> Option<&Path> {
        match &self.files {
            SceneFiles::Dir(dir) => Some(dir),
            SceneFiles::Bucket(_) => None,
        }
    }

    /// The scene's folder in a local store. Panics for a bucket scene: for the CLI and tests,
    /// which open local stores only.
    pub fn dir(&self) -> &Path {
        self.local_dir().expect("a scene of a local store")
    }

    /// The own file of a block stored unpacked (older builds).
    pub fn block_path(&self, key: &BlockKey) -> PathBuf {
        self.dir().join("blocks").join(format!("{key}.vxb"))
    }

    pub fn pack_path(&self, hash: &str) -> PathBuf {
        self.dir().join(pack_path(hash))
    }

    /// Reads a block's bytes (one positioned read from its pack, or its own
    /// file) and checks them against the entry's hash. Blocking: on a bucket
    /// scene it waits for the runtime, so call it from a blocking thread
    /// (`spawn_blocking`), never from async code. Errors name the file
    /// relative to the scene directory.
    pub fn read_block(&self, entry: &BlockEntry) -> Result<Vec<u8>, BlockReadError> {
        let key = entry.key;
        let unreadable = |detail: String| BlockReadError::Unreadable { key, detail };
        let dir = match &self.files {
            SceneFiles::Dir(dir) => dir,
            SceneFiles::Bucket(bucket) => {
                let handle = tokio::runtime::Handle::try_current()
                    .map_err(|_| unreadable("a bucket scene is read inside the server's runtime".into()))?;
                let range = self.index.read().pack_range(&key);
                return handle.block_on(bucket.block(&self.id, range, entry)).map(|b| b.to_vec());
            }
        };
        let range = self.index.read().pack_range(&key);
        let bytes = match range {
            None => {
                let rel = format!("blocks/{key}.vxb");
                fs::read(dir.join(&rel)).map_err(|e| unreadable(format!("{rel}: {e}")))?
            }
            Some(r) => {
                let rel = pack_path(&r.pack.hash);
                let file =
                    fs::File::open(dir.join(&rel)).map_err(|e| unreadable(format!("pack {rel}: {e}")))?;
                let mut bytes = vec![0u8; r.bytes as usize];
                if let Err(e) = read_exact_at(&file, &mut bytes, r.offset) {
                    return Err(unreadable(match file.metadata().map(|m| m.len()) {
                        Ok(len) if len < r.end() => format!(
                            "pack {rel} is truncated: {len} bytes, the block lies at bytes {}..{} (the page names {} bytes)",
                            r.offset,
                            r.end(),
                            r.pack.bytes
                        ),
                        _ => format!("pack {rel}: {e}"),
                    }));
                }
                bytes
            }
        };
        if blake3::hash(&bytes).to_hex().as_str() != entry.hash {
            return Err(BlockReadError::Changed { key });
        }
        Ok(bytes)
    }

    pub fn page_path(&self, root: &BlockKey) -> PathBuf {
        self.dir().join(page_path(root))
    }

    /// [`StoredScene::read_block`] from async code: a blocking read of a local pack on
    /// tokio's blocking pool, or the bucket's cache and one ranged GET.
    pub async fn read_block_async(&self, entry: &BlockEntry) -> Result<Bytes, BlockReadError> {
        match &self.files {
            SceneFiles::Dir(_) => {
                let (scene, e) = (self.clone(), entry.clone());
                tokio::task::spawn_blocking(move || scene.read_block(&e).map(Bytes::from))
                    .await
                    .unwrap_or_else(|join| {
                        Err(BlockReadError::Unreadable { key: entry.key, detail: join.to_string() })
                    })
            }
            SceneFiles::Bucket(bucket) => {
                let range = self.index.read().pack_range(&entry.key);
                bucket.block(&self.id, range, entry).await
            }
        }
    }

    /// Several blocks in order: one blocking task for a local store, a few GETs at once from a
    /// bucket.
    pub async fn read_blocks(&self, entries: Vec<BlockEntry>) -> Result<Vec<Bytes>, BlockReadError> {
        match &self.files {
            SceneFiles::Dir(_) => {
                let scene = self.clone();
                let key = entries.first().map_or(self.manifest.root.key, |e| e.key);
                tokio::task::spawn_blocking(move || {
                    entries.iter().map(|e| scene.read_block(e).map(Bytes::from)).collect()
                })
                .await
                .unwrap_or_else(|join| Err(BlockReadError::Unreadable { key, detail: join.to_string() }))
            }
            SceneFiles::Bucket(bucket) => {
                let ranged: Vec<_> = {
                    let index = self.index.read();
                    entries.into_iter().map(|e| (index.pack_range(&e.key), e)).collect()
                };
                futures_util::stream::iter(ranged)
                    .map(|(range, e)| async move { bucket.block(&self.id, range, &e).await })
                    .buffered(BUCKET_BATCH_FETCHES)
                    .try_collect()
                    .await
            }
        }
    }

    /// A hierarchy page's bytes if they are the ones `hash` names; `None` when the scene has no such
    /// page (any more).
    pub async fn read_page(&self, root: &BlockKey, hash: &str) -> Result<Option<Bytes>, StoreError> {
        let Some((page, range)) = self.page_ref(root).await? else { return Ok(None) };
        if page.hash != hash {
            return Ok(None);
        }
        let failed = |message: String| StoreError::Damaged { id: self.id.clone(), message };
        match &self.files {
            SceneFiles::Dir(dir) => {
                let (dir, root) = (dir.clone(), *root);
                let bytes = tokio::task::spawn_blocking(move || read_page_bytes(&dir, &root, range.as_ref()))
                    .await
                    .map_err(|e| failed(e.to_string()))?
                    .ok();
                // Checked on every read, as blocks are: a replaced scene must not answer an old URL
                // with new bytes.
                Ok(bytes.filter(|b| content_hash(b) == hash).map(Bytes::from))
            }
            SceneFiles::Bucket(bucket) => match bucket.page(&self.id, &page, range).await {
                Ok(bytes) => Ok(Some(bytes)),
                Err(BucketReadError::Missing(_)) => Ok(None),
                Err(e) => Err(failed(format!("hierarchy page {root}: {e}"))),
            },
        }
    }

    /// `key`'s entry, reading the pages on its path first when they are not loaded yet; `None`
    /// when the scene has no such block.
    pub async fn entry(&self, key: &BlockKey) -> Result<Option<BlockEntry>, StoreError> {
        loop {
            let next = self.index.read().page_toward(key).cloned();
            let Some(page) = next else { return Ok(self.index.read().block(key).cloned()) };
            self.load_page(&page).await?;
        }
    }

    /// The page rooted at `root` (named by the page that lists `root`'s entry, read first when
    /// needed) and its range when it lies in a pack; `None` when the scene has no such page.
    pub async fn page_ref(
        &self,
        root: &BlockKey,
    ) -> Result<Option<(PageRef, Option<PackRange>)>, StoreError> {
        if self.entry(root).await?.is_none() {
            return Ok(None);
        }
        Ok(self.index.read().page(root).map(|(r, range)| (r.clone(), range)))
    }

    /// Reads every page that lists blocks of `level` or coarser, so that [`Self::blocks`] holds
    /// that level whole (a thumbnail reads one coarse level).
    pub async fn load_down_to(&self, level: u8) -> Result<(), StoreError> {
        loop {
            let next = self.index.read().missing_pages().find(|r| r.root.level > level).cloned();
            let Some(page) = next else { return Ok(()) };
            self.load_page(&page).await?;
        }
    }

    /// Reads, checks and adds one page the index names and has not loaded. Two lookups may read
    /// the same page at once; the second one's copy is dropped.
    async fn load_page(&self, page: &PageRef) -> Result<(), StoreError> {
        let root = page.root;
        let failed = |message: String| StoreError::Damaged { id: self.id.clone(), message };
        let range = self.index.read().page(&root).and_then(|(_, range)| range);
        let bytes: Bytes = match &self.files {
            SceneFiles::Dir(dir) => {
                let dir = dir.clone();
                tokio::task::spawn_blocking(move || read_page_bytes(&dir, &root, range.as_ref()))
                    .await
                    .map_err(|e| failed(e.to_string()))?
                    .map_err(|e| failed(format!("hierarchy page {root}: {e}")))?
                    .into()
            }
            SceneFiles::Bucket(bucket) => bucket.page(&self.id, page, range).await.map_err(|e| match e {
                // Deleted, renamed or replaced and collected since this replica listed it.
                BucketReadError::Missing(m) => StoreError::Gone { id: self.id.clone(), message: m },
                e => failed(format!("hierarchy page {root}: {e}")),
            })?,
        };
        let decoded =
            HierarchyPage::decode(&bytes, page).map_err(|e| failed(format!("hierarchy page {root}: {e}")))?;
        let mut index = self.index.write();
        if index.is_pending(&root) {
            index.insert_page(decoded).map_err(|e| failed(format!("hierarchy page {root}: {e}")))?;
        }
        Ok(())
    }

    /// Every block entry loaded so far, sorted by key: all of them for a scene from
    /// [`open_scene`].
    pub fn blocks(&self) -> Vec<BlockEntry> {
        let mut all: Vec<BlockEntry> = self.index.read().blocks().cloned().collect();
        all.sort_by_key(|b| b.key);
        all
    }
}

#[cfg(unix)]
fn read_exact_at(file: &fs::File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(not(unix))]
fn read_exact_at(mut file: &fs::File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    use std::io::{Read, Seek, SeekFrom};
    file.seek(SeekFrom::Start(offset))?;
    file.read_exact(buf)
}

/// Bytes `[offset, offset + bytes)` of a pack in the scene folder `dir`.
/// Errors name the pack, and say so when it is shorter than the range.
pub fn read_pack_range(dir: &Path, range: &PackRange) -> std::io::Result<Vec<u8>> {
    let rel = pack_path(&range.pack.hash);
    let named = |e: std::io::Error| std::io::Error::new(e.kind(), format!("pack {rel}: {e}"));
    let file = fs::File::open(dir.join(&rel)).map_err(named)?;
    let mut bytes = vec![0u8; range.bytes as usize];
    if let Err(e) = read_exact_at(&file, &mut bytes, range.offset) {
        return Err(match file.metadata().map(|m| m.len()) {
            Ok(len) if len < range.end() => std::io::Error::other(format!(
                "pack {rel} is truncated: {len} bytes, the range is bytes {}..{}",
                range.offset,
                range.end()
            )),
            _ => named(e),
        });
    }
    Ok(bytes)
}

/// A hierarchy page's bytes in the scene folder `dir`: its range of a pack, or its own file
/// (`pages/<root>.vxh`, older builds). Not checked against its hash here.
fn read_page_bytes(dir: &Path, root: &BlockKey, range: Option<&PackRange>) -> std::io::Result<Vec<u8>> {
    match range {
        Some(range) => read_pack_range(dir, range),
        None => fs::read(dir.join(page_path(root))),
    }
}

/// Reads every hierarchy page of the scene in `dir` (from its packs; older pages from files).
pub fn read_scene_index(dir: &Path, manifest: &Manifest) -> Result<SceneIndex, String> {
    load_scene_index(manifest, |r, range| match range {
        Some(range) => {
            let bytes = read_pack_range(dir, &range)?;
            if content_hash(&bytes) != r.hash {
                // Say which pack: the page's own hash error could not.
                return Err(std::io::Error::other(format!(
                    "page {} in pack {} does not match its hash",
                    r.root,
                    pack_path(&range.pack.hash)
                )));
            }
            Ok(bytes)
        }
        None => fs::read(dir.join(page_path(&r.root))),
    })
    .map_err(|e| e.to_string())
}

/// Lists the published scenes of a store, sorted by id. A missing store is empty.
pub fn list_scenes(store: &Path) -> Result<Vec<StoredScene>, StoreError> {
    let entries = match fs::read_dir(store) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io("list", store)(e)),
    };
    let mut scenes = Vec::new();
    for entry in entries {
        let entry = entry.map_err(io("list", store))?;
        let Some(id) = entry.file_name().to_str().map(str::to_string) else { continue };
        if validate_id(&id).is_err() || !entry.path().is_dir() {
            continue; // temp dirs, stray files
        }
        scenes.push(open_scene(store, &id)?);
    }
    scenes.sort_by(|a, b| a.id.cmp(&b.id));
    Ok(scenes)
}

pub fn open_scene(store: &Path, id: &str) -> Result<StoredScene, StoreError> {
    let (dir, manifest) = read_manifest(store, id)?;
    let index = read_scene_index(&dir, &manifest)
        .map_err(|message| StoreError::Damaged { id: id.to_string(), message })?;
    Ok(StoredScene {
        id: id.to_string(),
        files: SceneFiles::Dir(dir),
        manifest,
        index: Arc::new(PagedIndex::new(index)),
    })
}

/// A scene as a server lists it: from its manifest alone when the manifest states what a
/// listing shows (`bounds`, `page_bytes`), its pages read as lookups reach them; scenes built
/// before those fields are read whole, as [`open_scene`] does.
pub fn open_scene_listed(store: &Path, id: &str) -> Result<StoredScene, StoreError> {
    let (dir, manifest) = read_manifest(store, id)?;
    if !lists_from_manifest(&manifest) {
        return open_scene(store, id);
    }
    let index = Arc::new(PagedIndex::new(SceneIndex::new(&manifest)));
    Ok(StoredScene { id: id.to_string(), files: SceneFiles::Dir(dir), manifest, index })
}

/// Whether a listing needs nothing but the manifest (see [`open_scene_listed`]).
pub fn lists_from_manifest(manifest: &Manifest) -> bool {
    manifest.bounds.is_some() && manifest.page_bytes.is_some()
}

fn read_manifest(store: &Path, id: &str) -> Result<(PathBuf, Manifest), StoreError> {
    validate_id(id)?;
    let dir = store.join(id);
    let path = dir.join("manifest.json");
    let bytes = fs::read(&path).map_err(io("read", &path))?;
    let manifest = Manifest::from_json(&bytes)
        .map_err(|e| StoreError::Damaged { id: id.to_string(), message: e.to_string() })?;
    Ok((dir, manifest))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{BuildOptions, Resolution, build_scene};

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_listed_scene_reads_only_the_pages_a_lookup_needs() {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("store");
        let koala = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj");
        // 1024 = 16 blocks a side: levels 0–4, pages rooted on levels 4 and 1.
        let opts = BuildOptions { resolution: Resolution::Explicit(1024), ..Default::default() };
        let id = build_scene(&koala, &store, &opts).unwrap().id;
        let whole = open_scene(&store, &id).unwrap();
        let total = whole.index.read().pages_loaded();
        let all = whole.blocks();
        assert!(total > 2, "{total} pages");

        let listed = open_scene_listed(&store, &id).unwrap();
        assert_eq!(listed.index.read().pages_loaded(), 0, "a listing reads the manifest alone");
        let level0: Vec<&BlockEntry> = all.iter().filter(|e| e.key.level == 0).collect();
        let union = level0.iter().fold(level0[0].bounds, |mut b, e| {
            for a in 0..3 {
                b.min[a] = b.min[a].min(e.bounds.min[a]);
                b.max[a] = b.max[a].max(e.bounds.max[a]);
            }
            b
        });
        assert_eq!(listed.manifest.bounds, Some(union));
        assert_eq!(listed.manifest.page_bytes, Some(whole.index.read().page_bytes_loaded()));

        let deep = level0[level0.len() / 2];
        assert_eq!(listed.entry(&deep.key).await.unwrap().as_ref(), Some(deep));
        assert_eq!(listed.index.read().pages_loaded(), 2, "one page per page layer");
        assert_eq!(listed.read_block_async(deep).await.unwrap(), whole.read_block(deep).unwrap());
        let absent =
            (0..16).map(|x| BlockKey::new(0, x, 0, 15)).find(|k| whole.index.read().block(k).is_none());
        assert!(listed.entry(&absent.expect("a corner block the koala misses")).await.unwrap().is_none());
        for e in &all {
            assert_eq!(listed.entry(&e.key).await.unwrap().as_ref(), Some(e), "{}", e.key);
        }
        assert_eq!(listed.index.read().pages_loaded(), total);

        // A page URL resolves through the pages above it, and checks the hash.
        let fresh = open_scene_listed(&store, &id).unwrap();
        let (page, range) = whole
            .index
            .read()
            .loaded_pages()
            .find(|(r, _)| r.root.level == 1)
            .map(|(r, g)| (r.clone(), g))
            .unwrap();
        let bytes = fresh.read_page(&page.root, &page.hash).await.unwrap().unwrap();
        assert_eq!(content_hash(&bytes), page.hash);
        assert!(fresh.read_page(&page.root, &"0".repeat(64)).await.unwrap().is_none());

        // A damaged page is an error naming it, not a panic or a missing block.
        let range = range.unwrap();
        let pack = dir.path().join("store").join(&id).join(pack_path(&range.pack.hash));
        let mut packed = fs::read(&pack).unwrap();
        packed[range.offset as usize + 8] ^= 0xff;
        fs::write(&pack, packed).unwrap();
        let damaged = open_scene_listed(&store, &id).unwrap();
        let below = all.iter().find(|e| e.key.level == 0 && e.key.parent() == page.root).unwrap();
        let err = damaged.entry(&below.key).await.unwrap_err().to_string();
        assert!(err.contains(&format!("hierarchy page {}", page.root)), "{err}");

        // Control: a manifest from before `bounds` and `page_bytes` is listed whole.
        let path = store.join(&id).join("manifest.json");
        let mut older: serde_json::Value = serde_json::from_slice(&fs::read(&path).unwrap()).unwrap();
        older.as_object_mut().unwrap().retain(|k, _| k != "bounds" && k != "page_bytes");
        fs::write(&path, serde_json::to_vec(&older).unwrap()).unwrap();
        let err = open_scene_listed(&store, &id).unwrap_err().to_string();
        assert!(err.contains("hierarchy page"), "read whole, the damaged page fails the listing: {err}");
    }

    #[test]
    fn ids() {
        assert_eq!(id_from_file_stem(Path::new("/x/Koala Scan.OBJ")), "koala-scan");
        assert_eq!(id_from_file_stem(Path::new("..")), "scene");
        for good in ["koala", "a-1_b"] {
            assert!(validate_id(good).is_ok());
        }
        for bad in ["", "..", "a/b", "-x", "Koala", "a b", &"x".repeat(65)] {
            assert!(validate_id(bad).is_err(), "{bad:?}");
        }
    }
}
