//! The server's view of a store: published scenes held in memory (manifest and
//! metadata), renamed and deleted atomically on disk, refreshed when a build
//! publishes. A bucket's scenes are listed from the bucket and, on replicas with a
//! coordinator, renamed and deleted there under the coordinator's scene locks
//! ([`Catalog::rename_in_bucket`], [`Catalog::delete_in_bucket`]).
//!
//! Beside `manifest.json` a scene built by the server has `scene.json`
//! ([`BuildInfo`]: when and how long it was built, display name), written by
//! temp file + rename so it is either absent or whole.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use axum::body::Bytes;
use serde::{Deserialize, Serialize};
use voxstream_format::{Manifest, SceneIndex};

use futures_util::StreamExt;

use crate::bucket_store::BucketStore;
use crate::coordinator::Coordinator;
use crate::store::{self, PagedIndex, SceneFiles, StoreError, StoredScene};

pub const BUILD_INFO_FILE: &str = "scene.json";

/// Written beside the manifest by the server after a build, rewritten on rename.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct BuildInfo {
    /// Unix seconds when the build finished.
    #[serde(default)]
    pub built_at: Option<u64>,
    #[serde(default)]
    pub build_seconds: Option<f64>,
    /// Shown instead of the manifest's name when set.
    #[serde(default)]
    pub display_name: Option<String>,
}

/// A catalog row: what a scene is, where it came from and what it costs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SceneMeta {
    pub id: String,
    pub name: String,
    /// Input file name and format (obj, ply, stl, gltf, glb).
    pub source_file: String,
    pub source_format: String,
    pub triangles: u64,
    pub skipped_triangles: u64,
    /// Level-0 voxels stored.
    pub voxels: u64,
    pub blocks: u32,
    pub levels: u32,
    /// Level-0 voxels per grid edge.
    pub resolution: u32,
    /// Edge of a level-0 voxel in source units.
    pub voxel_size: f64,
    /// Tight bounds of the voxels in source coordinates.
    pub bounds_min: [f64; 3],
    pub bounds_max: [f64; 3],
    /// Source units when the input says (e.g. "m"); null when unknown.
    pub units: Option<String>,
    /// Unix seconds; null for scenes built by the CLI.
    pub built_at: Option<u64>,
    pub build_seconds: Option<f64>,
    /// Encoded block bytes (all levels).
    pub bytes: u64,
    /// Manifest, hierarchy pages and block files, in bytes.
    pub bytes_on_disk: u64,
    /// Manifest and hierarchy pages, bytes.
    pub hierarchy_bytes: u64,
    /// How the resolution was chosen.
    #[schema(value_type = Object)]
    pub resolution_choice: voxstream_format::ResolutionChoice,
}

pub struct LoadedScene {
    pub stored: StoredScene,
    pub manifest_json: Bytes,
    pub meta: SceneMeta,
}

impl LoadedScene {
    fn load(stored: StoredScene) -> LoadedScene {
        let info = stored.local_dir().map(read_build_info).unwrap_or_default();
        Self::load_with(stored, info)
    }

    /// A scene with its `scene.json` (a bucket scene's is `<id>/scene.json`, absent until renamed).
    fn load_with(stored: StoredScene, info: BuildInfo) -> LoadedScene {
        let manifest_json = Bytes::from(stored.manifest.to_json());
        let meta = scene_meta(&stored, &info, manifest_json.len() as u64);
        LoadedScene { stored, manifest_json, meta }
    }
}

