//! Build jobs: each complete upload becomes one job, run on a bounded pool of
//! blocking workers, reported through a `watch` channel (for SSE) and recorded
//! in `<store>/.jobs/<id>.json` (temp file + rename) at every state change.
//!
//! Restart recovery: a job recorded as queued or running whose upload is still
//! there is queued again (the build starts over: the store publishes only
//! complete scenes, so a killed build left nothing but a `.tmp-*` directory);
//! without its upload, or after [`MAX_ATTEMPTS`] interrupted starts, it is
//! marked failed with the reason.

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::{Semaphore, watch};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::catalog::{BuildInfo, Catalog, now_unix, write_build_info};
use crate::metrics::Metrics;
use crate::pipeline::progress::Progress;
use crate::pipeline::voxelize::Topology;
use crate::pipeline::{BuildError, BuildOptions, OnPublished, Resolution, build_scene_reporting};
use crate::uploads::{Uploads, write_json_atomic};

pub const JOBS_DIR: &str = ".jobs";
/// Starts of one job that may be cut short by a crash before it is given up:
/// a build that kills the server every time must not loop forever.
pub const MAX_ATTEMPTS: u32 = 5;
/// Unfinished resumable uploads older than this are removed at start.
pub const UPLOAD_EXPIRY_SECS: u64 = 7 * 24 * 3600;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_final(self) -> bool {
        matches!(self, JobState::Done | JobState::Failed | JobState::Cancelled)
    }

    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
}

/// A build job as `GET /api/jobs/{id}` shows it and `.jobs/<id>.json` keeps it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Job {
    /// Also the id of the upload it builds.
    pub id: String,
    /// The scene it publishes.
    pub scene_id: String,
    pub state: JobState,
    /// read, voxelize, lod or write while running.
    pub stage: Option<String>,
    /// Of the whole build, 0..=1.
    pub fraction: f64,
    /// Seconds left, estimated from the time so far; null until it can be guessed.
    pub eta_seconds: Option<f64>,
    pub triangles_per_second: f64,
    /// Why it failed or was cancelled.
    pub error: Option<String>,
    /// The uploaded file as the build reads it (`<scene>.<format>`).
    pub input_file: String,
    pub input_bytes: u64,
    /// Level-0 voxels an edge; null: matched to the scan (auto), at most `max_resolution`.
    #[serde(default)]
    pub resolution: Option<u32>,
    #[serde(default = "max_resolution")]
    pub max_resolution: u32,
    pub topology: String,
    pub created_at: u64,
    pub started_at: Option<u64>,
    pub finished_at: Option<u64>,
    /// Builds started, counting ones a crash or shutdown cut short.
    pub attempts: u32,
    /// With a coordinator: the replica building it now or last (`host/pid/n`).
    #[serde(default)]
    pub builder: Option<String>,
    /// With a coordinator: the blake3 of the input as the builder assembled it from the upload's parts.
    #[serde(default)]
    pub input_blake3: Option<String>,
}

impl Job {
    /// The build options this job asks for (resolution, cap, scene name, topology), cancelled
    /// through `cancel`; both the local runner and the cluster's builders start from these.
    pub fn build_options(&self, cancel: Arc<AtomicBool>) -> BuildOptions {
        BuildOptions {
            resolution: self.resolution.map_or(Resolution::Auto, Resolution::Explicit),
            max_resolution: self.max_resolution,
            name: Some(self.scene_id.clone()),
            topology: parse_topology(&self.topology).unwrap_or(Topology::Conservative),
            cancel: Some(cancel),
            ..Default::default()
        }
    }
}

pub fn parse_topology(name: &str) -> Option<Topology> {
    match name {
        "conservative" => Some(Topology::Conservative),
        "26-separating" => Some(Topology::Separating26),
        "6-separating" => Some(Topology::Separating6),
        _ => None,
    }
}

/// 16 lowercase hex digits: job and upload ids.
pub fn new_id() -> String {
    format!("{:016x}", rand::random::<u64>())
}

