//! Garbage collection of a bucket's unreferenced objects, on replicas with a coordinator.
//!
//! What becomes garbage: the packs of a replaced scene (a rebuild publishes a new manifest; the
//! old packs stay, since a reader of the previous manifest may still need them), the objects of a
//! build that failed or was killed after uploading (packs, no manifest), what an interrupted
//! rename or delete leaves, and upload parts whose upload record is gone.
//!
//! What is removed, per scene id under the prefix, holding that scene's lock in the coordinator
//! (tried, not waited for: a scene being edited is skipped) and only when no build of it is queued
//! or running, nor a build marker younger than [`crate::bucket_build::MARKER_LIVE`] says a build is
//! writing it (`<id>/building.json`, rewritten every 30 s by every build into the bucket, the
//! cluster's and `voxstream build --out s3://…` alike, deleted after its manifest):
//! - with a manifest: objects under `<id>/packs/` that the manifest's scene (every page of its
//!   hierarchy) does not name, once both the object and the manifest are older than the grace
//!   period;
//! - without a manifest: every object under `<id>/` older than the grace period;
//! - `.uploads/<upload>/…` parts older than the grace period whose upload has no record.
//!
//! Why a grace period, and why it also counts from the manifest's own age: after a scene is
//! replaced, a replica may serve the previous manifest until its next listing, and a browser that
//! fetched it keeps asking for the blocks it names; the objects only that manifest names became
//! unreferenced when the new one was written, so they are kept until the new manifest is older
//! than the grace period. Builds that are not fenced by the coordinator (`voxstream build --out
//! s3://…` from a workstation) upload their packs before their manifest and keep them with their
//! marker, however long they take; once a killed build's marker is stale, its objects are garbage
//! like any other (a stale marker under a published scene goes too).
//!
//! One replica collects at a time (a try-lock in the coordinator, [`crate::coordinator::GC_LOCK`]);
//! the others skip their pass. What is removed is logged and counted in `/metrics`
//! (`voxstream_gc_objects_deleted_total`, `voxstream_gc_bytes_deleted_total`).

use std::collections::{BTreeMap, HashSet};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use prometheus_client::metrics::counter::Counter;
use voxstream_format::Manifest;
use voxstream_format::hierarchy::pack_path;

use crate::bucket_build::{BUILD_MARKER, marker_is_live};
use crate::bucket_store::{BucketStore, ObjectInfo};
use crate::coordinator::{Coordinator, SceneLockError, upload_prefix};

/// When the collector runs.
#[derive(Debug, Clone, Copy)]
pub struct GcSettings {
    /// Between passes over the whole bucket; `None`: no collection at all.
    pub interval: Option<Duration>,
    /// Objects younger than this (and a scene's unreferenced packs while its manifest is younger)
    /// are kept.
    pub grace: Duration,
}

impl Default for GcSettings {
    fn default() -> Self {
        Self { interval: Some(Duration::from_secs(3600)), grace: Duration::from_secs(3600) }
    }
}

/// What the collector removed, counted in the server's metrics.
#[derive(Clone, Default)]
pub struct GcMetrics {
    pub objects: Counter,
    pub bytes: Counter,
}

/// What one pass removed and what it skipped.
#[derive(Debug, Clone, Default)]
pub struct GcReport {
    pub objects: u64,
    pub bytes: u64,
    /// Scenes left alone: being built, edited or collected elsewhere, or unreadable.
    pub skipped: Vec<String>,
}

fn now_ms() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as i64)
}