fn scene_meta(stored: &StoredScene, info: &BuildInfo, manifest_bytes: u64) -> SceneMeta {
    let (id, m) = (&stored.id, &stored.manifest);
    // Scenes built before the manifest stated these were read whole when listed.
    let (lo, hi) = match m.bounds {
        Some(b) => b.grid_units(0),
        None => {
            let index = stored.index.read();
            let level0 = index.blocks().filter(|b| b.key.level == 0).map(|b| b.bounds.grid_units(0));
            level0
                .reduce(|(lo, hi), (bmin, bmax)| {
                    (std::array::from_fn(|a| lo[a].min(bmin[a])), std::array::from_fn(|a| hi[a].max(bmax[a])))
                })
                .unwrap_or(([0.0; 3], [0.0; 3]))
        }
    };
    let page_bytes = m.page_bytes.unwrap_or_else(|| stored.index.read().page_bytes_loaded());
    let to_source = |g: [f64; 3]| std::array::from_fn(|a| m.grid.origin[a] + g[a] * m.grid.voxel_size);
    SceneMeta {
        id: id.to_string(),
        name: info.display_name.clone().unwrap_or_else(|| m.name.clone()),
        source_file: m.source.file.clone(),
        source_format: m.source.format.clone(),
        triangles: m.source.triangles,
        skipped_triangles: m.source.skipped_triangles,
        voxels: m.levels.first().map_or(0, |l| l.voxels),
        blocks: m.block_count() as u32,
        levels: m.levels.len() as u32,
        resolution_choice: m.resolution_choice.clone(),
        resolution: m.grid.resolution,
        voxel_size: m.grid.voxel_size,
        bounds_min: to_source(lo),
        bounds_max: to_source(hi),
        units: m.grid.units.clone(),
        built_at: info.built_at,
        build_seconds: info.build_seconds,
        bytes: m.levels.iter().map(|l| l.bytes).sum::<u64>(),
        hierarchy_bytes: manifest_bytes + page_bytes,
        bytes_on_disk: m.levels.iter().map(|l| l.bytes).sum::<u64>() + manifest_bytes + page_bytes,
    }
}

fn read_build_info(scene_dir: &Path) -> BuildInfo {
    fs::read(scene_dir.join(BUILD_INFO_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

/// Writes `scene.json` into a scene directory by temp file + rename.
pub fn write_build_info(scene_dir: &Path, info: &BuildInfo) -> std::io::Result<()> {
    let tmp = scene_dir.join(format!(".{BUILD_INFO_FILE}.tmp"));
    fs::write(&tmp, serde_json::to_vec_pretty(info).expect("build info serialises"))?;
    fs::File::open(&tmp)?.sync_all()?;
    fs::rename(&tmp, scene_dir.join(BUILD_INFO_FILE))
}

#[derive(Debug, thiserror::Error)]
pub enum CatalogError {
    #[error("no scene with id {0:?}")]
    NotFound(String),
    #[error("a scene with id {0:?} already exists")]
    Exists(String),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    #[error("{0} is served read-only: {hint}", hint = READ_ONLY_BUCKET_HINT)]
    ReadOnlyBucket(String),
    /// A build of the scene is queued or running, or another replica is editing or collecting it.
    #[error("{0}")]
    Busy(String),
    /// The coordinator could not be asked.
    #[error("{0}")]
    Unavailable(String),
    /// The bucket refused or failed a request.
    #[error("{0}")]
    Bucket(String),
}

impl From<crate::coordinator::SceneLockError> for CatalogError {
    fn from(e: crate::coordinator::SceneLockError) -> Self {
        use crate::coordinator::SceneLockError;
        match e {
            SceneLockError::Busy(_) | SceneLockError::Building(_) => CatalogError::Busy(e.to_string()),
            SceneLockError::Failed(_) => CatalogError::Unavailable(e.to_string()),
        }
    }
}

/// How scenes get into a bucket, for refusals of writes on a replica.
pub const READ_ONLY_BUCKET_HINT: &str = "this replica serves a bucket read-only: build with `voxstream build --out \
     s3://bucket/prefix`, or start the replicas with --coordinator to take uploads";

/// Where a catalog's scenes live.
#[derive(Clone)]
pub enum SceneStore {
    /// A folder: `<store>/<id>/`, renamed and deleted by this server.
    Local(PathBuf),
    /// `s3://bucket/prefix`: listed from the bucket (every replica lists the same scenes), read
    /// through a bounded cache; renamed and deleted only with a coordinator (fenced there).
    Bucket(Arc<BucketStore>),
}

impl std::fmt::Display for SceneStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SceneStore::Local(dir) => write!(f, "{}", dir.display()),
            SceneStore::Bucket(b) => write!(f, "{} at {}", b.url(), b.bucket.endpoint),
        }
    }
}

/// How long an id the bucket did not have is answered from memory before the bucket is asked again.
const UNKNOWN_ID_RECHECK: Duration = Duration::from_secs(2);

pub fn now_unix() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

fn nanos() -> u128 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos())
}

