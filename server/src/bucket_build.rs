//! `voxstream build --out s3://bucket/prefix`: the build writes into a local temporary store as
//! always, and every pack and hierarchy page is uploaded as the writer finishes it (a bounded
//! queue and a bounded number of PUTs at once, so at most [`UPLOAD_QUEUE`] + [`UPLOAD_CONCURRENCY`]
//! files are held in memory, and a slow bucket slows the build instead of growing it). Once the
//! build and every upload have succeeded, the manifest is written, last: it is the scene's one
//! mutable object, so a reader sees the old scene or the new one, whole, never a half-published
//! one. Packs and pages are content-addressed (see [`crate::bucket_store`]), so uploading a new
//! version never overwrites an object the old manifest names. A failed or killed build leaves the
//! previous manifest in place (and unreferenced objects, not collected yet); the local temporary
//! store is removed in every case.

use std::path::Path;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use tokio::task::JoinSet;

use crate::objstore::Bucket;
use crate::pipeline::progress::Progress;
use crate::pipeline::{BuildOptions, BuildReport, FinishedFiles, build_scene_reporting};

/// Finished files waiting for an upload slot.
pub const UPLOAD_QUEUE: usize = 4;
/// PUTs in flight at once.
pub const UPLOAD_CONCURRENCY: usize = 4;
/// Immutable, content-addressed objects (packs and pages) are cached by anyone for a year.
const IMMUTABLE: &str = "public, max-age=31536000, immutable";

/// `<id>/building.json`: written when a build into the bucket starts, rewritten every
/// [`MARKER_REFRESH`] while it runs, deleted once its manifest is written. The collector leaves an
/// id alone while its marker is younger than [`MARKER_LIVE`], so a long `voxstream build --out
/// s3://…` run outside the cluster (no coordinator fences it) keeps its packs however long it
/// takes; a killed build's marker goes stale and its objects are collected as before.
pub const BUILD_MARKER: &str = "building.json";
/// How often a running build rewrites its marker.
pub const MARKER_REFRESH: std::time::Duration = std::time::Duration::from_secs(30);
/// How long a marker counts as a running build: four refreshes missed.
pub const MARKER_LIVE: std::time::Duration = std::time::Duration::from_secs(120);

/// Whether a marker written at `written_ms` (unix ms) still stands for a running build at `now_ms`.
pub fn marker_is_live(written_ms: i64, now_ms: i64) -> bool {
    now_ms.saturating_sub(written_ms) < MARKER_LIVE.as_millis() as i64
}

/// The running build's marker: rewritten by a task on the upload runtime until dropped.
struct BuildMarker {
    rel: String,
    refresh: tokio::task::JoinHandle<()>,
}

impl BuildMarker {
    fn start(bucket: &Arc<Bucket>, id: &str, handle: &tokio::runtime::Handle) -> anyhow::Result<Self> {
        let rel = format!("{id}/{BUILD_MARKER}");
        let body = serde_json::json!({ "pid": std::process::id() }).to_string().into_bytes();
        handle.block_on(bucket.put(&rel, body.clone(), "application/json", "no-cache"))?;
        let (bucket, again) = (bucket.clone(), rel.clone());
        let refresh = handle.spawn(async move {
            loop {
                tokio::time::sleep(MARKER_REFRESH).await;
                if let Err(e) = bucket.put(&again, body.clone(), "application/json", "no-cache").await {
                    tracing::warn!(marker = %again, error = %format!("{e:#}"), "cannot refresh the build marker");
                }
            }
        });
        Ok(Self { rel, refresh })
    }
}

impl Drop for BuildMarker {
    fn drop(&mut self) {
        self.refresh.abort();
    }
}

/// What a build into a bucket published.
pub struct BucketBuild {
    pub report: BuildReport,
    /// `s3://bucket/prefix/<id>`.
    pub url: String,
    /// Objects uploaded: packs and pages, then the manifest.
    pub objects: usize,
    pub bytes: u64,
}