/// One pass: every scene id under the prefix (or only `only`) and, on a full pass, the upload
/// parts. `Ok(None)`: another replica is collecting now.
pub async fn collect(
    bucket: &BucketStore,
    coordinator: &Coordinator,
    grace: Duration,
    only: Option<&str>,
    metrics: &GcMetrics,
) -> anyhow::Result<Option<GcReport>> {
    let pass = async {
        let ids = match only {
            Some(id) => vec![id.to_string()],
            None => bucket.list_ids().await.map_err(anyhow::Error::msg)?,
        };
        let mut report = GcReport::default();
        for id in ids {
            match coordinator
                .with_scenes_locked(&[id.as_str()], false, collect_scene(bucket, &id, grace))
                .await
            {
                Ok(Ok(None)) => {
                    tracing::info!(scene = %id, "not collected: a build outside the cluster is writing it");
                    report.skipped.push(id);
                }
                Ok(Ok(Some((objects, bytes)))) => {
                    if objects > 0 {
                        tracing::info!(scene = %id, objects, bytes, "collected unreferenced objects");
                    }
                    report.objects += objects;
                    report.bytes += bytes;
                    metrics.objects.inc_by(objects);
                    metrics.bytes.inc_by(bytes);
                }
                Ok(Err(e)) => {
                    tracing::warn!(scene = %id, error = %e, "scene not collected");
                    report.skipped.push(id);
                }
                Err(SceneLockError::Busy(_) | SceneLockError::Building(_)) => report.skipped.push(id),
                Err(e @ SceneLockError::Failed(_)) => return Err(anyhow::anyhow!("{e}")),
            }
        }
        if only.is_none() {
            let (objects, bytes) = collect_uploads(bucket, coordinator, grace).await?;
            if objects > 0 {
                tracing::info!(objects, bytes, "collected parts of ended uploads");
            }
            report.objects += objects;
            report.bytes += bytes;
            metrics.objects.inc_by(objects);
            metrics.bytes.inc_by(bytes);
        }
        anyhow::Ok(report)
    };
    coordinator.with_gc_lock(pass).await?.transpose()
}

/// The garbage of one scene id (its lock held, no build of it queued or running).
/// `None`: a build outside the cluster is writing the id (its marker is live), so it is skipped.
async fn collect_scene(
    bucket: &BucketStore,
    id: &str,
    grace: Duration,
) -> Result<Option<(u64, u64)>, String> {
    let now = now_ms();
    let old = |t: i64| now.saturating_sub(t) >= grace.as_millis() as i64;
    // Listed before the manifest is read: an object the listing shows is either named by the
    // manifest read after it or was uploaded before it.
    let objects = bucket.list_under(id).await?;
    let marker = format!("{id}/{BUILD_MARKER}");
    let marker_written = objects.iter().find(|o| o.rel == marker).map(|o| o.modified_ms);
    if marker_written.is_some_and(|t| marker_is_live(t, now)) {
        return Ok(None);
    }
    let garbage: Vec<ObjectInfo> = match bucket.manifest_with_time(id).await? {
        None => objects.into_iter().filter(|o| old(o.modified_ms)).collect(),
        Some((_, written)) if !old(written) => Vec::new(),
        Some((bytes, _)) => {
            let manifest = Manifest::from_json(&bytes).map_err(|e| format!("manifest: {e}"))?;
            // Every page: a pack only a page deep in the hierarchy names is still the scene's.
            let index = bucket.load_index(id, &manifest).await.map_err(|e| e.to_string())?;
            if !index.is_complete() {
                return Err("its hierarchy could not be read whole".into());
            }
            let keep: HashSet<String> =
                index.packs().map(|p| format!("{id}/{}", pack_path(&p.hash))).collect();
            let packs = format!("{id}/packs/");
            // A killed replacing build's stale marker goes too.
            objects
                .into_iter()
                .filter(|o| {
                    ((o.rel.starts_with(&packs) && !keep.contains(&o.rel)) || o.rel == marker)
                        && old(o.modified_ms)
                })
                .collect()
        }
    };
    bucket.delete_all(&garbage).await.map(Some)
}

/// Parts under `.uploads/<upload>/` whose upload has no record any more, older than `grace`.
async fn collect_uploads(
    bucket: &BucketStore,
    coordinator: &Coordinator,
    grace: Duration,
) -> anyhow::Result<(u64, u64)> {
    let now = now_ms();
    // Listed before the records are read: an upload created since has no part this old.
    let objects = bucket.list_under(".uploads").await.map_err(anyhow::Error::msg)?;
    if objects.is_empty() {
        return Ok((0, 0));
    }
    let live: HashSet<String> = coordinator.upload_ids().await?.into_iter().collect();
    let mut by_upload: BTreeMap<&str, Vec<ObjectInfo>> = BTreeMap::new();
    for o in &objects {
        let Some(upload) = o.rel.strip_prefix(".uploads/").and_then(|r| r.split('/').next()) else {
            continue;
        };
        debug_assert!(o.rel.starts_with(&upload_prefix(upload)));
        if !live.contains(upload) && now.saturating_sub(o.modified_ms) >= grace.as_millis() as i64 {
            by_upload.entry(upload).or_default().push(o.clone());
        }
    }
    let garbage: Vec<ObjectInfo> = by_upload.into_values().flatten().collect();
    bucket.delete_all(&garbage).await.map_err(anyhow::Error::msg)
}