/// The published scenes of one store.
pub struct Catalog {
    /// The local store folder; for a bucket, the replica's own scratch folder (inputs assembled
    /// and built there before upload, with a coordinator).
    store: PathBuf,
    scenes_at: SceneStore,
    scenes: RwLock<BTreeMap<String, Arc<LoadedScene>>>,
    /// Serialises renames and deletes against each other.
    edits: Mutex<()>,
    /// Ids a bucket lookup recently did not find, so a stream of requests for an unknown id does
    /// not become a stream of bucket requests.
    unknown: moka::future::Cache<String, ()>,
    /// The manifest and `scene.json` bytes each bucket scene was loaded from, to tell a replaced
    /// (or renamed) scene on re-listing.
    manifests: Mutex<BTreeMap<String, (Bytes, Option<Bytes>)>>,
    /// Counts this replica's deletes and renames of bucket scenes.
    edits_made: AtomicU64,
    /// The count at which each id was last dropped by a delete or rename here: a bucket load that
    /// began before that read a manifest that is gone, and must not put the scene back.
    forgotten: Mutex<BTreeMap<String, u64>>,
}

/// What one read of a bucket scene found.
enum BucketRead {
    Missing,
    /// The manifest and `scene.json` this replica already serves.
    Unchanged,
    Loaded(SceneRead),
}

/// A scene read from the bucket, not yet served.
struct SceneRead {
    scene: Arc<LoadedScene>,
    seen: (Bytes, Option<Bytes>),
    /// [`Catalog::edits_made`] when the read began.
    edits_before: u64,
}

impl Catalog {
    /// Reads every published scene. A damaged scene stops start-up with its
    /// name rather than being served half-readable.
    pub fn open(store: &Path) -> Result<Catalog, StoreError> {
        let scenes = store::list_scenes(store)?
            .into_iter()
            .map(|s| (s.id.clone(), Arc::new(LoadedScene::load(s))))
            .collect();
        Ok(Self::with_scenes(store.to_path_buf(), SceneStore::Local(store.to_path_buf()), scenes))
    }

    fn with_scenes(
        store: PathBuf,
        scenes_at: SceneStore,
        scenes: BTreeMap<String, Arc<LoadedScene>>,
    ) -> Catalog {
        Catalog {
            store,
            scenes_at,
            scenes: RwLock::new(scenes),
            edits: Mutex::new(()),
            unknown: moka::future::Cache::builder()
                .max_capacity(10_000)
                .time_to_live(UNKNOWN_ID_RECHECK)
                .build(),
            manifests: Mutex::new(BTreeMap::new()),
            edits_made: AtomicU64::new(0),
            forgotten: Mutex::new(BTreeMap::new()),
        }
    }

    /// Lists the bucket's scenes and loads every one with a manifest. A listing that fails is an
    /// error (a replica must not start serving an empty catalog); a scene that cannot be loaded is
    /// skipped with its cause logged, so one damaged scene does not stop every replica.
    /// `state_dir` holds the replica's own state.
    pub async fn open_bucket(bucket: Arc<BucketStore>, state_dir: &Path) -> Result<Catalog, String> {
        let catalog = Self::with_scenes(state_dir.to_path_buf(), SceneStore::Bucket(bucket), BTreeMap::new());
        catalog.relist().await?;
        Ok(catalog)
    }

    /// Where the scenes live.
    pub fn scene_store(&self) -> &SceneStore {
        &self.scenes_at
    }

    /// The local folder of the store (for a bucket, the replica's own state folder).
    pub fn store(&self) -> &Path {
        &self.store
    }

    /// Re-reads a bucket's listing: loads new scenes and scenes whose manifest changed, drops
    /// scenes whose manifest is gone. A scene that fails to load keeps its previous version.
    /// Nothing to do for a local store (the server is its only writer). Returns the error of the
    /// listing itself.
    pub async fn relist(&self) -> Result<(), String> {
        let SceneStore::Bucket(bucket) = &self.scenes_at else { return Ok(()) };
        // What was served before the listing: only those entries can be dropped for missing from
        // it (a scene this replica publishes or renames to meanwhile is newer than the listing).
        let before = self.scenes.read().expect("catalog lock").clone();
        let ids = bucket.list_ids().await?;
        let mut seen = Vec::new();
        for id in ids {
            match self.load_from_bucket(bucket, &id).await {
                Ok(true) => seen.push(id),
                Ok(false) => {}
                Err(e) => {
                    tracing::error!(scene = %id, error = %e, "scene in the bucket cannot be served");
                    if self.get(&id).is_some() {
                        seen.push(id);
                    }
                }
            }
        }
        self.drop_unlisted(&before, &seen);
        Ok(())
    }