/// Builds `mesh` and publishes it as `<prefix>/<id>/` in `bucket` (see the module's notes).
pub fn build_into_bucket(
    mesh: &Path,
    bucket: &str,
    prefix: &str,
    opts: BuildOptions,
    report: &(dyn Fn(Progress) + Sync),
) -> anyhow::Result<BucketBuild> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the upload runtime")?;
    // Unreachable endpoint, refused credentials, missing bucket: said before anything is read.
    let bucket = Arc::new(rt.block_on(crate::objstore::connect(
        bucket,
        prefix,
        crate::objstore::START_CHECK_DEADLINE,
    ))?);
    let staged = stage_in_bucket(mesh, &bucket, rt.handle(), opts, report)?;
    // Last: from here on readers see the new scene.
    rt.block_on(staged.publish(&bucket))?;
    Ok(staged.into_build(&bucket))
}

/// A scene whose packs and pages are in the bucket and whose manifest is not yet: invisible to
/// readers until [`StagedScene::publish`].
pub struct StagedScene {
    pub report: BuildReport,
    pub id: String,
    pub manifest: Vec<u8>,
    objects: usize,
    bytes: u64,
    /// The local build the report names; removed with the staged scene.
    _scratch: tempfile::TempDir,
    /// Kept fresh until the manifest is written (dropped on failure: it goes stale).
    marker: BuildMarker,
}

impl StagedScene {
    /// Writes the manifest: the one PUT that makes the scene (or its new version) visible.
    pub async fn publish(&self, bucket: &Bucket) -> anyhow::Result<()> {
        bucket
            .put(&format!("{}/manifest.json", self.id), self.manifest.clone(), "application/json", "no-cache")
            .await?;
        self.marker.refresh.abort();
        if let Err(e) = bucket.store.delete(&bucket.path(&self.marker.rel)).await {
            // Harmless: it goes stale, and the collector removes it.
            tracing::warn!(marker = %self.marker.rel, error = %e, "cannot delete the build marker");
        }
        Ok(())
    }

    pub fn into_build(self, bucket: &Bucket) -> BucketBuild {
        let url = format!("s3://{}/{}", bucket.bucket, bucket.path(&self.id));
        BucketBuild {
            objects: self.objects + 1,
            bytes: self.bytes + self.manifest.len() as u64,
            report: self.report,
            url,
        }
    }
}

/// Builds `mesh` and uploads its packs and pages (not the manifest) through `handle`'s runtime.
/// Blocking: call it off the runtime's worker threads (the CLI's main thread, `spawn_blocking`).
pub fn stage_in_bucket(
    mesh: &Path,
    bucket: &Arc<Bucket>,
    handle: &tokio::runtime::Handle,
    mut opts: BuildOptions,
    report: &(dyn Fn(Progress) + Sync),
) -> anyhow::Result<StagedScene> {
    let id = match &opts.name {
        Some(name) => name.clone(),
        None => crate::store::id_from_file_stem(mesh),
    };
    crate::store::validate_id(&id)?;
    opts.name = Some(id.clone());
    let scratch_parent = opts.temp_dir.clone().unwrap_or_else(std::env::temp_dir);
    std::fs::create_dir_all(&scratch_parent)
        .with_context(|| format!("cannot create {}", scratch_parent.display()))?;
    let scratch = tempfile::Builder::new()
        .prefix("voxstream-bucket-build-")
        .tempdir_in(&scratch_parent)
        .with_context(|| format!("cannot create a temporary store in {}", scratch_parent.display()))?;

    let marker = BuildMarker::start(bucket, &id, handle)?;
    let (tx, rx) = tokio::sync::mpsc::channel::<(String, Vec<u8>)>(UPLOAD_QUEUE);
    let failure: Arc<Mutex<Option<String>>> = Arc::default();
    let uploader = handle.spawn(upload_all(bucket.clone(), id.clone(), rx, failure.clone()));
    let sink_failure = failure.clone();
    opts.finished_files = Some(FinishedFiles(Arc::new(move |name: &str, bytes: Vec<u8>| {
        // Blocks while the queue is full: the build waits for the bucket.
        tx.blocking_send((name.to_string(), bytes)).map_err(|_| {
            let cause = sink_failure.lock().expect("failure lock").clone();
            format!(
                "uploading to the bucket failed: {}",
                cause.unwrap_or_else(|| "the uploader stopped".into())
            )
        })
    })));
    let built = build_scene_reporting(mesh, scratch.path(), &opts, report);
    drop(opts); // closes the queue: the uploader ends once it has sent what is queued
    let uploaded = handle.block_on(uploader);
    let report = built?;
    let (objects, bytes) = match uploaded {
        Ok(Ok(counts)) => counts,
        Ok(Err(e)) => anyhow::bail!("uploading scene {id:?}: {e}"),
        Err(e) => anyhow::bail!("the uploader of scene {id:?} stopped: {e}"),
    };
    let manifest_path = report.scene_dir.join("manifest.json");
    let manifest = std::fs::read(&manifest_path)
        .with_context(|| format!("cannot read the built manifest {}", manifest_path.display()))?;
    Ok(StagedScene { report, id, manifest, objects, bytes, _scratch: scratch, marker })
}