pub fn valid_job_id(id: &str) -> bool {
    id.len() == 16 && id.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("no job with id {0:?}")]
    NotFound(String),
    #[error("job {id} already ended ({state})")]
    Ended { id: String, state: &'static str },
    #[error("the coordinator is unavailable: {0}")]
    Unavailable(String),
}

struct JobHandle {
    tx: watch::Sender<Job>,
    /// The build's cancel flag: set by a user's cancel or by shutdown.
    cancel: Arc<AtomicBool>,
    user_cancelled: AtomicBool,
}

fn max_resolution() -> u32 {
    crate::pipeline::voxelize::MAX_RESOLUTION
}

pub struct JobManager {
    store: PathBuf,
    catalog: Arc<Catalog>,
    uploads: Uploads,
    metrics: Arc<Metrics>,
    jobs: Mutex<HashMap<String, Arc<JobHandle>>>,
    /// One build per scene id at a time: two publishes of one id must not interleave.
    scene_locks: Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
    workers: Arc<Semaphore>,
    tracker: TaskTracker,
    shutdown: CancellationToken,
}

#[derive(Debug, Default)]
pub struct Recovery {
    pub resumed: Vec<String>,
    pub failed: Vec<String>,
    pub removed_uploads: Vec<String>,
}

impl JobManager {
    pub fn new(
        catalog: Arc<Catalog>,
        metrics: Arc<Metrics>,
        workers: usize,
        shutdown: CancellationToken,
    ) -> Arc<JobManager> {
        let store = catalog.store().to_path_buf();
        Arc::new(JobManager {
            uploads: Uploads::new(&store),
            store,
            catalog,
            metrics,
            jobs: Mutex::new(HashMap::new()),
            scene_locks: Mutex::new(HashMap::new()),
            workers: Arc::new(Semaphore::new(workers.max(1))),
            tracker: TaskTracker::new(),
            shutdown,
        })
    }

    fn jobs_dir(&self) -> PathBuf {
        self.store.join(JOBS_DIR)
    }

    fn persist(&self, job: &Job) {
        let dir = self.jobs_dir();
        let result = fs::create_dir_all(&dir).and_then(|()| {
            write_json_atomic(
                &dir.join(format!("{}.json", job.id)),
                &serde_json::to_vec_pretty(job).expect("job serialises"),
            )
        });
        if let Err(e) = result {
            tracing::error!(job = %job.id, error = %e, "cannot record job state");
        }
    }

    pub fn input_path(&self, job: &Job) -> PathBuf {
        self.uploads.upload_dir(&job.id).join(&job.input_file)
    }