    /// Drops the scenes of `before` (what was served when a listing began) that the listing did
    /// not see, unless a newer load replaced them meanwhile.
    fn drop_unlisted(&self, before: &BTreeMap<String, Arc<LoadedScene>>, seen: &[String]) {
        let mut scenes = self.scenes.write().expect("catalog lock");
        for (id, old) in before.iter().filter(|(id, _)| !seen.contains(id)) {
            if scenes.get(id).is_some_and(|now| Arc::ptr_eq(now, old)) {
                tracing::info!(scene = %id, "scene no longer in the bucket");
                scenes.remove(id);
                self.manifests.lock().expect("manifest lock").remove(id);
            }
        }
    }

    /// Loads (or reloads) scene `id` from the bucket when its manifest differs from the one loaded.
    /// `Ok(false)`: the scene has no manifest, or a delete or rename here dropped it while it loaded.
    async fn load_from_bucket(&self, bucket: &Arc<BucketStore>, id: &str) -> Result<bool, String> {
        match self.read_from_bucket(bucket, id).await? {
            BucketRead::Missing => Ok(false),
            BucketRead::Unchanged => Ok(true),
            BucketRead::Loaded(read) => Ok(self.install(read)),
        }
    }

    /// Reads scene `id` from the bucket, noting how many edits this replica had made when it began.
    async fn read_from_bucket(&self, bucket: &Arc<BucketStore>, id: &str) -> Result<BucketRead, String> {
        let edits_before = self.edits_made.load(Ordering::SeqCst);
        let Some(bytes) = bucket.manifest(id).await? else { return Ok(BucketRead::Missing) };
        let info_bytes = bucket.optional(&format!("{id}/{BUILD_INFO_FILE}")).await?;
        let seen = (bytes.clone(), info_bytes.clone());
        if self.manifests.lock().expect("manifest lock").get(id) == Some(&seen) {
            return Ok(BucketRead::Unchanged);
        }
        // A damaged scene.json only loses the display name, as on a local store.
        let info: BuildInfo =
            info_bytes.as_deref().and_then(|b| serde_json::from_slice(b).ok()).unwrap_or_default();
        let manifest = Manifest::from_json(&bytes).map_err(|e| format!("scene {id} is damaged: {e}"))?;
        // Pages are read as lookups reach them, unless the listing itself needs them all.
        let index = if store::lists_from_manifest(&manifest) {
            SceneIndex::new(&manifest)
        } else {
            bucket.load_index(id, &manifest).await.map_err(|e| e.to_string())?
        };
        let stored = StoredScene {
            id: id.to_string(),
            files: SceneFiles::Bucket(bucket.clone()),
            manifest,
            index: Arc::new(PagedIndex::new(index)),
        };
        let scene = Arc::new(LoadedScene::load_with(stored, info));
        Ok(BucketRead::Loaded(SceneRead { scene, seen, edits_before }))
    }

    /// Serves what [`Catalog::read_from_bucket`] read, unless a delete or rename here dropped the
    /// id after the read began (its manifest may be gone already; the scene would come back).
    fn install(&self, read: SceneRead) -> bool {
        let id = read.scene.stored.id.clone();
        let mut scenes = self.scenes.write().expect("catalog lock");
        let dropped_since =
            self.forgotten.lock().expect("forgotten lock").get(&id).is_some_and(|&at| at > read.edits_before);
        if dropped_since {
            return false;
        }
        scenes.insert(id.clone(), read.scene);
        self.manifests.lock().expect("manifest lock").insert(id.clone(), read.seen);
        tracing::info!(scene = %id, "scene loaded from the bucket");
        true
    }

    /// Loads scene `id` from the bucket now (a build on this replica just published it).
    pub async fn reload(&self, id: &str) -> Result<bool, String> {
        let SceneStore::Bucket(bucket) = &self.scenes_at else { return Ok(false) };
        self.unknown.invalidate(id).await;
        self.load_from_bucket(bucket, id).await
    }

    /// A scene, asking the bucket for an id not listed yet (another replica's build may have
    /// published it since the last listing); unknown ids are remembered for a moment.
    pub async fn find(&self, id: &str) -> Option<Arc<LoadedScene>> {
        if let Some(scene) = self.get(id) {
            return Some(scene);
        }
        let SceneStore::Bucket(bucket) = &self.scenes_at else { return None };
        if self.unknown.contains_key(id) {
            return None;
        }
        match self.load_from_bucket(bucket, id).await {
            Ok(true) => self.get(id),
            Ok(false) => {
                self.unknown.insert(id.to_string(), ()).await;
                None
            }
            Err(e) => {
                tracing::warn!(scene = %id, error = %e, "scene in the bucket cannot be served");
                self.unknown.insert(id.to_string(), ()).await;
                None
            }
        }
    }

