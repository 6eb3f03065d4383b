//! Build jobs of bucket replicas that share a coordinator ([`crate::coordinator`]): every replica
//! runs a claim loop; the replica that claims a job assembles its input from the upload's parts
//! in the bucket (streamed into a local file, one part in memory at a time), builds it, uploads
//! packs and pages as they are written, and publishes the manifest under the lease (fenced).
//! Progress, cancel requests and the lease travel through the job's row, so any replica answers
//! `GET /api/jobs/{id}` and its event stream.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, watch};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::bucket_build::{StagedScene, stage_in_bucket};
use crate::bucket_store::BucketStore;
use crate::catalog::{Catalog, now_unix};
use crate::coordinator::{Claim, Coordinator, PublishError};
use crate::gc::{GcReport, GcSettings};
use crate::jobs::{Job, JobState, UPLOAD_EXPIRY_SECS};
use crate::metrics::Metrics;
use crate::objstore::Bucket;
use crate::pipeline::progress::Progress;
use crate::pipeline::{BuildError, BuildOptions};

/// How often an idle replica looks for a job to claim.
const CLAIM_POLL: Duration = Duration::from_millis(500);
/// How often an event stream on a replica that is not building re-reads the job.
const EVENT_POLL: Duration = Duration::from_millis(300);
/// How often unfinished uploads older than [`UPLOAD_EXPIRY_SECS`] are looked for.
const EXPIRY_EVERY: Duration = Duration::from_secs(3600);

pub struct ClusterJobs {
    pub coordinator: Arc<Coordinator>,
    bucket: Arc<Bucket>,
    /// The bucket as the catalog reads it (for the garbage collector).
    store: Arc<BucketStore>,
    gc: GcSettings,
    catalog: Arc<Catalog>,
    metrics: Arc<Metrics>,
    workers: Arc<Semaphore>,
    tracker: TaskTracker,
    shutdown: CancellationToken,
    /// Where inputs are assembled and builds write before uploading (the replica's temp folder).
    scratch: PathBuf,
}

/// How a build ended before publication.
enum Built {
    Staged(Box<StagedScene>),
    Cancelled,
    Failed(String),
}