    /// Reads the job records of the store: queued and interrupted jobs start
    /// again, the rest are listed. Uploads that belong to no job and cannot
    /// be resumed (plain POSTs cut short, tus uploads older than a week) are
    /// removed. Call inside the runtime.
    pub fn recover(self: &Arc<Self>) -> Recovery {
        let mut recovery = Recovery::default();
        let mut known = std::collections::HashSet::new();
        let entries = fs::read_dir(self.jobs_dir()).into_iter().flatten().flatten();
        let mut records: Vec<Job> = Vec::new();
        for entry in entries {
            let path = entry.path();
            if path.extension().and_then(|e| e.to_str()) != Some("json") {
                let _ = fs::remove_file(&path); // temp files of an interrupted write
                continue;
            }
            match fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|b| serde_json::from_slice::<Job>(&b).map_err(|e| e.to_string()))
            {
                Ok(job) if valid_job_id(&job.id) => records.push(job),
                Ok(_) | Err(_) => {
                    tracing::warn!(path = %path.display(), "unreadable job record removed");
                    let _ = fs::remove_file(&path);
                }
            }
        }
        records.sort_by_key(|j| j.created_at);
        for mut job in records {
            known.insert(job.id.clone());
            if job.state.is_final() {
                // A crash between recording the end and removing the upload.
                self.uploads.remove(&job.id);
            } else {
                let reason = if !self.input_path(&job).is_file() {
                    Some("the server stopped during the build and the upload is gone".to_string())
                } else if job.attempts >= MAX_ATTEMPTS {
                    Some(format!("the build was interrupted {} times; giving up", job.attempts))
                } else {
                    None
                };
                match reason {
                    None => {
                        job.state = JobState::Queued;
                        job.stage = None;
                        job.fraction = 0.0;
                        job.eta_seconds = None;
                        self.persist(&job);
                        recovery.resumed.push(job.id.clone());
                        self.start(job);
                        continue;
                    }
                    Some(reason) => {
                        job.state = JobState::Failed;
                        job.error = Some(reason);
                        job.finished_at = Some(now_unix());
                        self.persist(&job);
                        self.uploads.remove(&job.id);
                        recovery.failed.push(job.id.clone());
                    }
                }
            }
            self.insert(job);
        }
        for id in self.uploads.ids() {
            if known.contains(&id) {
                continue;
            }
            match self.uploads.load(&id) {
                Some(record)
                    if record.resumable
                        && now_unix().saturating_sub(record.created_at) < UPLOAD_EXPIRY_SECS => {}
                _ => {
                    self.uploads.remove(&id);
                    recovery.removed_uploads.push(id);
                }
            }
        }
        recovery
    }

    fn insert(&self, job: Job) -> Arc<JobHandle> {
        let handle = Arc::new(JobHandle {
            tx: watch::Sender::new(job.clone()),
            cancel: Arc::new(AtomicBool::new(false)),
            user_cancelled: AtomicBool::new(false),
        });
        self.jobs.lock().expect("jobs lock").insert(job.id.clone(), handle.clone());
        handle
    }

    /// Records a new job and queues it.
    pub fn submit(self: &Arc<Self>, job: Job) -> Job {
        self.persist(&job);
        self.start(job.clone());
        job
    }

    fn start(self: &Arc<Self>, job: Job) {
        let handle = self.insert(job);
        self.metrics.jobs_queued.inc();
        let this = self.clone();
        self.tracker.spawn(async move { this.run(handle).await });
    }

    pub fn get(&self, id: &str) -> Option<Job> {
        self.jobs.lock().expect("jobs lock").get(id).map(|h| h.tx.borrow().clone())
    }

    /// All jobs, newest first.
    pub fn list(&self) -> Vec<Job> {
        let mut jobs: Vec<Job> =
            self.jobs.lock().expect("jobs lock").values().map(|h| h.tx.borrow().clone()).collect();
        jobs.sort_by(|a, b| b.created_at.cmp(&a.created_at).then(a.id.cmp(&b.id)));
        jobs
    }

    pub fn subscribe(&self, id: &str) -> Option<watch::Receiver<Job>> {
        self.jobs.lock().expect("jobs lock").get(id).map(|h| h.tx.subscribe())
    }

    /// Whether a queued or running job will publish `scene_id`.
    pub fn building(&self, scene_id: &str) -> bool {
        self.jobs.lock().expect("jobs lock").values().any(|h| {
            let j = h.tx.borrow();
            j.scene_id == scene_id && !j.state.is_final()
        })
    }

    /// Asks a job to stop; a queued job ends at once, a running one at the
    /// build's next check (it then publishes nothing).
    pub fn cancel(&self, id: &str) -> Result<Job, JobError> {
        let handle = self.jobs.lock().expect("jobs lock").get(id).cloned();
        let handle = handle.ok_or_else(|| JobError::NotFound(id.to_string()))?;
        let state = handle.tx.borrow().state;
        if state.is_final() {
            return Err(JobError::Ended { id: id.to_string(), state: state.name() });
        }
        handle.user_cancelled.store(true, Ordering::SeqCst);
        handle.cancel.store(true, Ordering::SeqCst);
        Ok(handle.tx.borrow().clone())
    }

    async fn run(self: Arc<Self>, h: Arc<JobHandle>) {
        let scene_id = h.tx.borrow().scene_id.clone();
        let scene_lock = self.scene_locks.lock().expect("scene locks").entry(scene_id).or_default().clone();
        let _scene = tokio::select! {
            g = scene_lock.lock_owned() => g,
            _ = self.shutdown.cancelled() => { self.metrics.jobs_queued.dec(); return }
        };
        let permit = tokio::select! {
            p = self.workers.clone().acquire_owned() => p.expect("the worker semaphore is never closed"),
            _ = self.shutdown.cancelled() => { self.metrics.jobs_queued.dec(); return } // stays queued on disk
        };
        self.metrics.jobs_queued.dec();
        if h.user_cancelled.load(Ordering::SeqCst) {
            self.finish(&h, JobState::Cancelled, Some("cancelled before it started".into()), 0.0);
            return;
        }
        h.tx.send_modify(|j| {
            j.state = JobState::Running;
            j.started_at = Some(now_unix());
            j.attempts += 1;
            j.error = None;
        });
        let job = h.tx.borrow().clone();
        self.persist(&job);
        self.metrics.jobs_running.inc();
        self.metrics.builds_started.inc();
        let started = Instant::now();
        let input = self.input_path(&job);
        let store = self.store.clone();
        let opts = BuildOptions {
            // Readers switch to the new manifest before the replaced scene's blocks are removed.
            on_published: Some(OnPublished(Arc::new({
                let catalog = self.catalog.clone();
                move |id: &str| {
                    if let Err(e) = catalog.refresh(id) {
                        tracing::warn!(scene = %id, error = %e, "cannot re-read the scene just published");
                    }
                }
            }))),
            ..job.build_options(h.cancel.clone())
        };
        let tx = h.tx.clone();
        let result = tokio::task::spawn_blocking(move || {
            let report = move |p: Progress| {
                let elapsed = started.elapsed().as_secs_f64();
                tx.send_modify(|j| {
                    j.stage = Some(p.stage.name().to_string());
                    j.fraction = p.fraction;
                    j.triangles_per_second = p.triangles_per_second;
                    j.eta_seconds = (p.fraction > 0.01).then(|| elapsed * (1.0 - p.fraction) / p.fraction);
                });
            };
            build_scene_reporting(&input, &store, &opts, &report)
        })
        .await;
        drop(permit);
        self.metrics.jobs_running.dec();
        let seconds = started.elapsed().as_secs_f64();
        match result {
            Ok(Ok(report)) => {
                let info = BuildInfo {
                    built_at: Some(now_unix()),
                    build_seconds: Some(report.seconds),
                    display_name: None,
                };
                if let Err(e) = write_build_info(&report.scene_dir, &info) {
                    tracing::warn!(scene = %report.id, error = %e, "cannot write scene.json");
                }
                match self.catalog.refresh(&report.id) {
                    Ok(_) => self.finish(&h, JobState::Done, None, seconds),
                    Err(e) => self.finish(&h, JobState::Failed, Some(e.to_string()), seconds),
                }
            }
            Ok(Err(BuildError::Cancelled)) if !h.user_cancelled.load(Ordering::SeqCst) => {
                // Shutdown: leave it queued on disk so the next start builds it again.
                h.tx.send_modify(|j| {
                    j.state = JobState::Queued;
                    j.stage = None;
                    j.fraction = 0.0;
                    j.eta_seconds = None;
                });
                self.persist(&h.tx.borrow().clone());
                tracing::info!(job = %job.id, "build interrupted by shutdown; it resumes on the next start");
            }
            Ok(Err(BuildError::Cancelled)) => {
                self.finish(&h, JobState::Cancelled, Some("cancelled".into()), seconds)
            }
            Ok(Err(e)) => self.finish(&h, JobState::Failed, Some(e.to_string()), seconds),
            Err(e) => self.finish(&h, JobState::Failed, Some(format!("the build crashed: {e}")), seconds),
        }
    }

    fn finish(&self, h: &JobHandle, state: JobState, error: Option<String>, seconds: f64) {
        h.tx.send_modify(|j| {
            j.state = state;
            j.error = error;
            j.finished_at = Some(now_unix());
            j.eta_seconds = None;
            if state == JobState::Done {
                j.fraction = 1.0;
            }
        });
        let job = h.tx.borrow().clone();
        // The record first: once it says the job ended, the upload is no longer needed.
        self.persist(&job);
        self.uploads.remove(&job.id);
        self.metrics
            .job_seconds
            .get_or_create(&Metrics::labels(&[("outcome", state.name())]))
            .observe(seconds);
        match state {
            JobState::Done => tracing::info!(job = %job.id, scene = %job.scene_id, seconds, "build done"),
            _ => {
                tracing::warn!(job = %job.id, scene = %job.scene_id, state = state.name(), error = ?job.error, "build ended")
            }
        }
    }

    /// Stops taking work and asks running builds to stop (they stay queued on
    /// disk); waits for them up to `timeout`.
    pub async fn shutdown(&self, timeout: Duration) {
        for h in self.jobs.lock().expect("jobs lock").values() {
            h.cancel.store(true, Ordering::SeqCst);
        }
        self.tracker.close();
        if tokio::time::timeout(timeout, self.tracker.wait()).await.is_err() {
            tracing::warn!("builds still running after {timeout:?}; they resume on the next start");
        }
    }

    pub fn store(&self) -> &Path {
        &self.store
    }
}