    pub fn list(&self) -> Vec<Arc<LoadedScene>> {
        self.scenes.read().expect("catalog lock").values().cloned().collect()
    }

    pub fn get(&self, id: &str) -> Option<Arc<LoadedScene>> {
        self.scenes.read().expect("catalog lock").get(id).cloned()
    }

    /// Whether this catalog still serves `scene` as it was when a request took it: the same
    /// entry, and for a local store the same manifest in its folder. A read that failed on a
    /// scene no longer served lost a race with a delete, rename or rebuild: the answer is the
    /// scene's absence (404), not a damaged store (500).
    pub fn still_serves(&self, scene: &Arc<LoadedScene>) -> bool {
        let same_entry = self.get(&scene.stored.id).is_some_and(|s| Arc::ptr_eq(&s, scene));
        same_entry
            && scene.stored.local_dir().is_none_or(|dir| {
                fs::read(dir.join("manifest.json"))
                    .ok()
                    .and_then(|bytes| Manifest::from_json(&bytes).ok())
                    .is_some_and(|m| m == scene.stored.manifest)
            })
    }

    pub fn contains(&self, id: &str) -> bool {
        self.scenes.read().expect("catalog lock").contains_key(id)
            || matches!(&self.scenes_at, SceneStore::Local(dir) if dir.join(id).exists())
    }

    /// Re-reads one scene from disk after a build published it.
    pub fn refresh(&self, id: &str) -> Result<Arc<LoadedScene>, StoreError> {
        if let SceneStore::Bucket(b) = &self.scenes_at {
            return Err(StoreError::Damaged {
                id: id.to_string(),
                message: format!("{} is served read-only", b.url()),
            });
        }
        let loaded = Arc::new(LoadedScene::load(store::open_scene_listed(&self.store, id)?));
        self.scenes.write().expect("catalog lock").insert(id.to_string(), loaded.clone());
        Ok(loaded)
    }

    /// Renames a scene's id (one directory rename) and/or sets its display name.
    pub fn rename(
        &self,
        id: &str,
        new_id: Option<&str>,
        display_name: Option<&str>,
    ) -> Result<Arc<LoadedScene>, CatalogError> {
        let _edits = self.edits.lock().expect("catalog edit lock");
        if self.get(id).is_none() {
            return Err(CatalogError::NotFound(id.into()));
        }
        if let SceneStore::Bucket(b) = &self.scenes_at {
            return Err(CatalogError::ReadOnlyBucket(b.url()));
        }
        let mut current = id.to_string();
        if let Some(to) = new_id.filter(|to| *to != id) {
            store::validate_id(to)?;
            let (from_dir, to_dir) = (self.store.join(id), self.store.join(to));
            if self.contains(to) {
                return Err(CatalogError::Exists(to.into()));
            }
            fs::rename(&from_dir, &to_dir).map_err(|source| CatalogError::Io {
                action: "rename",
                path: from_dir.clone(),
                source,
            })?;
            sync_dir(&self.store);
            self.scenes.write().expect("catalog lock").remove(id);
            current = to.to_string();
        }
        if let Some(name) = display_name {
            let dir = self.store.join(&current);
            let mut info = read_build_info(&dir);
            info.display_name = Some(name.to_string());
            write_build_info(&dir, &info).map_err(|source| CatalogError::Io {
                action: "write",
                path: dir.join(BUILD_INFO_FILE),
                source,
            })?;
        }
        Ok(self.refresh(&current)?)
    }

