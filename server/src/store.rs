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
use voxstream_format::hierarchy::{PackRange, content_hash, pack_path, page_path};
use voxstream_format::{BlockEntry, BlockKey, Manifest, SceneIndex, load_scene_index};

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

/// A published scene, as the server reads it: the manifest and every page,
/// checked when opened, so a listed scene's hierarchy is complete.
#[derive(Debug, Clone)]
pub struct StoredScene {
    pub id: String,
    pub files: SceneFiles,
    pub manifest: Manifest,
    pub index: std::sync::Arc<SceneIndex>,
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
                return handle.block_on(bucket.block(&self.id, &self.index, entry)).map(|b| b.to_vec());
            }
        };
        let bytes = match self.index.pack_range(&key) {
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
            SceneFiles::Bucket(bucket) => bucket.block(&self.id, &self.index, entry).await,
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
                futures_util::stream::iter(entries)
                    .map(|e| async move { bucket.block(&self.id, &self.index, &e).await })
                    .buffered(BUCKET_BATCH_FETCHES)
                    .try_collect()
                    .await
            }
        }
    }

    /// A hierarchy page's bytes if they are the ones `hash` names; `None` when the scene has no such
    /// page (any more).
    pub async fn read_page(&self, root: &BlockKey, hash: &str) -> Result<Option<Bytes>, String> {
        match &self.files {
            SceneFiles::Dir(dir) => {
                let (dir, root, range) =
                    (dir.clone(), *root, self.index.loaded_page(root).and_then(|(_, r)| r));
                let bytes = tokio::task::spawn_blocking(move || match range {
                    Some(range) => read_pack_range(&dir, &range),
                    None => fs::read(dir.join(page_path(&root))),
                })
                .await
                .map_err(|e| e.to_string())?
                .ok();
                // Checked on every read, as blocks are: a replaced scene must not answer an old URL
                // with new bytes.
                Ok(bytes.filter(|b| content_hash(b) == hash).map(Bytes::from))
            }
            SceneFiles::Bucket(bucket) => {
                let Some((page, range)) = self.index.loaded_page(root).filter(|(p, _)| p.hash == hash) else {
                    return Ok(None);
                };
                match bucket.page(&self.id, page, range).await {
                    Ok(bytes) => Ok(Some(bytes)),
                    Err(BucketReadError::Missing(_)) => Ok(None),
                    Err(e) => Err(e.to_string()),
                }
            }
        }
    }

    /// Every block entry, sorted by key.
    pub fn blocks(&self) -> Vec<&BlockEntry> {
        let mut all: Vec<&BlockEntry> = self.index.blocks().collect();
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
    validate_id(id)?;
    let dir = store.join(id);
    let path = dir.join("manifest.json");
    let bytes = fs::read(&path).map_err(io("read", &path))?;
    let damaged = |message: String| StoreError::Damaged { id: id.to_string(), message };
    let manifest = Manifest::from_json(&bytes).map_err(|e| damaged(e.to_string()))?;
    let index = read_scene_index(&dir, &manifest).map_err(damaged)?;
    Ok(StoredScene {
        id: id.to_string(),
        files: SceneFiles::Dir(dir),
        manifest,
        index: std::sync::Arc::new(index),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