/// The jobs a server answers for: its own (a local store), or every replica's through the
/// coordinator (a bucket with `--coordinator`).
#[derive(Clone)]
pub enum Jobs {
    Local(Arc<JobManager>),
    Cluster(Arc<crate::cluster_jobs::ClusterJobs>),
}

fn unavailable(e: anyhow::Error) -> JobError {
    JobError::Unavailable(format!("{e:#}"))
}

impl Jobs {
    pub async fn get(&self, id: &str) -> Result<Option<Job>, JobError> {
        match self {
            Jobs::Local(m) => Ok(m.get(id)),
            Jobs::Cluster(c) => c.coordinator.job(id).await.map_err(unavailable),
        }
    }

    /// All jobs, newest first.
    pub async fn list(&self) -> Result<Vec<Job>, JobError> {
        match self {
            Jobs::Local(m) => Ok(m.list()),
            Jobs::Cluster(c) => c.coordinator.jobs().await.map_err(unavailable),
        }
    }

    /// Whether a queued or running job will publish `scene_id`.
    pub async fn building(&self, scene_id: &str) -> Result<bool, JobError> {
        match self {
            Jobs::Local(m) => Ok(m.building(scene_id)),
            Jobs::Cluster(c) => c.coordinator.building(scene_id).await.map_err(unavailable),
        }
    }