    /// Deletes a scene atomically: one rename out of the listing (to
    /// `.trash-*`), then the files are removed.
    pub fn delete(&self, id: &str) -> Result<(), CatalogError> {
        let _edits = self.edits.lock().expect("catalog edit lock");
        if self.get(id).is_none() {
            return Err(CatalogError::NotFound(id.into()));
        }
        if let SceneStore::Bucket(b) = &self.scenes_at {
            return Err(CatalogError::ReadOnlyBucket(b.url()));
        }
        let dir = self.store.join(id);
        let trash = self.store.join(format!(".trash-{id}-{}", nanos()));
        // Unlisted before its files move, so a read that fails on them finds the scene gone.
        let listed = self.scenes.write().expect("catalog lock").remove(id);
        if let Err(source) = fs::rename(&dir, &trash) {
            if let Some(scene) = listed {
                self.scenes.write().expect("catalog lock").insert(id.to_string(), scene);
            }
            return Err(CatalogError::Io { action: "delete", path: dir, source });
        }
        sync_dir(&self.store);
        if let Err(e) = fs::remove_dir_all(&trash) {
            tracing::warn!(path = %trash.display(), error = %e, "deleted scene's files remain; removed on next start");
        }
        Ok(())
    }
}

/// Renames and deletes of bucket scenes, fenced through the coordinator (see
/// [`Coordinator::with_scenes_locked`]): never while a build of either id is queued or running on
/// any replica, nor while another replica edits or collects either id.
impl Catalog {
    fn bucket(&self) -> Result<&Arc<BucketStore>, CatalogError> {
        match &self.scenes_at {
            SceneStore::Bucket(b) => Ok(b),
            SceneStore::Local(_) => Err(CatalogError::Bucket("not a bucket store".into())),
        }
    }

    /// Drops scene `id` from this replica's catalog at once (the others drop it at their next
    /// listing, when its manifest is gone).
    fn forget(&self, id: &str) {
        let mut scenes = self.scenes.write().expect("catalog lock");
        let at = self.edits_made.fetch_add(1, Ordering::SeqCst) + 1;
        self.forgotten.lock().expect("forgotten lock").insert(id.to_string(), at);
        scenes.remove(id);
        self.manifests.lock().expect("manifest lock").remove(id);
    }

    /// Deletes a bucket scene: its manifest first (the one mutable pointer: from then on no replica
    /// loads it again, and each drops it at its next listing), then every other object under
    /// `<id>/` (packs, pages, `scene.json`). Objects a failure leaves behind are the collector's
    /// (a scene without a manifest is all garbage once older than the grace period).
    pub async fn delete_in_bucket(&self, coordinator: &Coordinator, id: &str) -> Result<(), CatalogError> {
        let bucket = self.bucket()?;
        coordinator
            .with_scenes_locked(&[id], true, async {
                // Listed before the manifest goes, so nothing it names is missed.
                let objects = bucket.list_under(id).await.map_err(CatalogError::Bucket)?;
                if bucket.manifest(id).await.map_err(CatalogError::Bucket)?.is_none() {
                    self.forget(id);
                    return Err(CatalogError::NotFound(id.into()));
                }
                bucket.delete(&format!("{id}/manifest.json")).await.map_err(CatalogError::Bucket)?;
                self.forget(id);
                let rest: Vec<_> = objects.into_iter().filter(|o| !o.rel.ends_with("/manifest.json")).collect();
                match bucket.purge_scene(id, &rest).await {
                    Ok((n, bytes)) => tracing::info!(scene = %id, objects = n + 1, bytes, "scene deleted from the bucket"),
                    Err(e) => tracing::warn!(scene = %id, error = %e, "scene deleted (its manifest is gone); some objects remain for the collector"),
                }
                Ok(())
            })
            .await?
    }