impl ClusterJobs {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        coordinator: Arc<Coordinator>,
        bucket: &Arc<BucketStore>,
        catalog: Arc<Catalog>,
        metrics: Arc<Metrics>,
        workers: usize,
        gc: GcSettings,
        shutdown: CancellationToken,
    ) -> Arc<ClusterJobs> {
        let scratch = catalog.store().to_path_buf();
        Arc::new(ClusterJobs {
            coordinator,
            bucket: Arc::new(bucket.bucket.clone()),
            store: bucket.clone(),
            gc,
            catalog,
            metrics,
            workers: Arc::new(Semaphore::new(workers.max(1))),
            tracker: TaskTracker::new(),
            shutdown,
            scratch,
        })
    }

    pub fn bucket(&self) -> &Bucket {
        &self.bucket
    }

    /// Starts the claim loop, and the garbage collector's when it is on.
    pub fn start(self: &Arc<Self>) {
        let this = self.clone();
        self.tracker.spawn(async move { this.claim_loop().await });
        if let Some(every) = self.gc.interval {
            let this = self.clone();
            tokio::spawn(async move { this.gc_loop(every).await });
        }
    }

    /// One garbage collection pass now (all scenes, or only `only`); `Ok(None)` when another
    /// replica is collecting.
    pub async fn collect_garbage(&self, only: Option<&str>) -> anyhow::Result<Option<GcReport>> {
        crate::gc::collect(&self.store, &self.coordinator, self.gc.grace, only, &self.metrics.gc).await
    }

    async fn gc_loop(self: Arc<Self>, every: Duration) {
        let mut tick = crate::ticker::every(every).await;
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                () = self.shutdown.cancelled() => return,
            }
            match self.collect_garbage(None).await {
                Ok(Some(r)) => {
                    tracing::info!(objects = r.objects, bytes = r.bytes, skipped = ?r.skipped, "garbage collection pass")
                }
                Ok(None) => tracing::debug!("another replica is collecting garbage"),
                Err(e) => tracing::warn!(error = %format!("{e:#}"), "garbage collection failed"),
            }
        }
    }

    /// After a build published `scene` (replacing a scene leaves the previous packs): collects
    /// that scene once the new manifest is older than the grace period.
    fn collect_after_publish(self: &Arc<Self>, scene: String) {
        if self.gc.interval.is_none() {
            return;
        }
        let this = self.clone();
        tokio::spawn(async move {
            tokio::select! {
                () = tokio::time::sleep(this.gc.grace + Duration::from_millis(500)) => {}
                () = this.shutdown.cancelled() => return,
            }
            // Another replica collecting now: retry a few times, then leave it to the periodic pass.
            for _ in 0..5 {
                match this.collect_garbage(Some(&scene)).await {
                    Ok(Some(r)) if !r.skipped.is_empty() => {}
                    Ok(Some(_)) => return,
                    Ok(None) => {}
                    Err(e) => {
                        tracing::warn!(scene = %scene, error = %format!("{e:#}"), "garbage collection after the build failed");
                        return;
                    }
                }
                tokio::select! {
                    () = tokio::time::sleep(Duration::from_secs(2)) => {}
                    () = this.shutdown.cancelled() => return,
                }
            }
        });
    }

    async fn claim_loop(self: Arc<Self>) {
        let mut last_expiry: Option<Instant> = None;
        loop {
            let permit = tokio::select! {
                p = self.workers.clone().acquire_owned() => p.expect("the worker semaphore is never closed"),
                () = self.shutdown.cancelled() => return,
            };
            if last_expiry.is_none_or(|t| t.elapsed() >= EXPIRY_EVERY) {
                last_expiry = Some(Instant::now());
                self.expire_uploads().await;
            }
            match self.sweep_and_claim().await {
                Ok(Some(claim)) => {
                    let this = self.clone();
                    self.tracker.spawn(async move { this.run(claim, permit).await });
                    continue;
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(error = %format!("{e:#}"), "looking for a build to claim failed"),
            }
            drop(permit);
            tokio::select! {
                () = tokio::time::sleep(CLAIM_POLL) => {}
                () = self.shutdown.cancelled() => return,
            }
        }
    }

    async fn sweep_and_claim(&self) -> anyhow::Result<Option<Claim>> {
        for id in self.coordinator.sweep().await? {
            tracing::warn!(job = %id, "build given up (its builders kept dying) or cancelled while its builder was gone");
            self.coordinator.remove_upload(&self.bucket, &id).await;
        }
        self.metrics.jobs_queued.set(self.coordinator.queued().await?);
        self.coordinator.claim().await
    }

    async fn expire_uploads(&self) {
        let cutoff = now_unix().saturating_sub(UPLOAD_EXPIRY_SECS);
        match self.coordinator.stale_uploads(cutoff).await {
            Ok(ids) => {
                for id in ids {
                    if let Ok(true) = self.coordinator.delete_upload(&self.bucket, &id).await {
                        tracing::info!(upload = %id, "unfinished upload expired");
                    }
                }
            }
            Err(e) => tracing::warn!(error = %format!("{e:#}"), "cannot look for expired uploads"),
        }
    }

    async fn run(self: Arc<Self>, claim: Claim, permit: OwnedSemaphorePermit) {
        let id = claim.job.id.clone();
        tracing::info!(job = %id, scene = %claim.job.scene_id, attempt = claim.job.attempts, "build claimed");
        self.metrics.builds_started.inc();
        self.metrics.jobs_running.inc();
        let started = Instant::now();
        let progress = Arc::new(Mutex::new(claim.job.clone()));
        let cancel = Arc::new(AtomicBool::new(false));
        let flags = Flags::default();
        let stop_heartbeat = CancellationToken::new();
        let heartbeat = tokio::spawn(heartbeat(
            self.coordinator.clone(),
            claim.clone(),
            progress.clone(),
            cancel.clone(),
            flags.clone(),
            stop_heartbeat.clone(),
            self.shutdown.clone(),
        ));
        let built = self.build(&claim, &progress, &cancel).await;
        let seconds = started.elapsed().as_secs_f64();
        let snapshot = || progress.lock().expect("progress lock").clone();
        let ended = match built {
            _ if flags.lease_lost.load(Ordering::SeqCst) => {
                tracing::warn!(job = %id, "the lease was taken over by another replica; this build publishes nothing");
                None
            }
            Built::Staged(staged) => {
                let mut done = snapshot();
                done.state = JobState::Done;
                done.fraction = 1.0;
                done.eta_seconds = None;
                stop_heartbeat.cancel();
                let _ = heartbeat.await;
                match self.coordinator.publish(&claim, &done, staged.publish(&self.bucket)).await {
                    Ok(()) => {
                        if let Err(e) = self.catalog.reload(&done.scene_id).await {
                            tracing::warn!(scene = %done.scene_id, error = %e, "published, but this replica cannot load it yet");
                        }
                        tracing::info!(job = %id, scene = %done.scene_id, seconds, "build done");
                        self.collect_after_publish(done.scene_id.clone());
                        Some(JobState::Done)
                    }
                    Err(PublishError::LeaseLost) => {
                        tracing::warn!(job = %id, "the lease expired before publication; this build publishes nothing");
                        None
                    }
                    Err(PublishError::Failed(e)) => {
                        self.end(&claim, snapshot(), JobState::Failed, format!("publishing failed: {e:#}"))
                            .await
                    }
                }
            }
            Built::Cancelled if flags.user_cancelled.load(Ordering::SeqCst) => {
                self.end(&claim, snapshot(), JobState::Cancelled, "cancelled".into()).await
            }
            Built::Cancelled => {
                // Shutdown: give it back so another replica builds it now, not after the lease.
                if let Err(e) = self.coordinator.release(&claim).await {
                    tracing::warn!(job = %id, error = %format!("{e:#}"), "cannot give the build back; another replica takes it after the lease");
                } else {
                    tracing::info!(job = %id, "build interrupted by shutdown; given back to the queue");
                }
                None
            }
            Built::Failed(message) => self.end(&claim, snapshot(), JobState::Failed, message).await,
        };
        stop_heartbeat.cancel();
        drop(permit);
        self.metrics.jobs_running.dec();
        if let Some(state) = ended {
            self.metrics
                .job_seconds
                .get_or_create(&Metrics::labels(&[("outcome", state.name())]))
                .observe(seconds);
            self.coordinator.remove_upload(&self.bucket, &id).await;
        }
    }

    /// Records a failed or cancelled end (if the lease is still ours); the state recorded.
    async fn end(&self, claim: &Claim, mut job: Job, state: JobState, error: String) -> Option<JobState> {
        tracing::warn!(job = %job.id, scene = %job.scene_id, state = state.name(), %error, "build ended");
        job.state = state;
        job.error = Some(error);
        job.eta_seconds = None;
        match self.coordinator.finish(claim, &job).await {
            Ok(true) => Some(state),
            Ok(false) => None,
            Err(e) => {
                tracing::warn!(job = %job.id, error = %format!("{e:#}"), "cannot record the build's end; it is retried after the lease");
                None
            }
        }
    }

    /// Assembles the input and builds it into the bucket, all but the manifest.
    async fn build(&self, claim: &Claim, progress: &Arc<Mutex<Job>>, cancel: &Arc<AtomicBool>) -> Built {
        let job = &claim.job;
        let scratch = match tempfile::Builder::new().prefix("voxstream-job-").tempdir_in(&self.scratch) {
            Ok(dir) => dir,
            Err(e) => return Built::Failed(format!("cannot create a build folder: {e}")),
        };
        let input = scratch.path().join(&job.input_file);
        match self.assemble(job, &input, cancel).await {
            Ok(Some(hash)) => progress.lock().expect("progress lock").input_blake3 = Some(hash),
            Ok(None) => return Built::Cancelled,
            Err(e) => return Built::Failed(format!("cannot assemble the upload: {e}")),
        }
        // More build options are coming (memory budget, ...): keep their defaults.
        #[allow(clippy::needless_update)]
        let opts = BuildOptions {
            temp_dir: Some(scratch.path().to_path_buf()),
            ..job.build_options(cancel.clone())
        };
        let bucket = self.bucket.clone();
        let handle = tokio::runtime::Handle::current();
        let progress = progress.clone();
        let started = Instant::now();
        let staged = tokio::task::spawn_blocking(move || {
            let report = move |p: Progress| {
                let elapsed = started.elapsed().as_secs_f64();
                let mut j = progress.lock().expect("progress lock");
                j.stage = Some(p.stage.name().to_string());
                j.fraction = p.fraction;
                j.triangles_per_second = p.triangles_per_second;
                j.eta_seconds = (p.fraction > 0.01).then(|| elapsed * (1.0 - p.fraction) / p.fraction);
            };
            stage_in_bucket(&input, &bucket, &handle, opts, &report)
        })
        .await;
        drop(scratch);
        match staged {
            Ok(Ok(staged)) => Built::Staged(Box::new(staged)),
            Ok(Err(e)) if matches!(e.downcast_ref::<BuildError>(), Some(BuildError::Cancelled)) => {
                Built::Cancelled
            }
            Ok(Err(e)) => Built::Failed(format!("{e:#}")),
            Err(e) => Built::Failed(format!("the build crashed: {e}")),
        }
    }

    /// Streams the upload's parts, in order, into `path`; checks they cover the input exactly.
    /// Returns the input's blake3, or `None` when cancelled.
    async fn assemble(
        &self,
        job: &Job,
        path: &std::path::Path,
        cancel: &AtomicBool,
    ) -> anyhow::Result<Option<String>> {
        let parts = self.coordinator.parts(&job.id).await?;
        let mut file = tokio::fs::File::create(path).await?;
        let mut hasher = blake3::Hasher::new();
        let mut offset = 0u64;
        for (start, len, rel) in parts {
            if cancel.load(Ordering::SeqCst) {
                return Ok(None);
            }
            anyhow::ensure!(start == offset, "the upload's parts leave a gap at byte {offset}");
            let mut stream = self
                .bucket
                .store
                .get(&self.bucket.path(&rel))
                .await
                .map_err(|e| anyhow::anyhow!("reading part {rel} at {}: {e}", self.bucket.endpoint))?
                .into_stream();
            let mut got = 0u64;
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(|e| anyhow::anyhow!("reading part {rel}: {e}"))?;
                hasher.update(&chunk);
                file.write_all(&chunk).await?;
                got += chunk.len() as u64;
            }
            anyhow::ensure!(got == len, "part {rel} holds {got} bytes, {len} expected");
            offset += len;
        }
        anyhow::ensure!(
            offset == job.input_bytes,
            "the upload's parts hold {offset} bytes, {} expected",
            job.input_bytes
        );
        file.sync_all().await?;
        Ok(Some(hasher.finalize().to_hex().to_string()))
    }

    /// The job and every change to it (read from the coordinator), until it ends.
    pub async fn subscribe(&self, id: &str) -> anyhow::Result<Option<watch::Receiver<Job>>> {
        let Some(first) = self.coordinator.job(id).await? else { return Ok(None) };
        let (tx, rx) = watch::channel(first);
        let (coordinator, shutdown, id) = (self.coordinator.clone(), self.shutdown.clone(), id.to_string());
        tokio::spawn(async move {
            while !tx.borrow().state.is_final() {
                tokio::select! {
                    () = tokio::time::sleep(EVENT_POLL) => {}
                    () = tx.closed() => return,
                    () = shutdown.cancelled() => return,
                }
                match coordinator.job(&id).await {
                    Ok(Some(job)) => {
                        tx.send_if_modified(|old| {
                            let changed = *old != job;
                            *old = job;
                            changed
                        });
                    }
                    Ok(None) => return,
                    Err(e) => {
                        tracing::warn!(job = %id, error = %format!("{e:#}"), "cannot read the job's progress")
                    }
                }
            }
        });
        Ok(Some(rx))
    }

    /// Stops claiming and asks running builds to stop (they are given back to the queue); waits
    /// for them up to `timeout`.
    pub async fn shutdown(&self, timeout: Duration) {
        self.tracker.close();
        if tokio::time::timeout(timeout, self.tracker.wait()).await.is_err() {
            tracing::warn!(
                "builds still running after {timeout:?}; other replicas take them over after the lease"
            );
        }
    }
}