/// Uploads queued files, [`UPLOAD_CONCURRENCY`] at once, until the queue closes; on the first
/// failure, records it, stops taking files (the build then fails) and returns it.
async fn upload_all(
    bucket: Arc<Bucket>,
    id: String,
    mut rx: tokio::sync::mpsc::Receiver<(String, Vec<u8>)>,
    failure: Arc<Mutex<Option<String>>>,
) -> Result<(usize, u64), String> {
    let mut running = JoinSet::new();
    let (mut objects, mut bytes) = (0usize, 0u64);
    let fail = |e: String| {
        failure.lock().expect("failure lock").get_or_insert(e.clone());
        e
    };
    loop {
        let next = tokio::select! {
            item = rx.recv(), if running.len() < UPLOAD_CONCURRENCY => item.map(Ok),
            Some(done) = running.join_next(), if !running.is_empty() => Some(Err(done)),
            else => break,
        };
        match next {
            Some(Ok((name, data))) => {
                let bucket = bucket.clone();
                let rel = format!("{id}/{name}");
                let len = data.len() as u64;
                running.spawn(async move {
                    bucket.put(&rel, data, "application/octet-stream", IMMUTABLE).await.map(|()| len)
                });
            }
            Some(Err(done)) => match done {
                Ok(Ok(len)) => {
                    objects += 1;
                    bytes += len;
                }
                Ok(Err(e)) => {
                    rx.close();
                    return Err(fail(format!("{e:#}")));
                }
                Err(e) => {
                    rx.close();
                    return Err(fail(e.to_string()));
                }
            },
            None => {
                // The queue closed: wait for what is in flight.
                while let Some(done) = running.join_next().await {
                    match done {
                        Ok(Ok(len)) => {
                            objects += 1;
                            bytes += len;
                        }
                        Ok(Err(e)) => return Err(fail(format!("{e:#}"))),
                        Err(e) => return Err(fail(e.to_string())),
                    }
                }
                return Ok((objects, bytes));
            }
        }
    }
    Ok((objects, bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_marker_stands_for_a_build_until_four_refreshes_are_missed() {
        let now = 1_000_000_000;
        assert!(marker_is_live(now, now));
        assert!(marker_is_live(now - MARKER_REFRESH.as_millis() as i64, now), "one refresh late");
        assert!(marker_is_live(now - 119_999, now));
        assert!(!marker_is_live(now - 120_000, now), "stale");
        assert!(!marker_is_live(0, now));
        assert!(marker_is_live(now + 5_000, now), "a clock ahead of this one still counts");
        assert!(MARKER_LIVE >= MARKER_REFRESH * 4);
    }
}