    /// Renames a bucket scene and/or sets its display name. A new id: every object but the
    /// manifest is copied server-side to `<new>/`, then the manifest (last, so the new id is never
    /// half-published), then the old manifest is deleted, then the old objects. A display name is
    /// `<id>/scene.json`, as a local store writes it.
    pub async fn rename_in_bucket(
        &self,
        coordinator: &Coordinator,
        id: &str,
        new_id: Option<&str>,
        display_name: Option<&str>,
    ) -> Result<Arc<LoadedScene>, CatalogError> {
        let bucket = self.bucket()?;
        let to = new_id.filter(|to| *to != id);
        if let Some(to) = to {
            store::validate_id(to)?;
        }
        let ids: Vec<&str> = std::iter::once(id).chain(to).collect();
        coordinator
            .with_scenes_locked(&ids, true, async {
                let mut current = id.to_string();
                if bucket.manifest(id).await.map_err(CatalogError::Bucket)?.is_none() {
                    self.forget(id);
                    return Err(CatalogError::NotFound(id.into()));
                }
                if let Some(to) = to {
                    if bucket.manifest(to).await.map_err(CatalogError::Bucket)?.is_some() {
                        return Err(CatalogError::Exists(to.into()));
                    }
                    let objects = bucket.list_under(id).await.map_err(CatalogError::Bucket)?;
                    let moved = |rel: &str| format!("{to}/{}", &rel[id.len() + 1..]);
                    let manifest = format!("{id}/manifest.json");
                    let rest: Vec<_> = objects.iter().filter(|o| o.rel != manifest).collect();
                    let pairs: Vec<(String, String)> = rest.iter().map(|o| (o.rel.clone(), moved(&o.rel))).collect();
                    let copies: Vec<Result<(), String>> = futures_util::stream::iter(pairs)
                        .map(|(from, to_rel)| async move { bucket.copy(&from, &to_rel).await })
                        .buffer_unordered(8)
                        .collect()
                        .await;
                    if let Some(Err(e)) = copies.into_iter().find(Result::is_err) {
                        // The new id has no manifest: what was copied is the collector's.
                        return Err(CatalogError::Bucket(e));
                    }
                    bucket.copy(&manifest, &moved(&manifest)).await.map_err(CatalogError::Bucket)?;
                    bucket.delete(&manifest).await.map_err(CatalogError::Bucket)?;
                    self.forget(id);
                    let old: Vec<_> = rest.into_iter().cloned().collect();
                    if let Err(e) = bucket.purge_scene(id, &old).await {
                        tracing::warn!(scene = %id, error = %e, "renamed; some objects of the old id remain for the collector");
                    }
                    tracing::info!(from = %id, to = %to, objects = objects.len(), "scene renamed in the bucket");
                    current = to.to_string();
                }
                if let Some(name) = display_name {
                    let rel = format!("{current}/{BUILD_INFO_FILE}");
                    let mut info: BuildInfo = bucket
                        .optional(&rel)
                        .await
                        .map_err(CatalogError::Bucket)?
                        .and_then(|b| serde_json::from_slice(&b).ok())
                        .unwrap_or_default();
                    info.display_name = Some(name.to_string());
                    let json = serde_json::to_vec_pretty(&info).expect("build info serialises");
                    bucket
                        .bucket
                        .put(&rel, json, "application/json", "no-cache")
                        .await
                        .map_err(|e| CatalogError::Bucket(format!("{e:#}")))?;
                }
                self.reload(&current).await.map_err(CatalogError::Bucket)?;
                self.get(&current).ok_or_else(|| CatalogError::NotFound(current.clone()))
            })
            .await?
    }
}

fn sync_dir(dir: &Path) {
    if let Err(e) = fs::File::open(dir).and_then(|d| d.sync_all()) {
        tracing::warn!(dir = %dir.display(), error = %e, "cannot sync directory");
    }
}

/// Removes what interrupted work leaves in a store: build temp dirs
/// (`.tmp-*` and `.build-*`, unless their builder process still runs), scenes moved aside for
/// replacement (`.old-*`; restored when the replacement never arrived) and
/// deleted scenes (`.trash-*`). Returns the names handled.
pub fn remove_stale(store: &Path) -> Vec<String> {
    let Ok(entries) = fs::read_dir(store) else { return Vec::new() };
    let mut removed = Vec::new();
    for entry in entries.flatten() {
        let Some(name) = entry.file_name().to_str().map(str::to_string) else { continue };
        // A crash between publish's two renames leaves the previous scene only in `.old-<id>-<pid>`:
        // put it back rather than lose it.
        if let Some(id) = name.strip_prefix(".old-").and_then(|rest| rest.rsplit_once('-')).map(|(id, _)| id)
            && store::validate_id(id).is_ok()
            && !store.join(id).exists()
            && !written_by_other_live_process(&name)
        {
            if fs::rename(entry.path(), store.join(id)).is_ok() {
                removed.push(format!("{name} (restored as {id})"));
            }
            continue;
        }
        let stale = if name.starts_with(".tmp-") || name.starts_with(".build-") || name.starts_with(".old-") {
            !written_by_other_live_process(&name)
        } else {
            name.starts_with(".trash-")
        };
        if stale && fs::remove_dir_all(entry.path()).is_ok() {
            removed.push(name);
        }
    }
    removed
}