#[derive(Clone, Default)]
struct Flags {
    user_cancelled: Arc<AtomicBool>,
    lease_lost: Arc<AtomicBool>,
}

/// Renews the lease and records progress a few times a lease; stops the build when the lease is
/// lost, a cancel was asked for, or the server shuts down.
async fn heartbeat(
    coordinator: Arc<Coordinator>,
    claim: Claim,
    progress: Arc<Mutex<Job>>,
    cancel: Arc<AtomicBool>,
    flags: Flags,
    stop: CancellationToken,
    shutdown: CancellationToken,
) {
    let every = (coordinator.lease / 3).clamp(Duration::from_millis(100), Duration::from_secs(1));
    let mut tick = crate::ticker::every(every).await;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = stop.cancelled() => return,
            () = shutdown.cancelled() => {
                cancel.store(true, Ordering::SeqCst);
                return;
            }
        }
        let snapshot = progress.lock().expect("progress lock").clone();
        match coordinator.heartbeat(&claim, &snapshot).await {
            Ok(Some(cancel_requested)) => {
                if cancel_requested {
                    flags.user_cancelled.store(true, Ordering::SeqCst);
                    cancel.store(true, Ordering::SeqCst);
                }
            }
            Ok(None) => {
                flags.lease_lost.store(true, Ordering::SeqCst);
                cancel.store(true, Ordering::SeqCst);
                return;
            }
            // Keeps trying: if the lease runs out meanwhile, publication is refused (fencing).
            Err(e) => {
                tracing::warn!(job = %claim.job.id, error = %format!("{e:#}"), "cannot renew the build's lease")
            }
        }
    }
}