    pub async fn cancel(&self, id: &str) -> Result<Job, JobError> {
        match self {
            Jobs::Local(m) => m.cancel(id),
            Jobs::Cluster(c) => match c.coordinator.cancel(id).await {
                Ok((job, ended_now)) => {
                    if ended_now {
                        // Queued: it never ran, so its upload goes now.
                        c.coordinator.remove_upload(c.bucket(), id).await;
                    }
                    Ok(job)
                }
                Err(crate::coordinator::CancelError::NotFound) => Err(JobError::NotFound(id.to_string())),
                Err(crate::coordinator::CancelError::Ended(state)) => {
                    Err(JobError::Ended { id: id.to_string(), state })
                }
                Err(crate::coordinator::CancelError::Failed(e)) => Err(unavailable(e)),
            },
        }
    }

    pub async fn subscribe(&self, id: &str) -> Result<Option<watch::Receiver<Job>>, JobError> {
        match self {
            Jobs::Local(m) => Ok(m.subscribe(id)),
            Jobs::Cluster(c) => c.subscribe(id).await.map_err(unavailable),
        }
    }

    pub async fn shutdown(&self, timeout: Duration) {
        match self {
            Jobs::Local(m) => m.shutdown(timeout).await,
            Jobs::Cluster(c) => c.shutdown(timeout).await,
        }
    }
}