/// `.tmp-<id>-<pid>-<nanos>` / `.build-<pid>-<random>` / `.old-<id>-<pid>`: a
/// `voxstream build` may be writing into the same store right now.
fn written_by_other_live_process(name: &str) -> bool {
    let mut parts = name.rsplit('-');
    let pid =
        if name.starts_with(".tmp-") || name.starts_with(".build-") { parts.nth(1) } else { parts.next() };
    let Some(pid) = pid.and_then(|p| p.parse::<u32>().ok()) else { return false };
    pid != std::process::id() && Path::new("/proc").join(pid.to_string()).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A replica's own delete or rename drops the id while a listing (or a lookup) is between
    /// reading the manifest and serving the scene: that load must not put the scene back.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn loads_and_listings_older_than_an_edit_here_do_not_undo_it() {
        use crate::objstore::Bucket;
        use crate::pipeline::{BuildOptions, Resolution, build_scene};
        use object_store::ObjectStore;

        let dir = tempfile::tempdir().unwrap();
        let koala = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj");
        let opts = BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() };
        let id = build_scene(&koala, &dir.path().join("store"), &opts).unwrap().id;
        let manifest = fs::read(dir.path().join("store").join(&id).join("manifest.json")).unwrap();
        let memory = Arc::new(object_store::memory::InMemory::new());
        let path = object_store::path::Path::from(format!("scenes/{id}/manifest.json"));
        memory.put(&path, manifest.into()).await.unwrap();
        let bucket = Bucket {
            store: memory,
            bucket: "test".into(),
            prefix: "scenes".into(),
            endpoint: "memory".into(),
        };
        let bucket = Arc::new(BucketStore::new(bucket, 1 << 20));
        let catalog = Catalog::open_bucket(bucket.clone(), dir.path()).await.unwrap();
        assert!(catalog.get(&id).is_some(), "the listing serves the scene");

        // Control: a read with no edit in between is served.
        catalog.forget(&id);
        let BucketRead::Loaded(read) = catalog.read_from_bucket(&bucket, &id).await.unwrap() else {
            panic!("the manifest is there and not served")
        };
        assert!(catalog.install(read));
        assert!(catalog.get(&id).is_some());

        // The race: the read began, then this replica deleted the scene.
        let BucketRead::Unchanged = catalog.read_from_bucket(&bucket, &id).await.unwrap() else {
            panic!("the same manifest reads as unchanged")
        };
        catalog.manifests.lock().unwrap().clear();
        let BucketRead::Loaded(stale) = catalog.read_from_bucket(&bucket, &id).await.unwrap() else {
            panic!("a forgotten manifest reads again")
        };
        catalog.forget(&id);
        assert!(!catalog.install(stale), "a load older than the delete is dropped");
        assert!(catalog.get(&id).is_none(), "the deleted scene came back");
        // A load that begins after the delete (a rebuild under the same id) is served.
        assert!(catalog.reload(&id).await.unwrap());
        assert!(catalog.get(&id).is_some());

        // A listing that began before this replica published the id again (so did not see it)
        // leaves the newer load served; control: the entry it began with is dropped.
        let before = catalog.scenes.read().unwrap().clone();
        catalog.forget(&id);
        assert!(catalog.reload(&id).await.unwrap());
        catalog.drop_unlisted(&before, &[]);
        assert!(catalog.get(&id).is_some(), "a listing older than the publish dropped it");
        let before = catalog.scenes.read().unwrap().clone();
        catalog.drop_unlisted(&before, &[]);
        assert!(catalog.get(&id).is_none(), "an unlisted scene stays served");
    }

    #[test]
    fn stale_dirs_of_dead_processes_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let own = std::process::id();
        // pid 1 is alive (init) and not us: kept; a pid far beyond pid_max is dead: removed.
        for name in [
            ".tmp-a-1-5",
            ".tmp-b-4194399999-5",
            ".trash-c-7",
            &format!(".tmp-d-{own}-1"),
            ".build-1-Xy7",
            ".build-4194399999-Ab3",
            "keep",
        ] {
            fs::create_dir(dir.path().join(name)).unwrap();
        }
        let mut removed = remove_stale(dir.path());
        removed.sort();
        assert_eq!(
            removed,
            vec![
                ".build-4194399999-Ab3".to_string(),
                ".tmp-b-4194399999-5".to_string(),
                format!(".tmp-d-{own}-1"),
                ".trash-c-7".into()
            ]
        );
        assert!(dir.path().join(".build-1-Xy7").exists());
        assert!(dir.path().join(".tmp-a-1-5").exists());
        assert!(dir.path().join("keep").exists());
    }
}
