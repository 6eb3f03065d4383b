//! The replicas' coordinator: build jobs with leases, and tus upload state, in PostgreSQL.
//!
//! Why PostgreSQL and not the bucket: a claim must be atomic, and Garage 2.5.0 answers a `PUT`
//! with `If-None-Match: *` on an existing key by overwriting it, so a create-if-absent object is no
//! lock there. Row locks are.
//!
//! - `voxstream_jobs`: one row a job, with `state` (queued, running, done, failed, cancelled), the
//!   lease (`owner`, a `lease` number raised at every claim, `lease_until`), `attempts` (builds
//!   started) and `error`; `job` holds the JSON the API shows (progress included). A partial unique
//!   index allows one queued or running job per scene id.
//! - Claiming is `UPDATE … WHERE id = (SELECT … FOR UPDATE SKIP LOCKED LIMIT 1) RETURNING …` over
//!   queued jobs and running jobs whose lease expired (their builder died): two replicas never
//!   claim the same row, and a dead builder's job is taken over once its lease runs out.
//! - The builder renews its lease (the heartbeat, a third of the lease) while it builds; a renewal
//!   that matches no row means the lease was taken over, and the build stops without publishing.
//! - Fencing: the manifest (the scene's one mutable object) is written inside a transaction that
//!   first locks the job's row and checks that this replica still holds the same lease, unexpired;
//!   the job is marked done in that transaction. While the row is locked nobody can take it over
//!   (claims skip locked rows). What remains: a builder cut off from PostgreSQL (its connection
//!   dropped, so its lock released) that still reaches the bucket may write its manifest after a
//!   new owner was given the job. Both build the same input with the same options, builds are
//!   deterministic (byte-identical, tested) and packs and pages are content-addressed, so both
//!   manifests are the same bytes naming the same objects: the late write changes nothing.
//! - Uploads: `voxstream_uploads` holds each tus upload's record, length, bytes received and its
//!   first bytes (to tell the format); the bytes are objects `<prefix>/.uploads/<id>/<offset>-<n>`
//!   in the bucket, listed in `voxstream_upload_parts`. A PATCH holds the upload's row lock for its
//!   whole body, so PATCHes on one upload are serialised across replicas, and its parts become
//!   visible only when it commits.
//! - Scene edits (rename, delete) and garbage collection are fenced by a transaction-scoped
//!   advisory lock per scene id (`pg_advisory_xact_lock(hashtextextended('voxstream-scene:' || id,
//!   0))`): the edit takes it (for both ids of a rename, in sorted order), checks that no job of
//!   those ids is queued or running, does its bucket work and commits. Queuing a job (an upload's
//!   completion) and a build's publication take the same lock, so no job of the scene can be
//!   queued or published while the edit runs (the upload's last PATCH answers 409 if the lock is
//!   held longer than its lock timeout). As with publication, a replica cut off from PostgreSQL
//!   loses its lock with its connection; its edit may then overlap a build queued meanwhile.
//! - One garbage collector at a time across replicas: a transaction-scoped advisory lock
//!   ([`GC_LOCK`]) tried, not waited for; a replica that does not get it skips its pass.
//!
//! Connection settings: `--coordinator postgres://user@host:port/db` (no password in it: a command
//! line shows in `ps` and logs); the password comes from `PGPASSWORD` in the environment or in the
//! file `VOXSTREAM_PG_ENV_FILE` names, as the `AWS_*` settings do. Messages name
//! `postgres://user@host:port/db` only.

use std::time::Duration;

use anyhow::{Context, bail};
use axum::body::Bytes;
use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime};
use futures_util::{Stream, StreamExt};
use prometheus_client::metrics::counter::Counter;
use tokio_postgres::NoTls;
use tokio_postgres::config::Host;
use tokio_postgres::error::SqlState;

use crate::jobs::{Job, JobState, valid_job_id};
use crate::objstore::Bucket;
use crate::uploads::UploadRecord;

/// The file of `KEY=value` lines the coordinator's password may come from (`PGPASSWORD=…`).
pub const PG_ENV_FILE_VAR: &str = "VOXSTREAM_PG_ENV_FILE";
/// Upload bytes are stored as bucket objects of at most this size (a PATCH's body is cut into
/// parts of it): what one PATCH holds in memory.
pub const PART_BYTES: usize = 8 << 20;
/// First bytes of an upload kept in its row, enough to tell its format.
const HEAD_BYTES: usize = 64;
/// How long a request waits for another replica's PATCH on the same upload before answering 423.
const UPLOAD_LOCK_WAIT: &str = "10s";
/// Serialises schema creation between replicas starting together.
const SCHEMA_LOCK: i64 = 0x0076_6f78_7374_726d; // "voxstrm"
/// Held by the replica collecting garbage (see [`Coordinator::with_gc_lock`]).
pub const GC_LOCK: i64 = 0x0076_6f78_6763_6c6b; // "voxgclk"
/// How long a scene edit waits for another edit or a collection of the same scene.
const SCENE_LOCK_WAIT: &str = "10s";
/// The advisory lock key of a scene id (collisions only serialise two ids needlessly).
const SCENE_LOCK_SQL: &str =
    "SELECT pg_advisory_xact_lock(hashtextextended('voxstream-scene:' || $1::text, 0))";
const SCENE_TRY_LOCK_SQL: &str =
    "SELECT pg_try_advisory_xact_lock(hashtextextended('voxstream-scene:' || $1::text, 0))";

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS voxstream_jobs (
    id text PRIMARY KEY,
    scene_id text NOT NULL,
    state text NOT NULL,
    owner text,
    lease bigint NOT NULL DEFAULT 0,
    lease_until timestamptz,
    attempts integer NOT NULL DEFAULT 0,
    error text,
    cancel_requested boolean NOT NULL DEFAULT false,
    created_at bigint NOT NULL,
    started_at bigint,
    finished_at bigint,
    job text NOT NULL
);
CREATE UNIQUE INDEX IF NOT EXISTS voxstream_jobs_one_build_per_scene
    ON voxstream_jobs (scene_id) WHERE state IN ('queued', 'running');
CREATE TABLE IF NOT EXISTS voxstream_uploads (
    id text PRIMARY KEY,
    record text NOT NULL,
    length bigint,
    received bigint NOT NULL DEFAULT 0,
    head bytea NOT NULL DEFAULT ''::bytea,
    complete boolean NOT NULL DEFAULT false,
    created_at bigint NOT NULL
);
CREATE TABLE IF NOT EXISTS voxstream_upload_parts (
    upload_id text NOT NULL REFERENCES voxstream_uploads (id) ON DELETE CASCADE,
    start_offset bigint NOT NULL,
    len bigint NOT NULL,
    object text NOT NULL,
    PRIMARY KEY (upload_id, start_offset)
);
";

/// A connection pool to the coordinator, and this replica's name in leases.
pub struct Coordinator {
    pool: Pool,
    /// `postgres://user@host:port/db`, for messages (never the password).
    pub endpoint: String,
    /// `host/pid/random`: unique per process, so a restarted replica never holds a dead one's lease.
    pub owner: String,
    /// How long a claim lasts without renewal (`--lease-secs`).
    pub lease: Duration,
}

/// A claimed job: the lease that fences its publication.
#[derive(Debug, Clone)]
pub struct Claim {
    pub job: Job,
    pub lease: i64,
}

/// What the error chain says, each cause once.
fn chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let more = s.to_string();
        if !text.contains(&more) {
            text = format!("{text}: {more}");
        }
        source = s.source();
    }
    text
}

/// The cause with a hint for the usual mistakes.
fn explain(e: &(dyn std::error::Error + 'static)) -> String {
    let text = chain(e);
    let hint = if text.contains("password authentication failed") || text.contains("no password") {
        " (credentials refused: check the user in --coordinator and PGPASSWORD)"
    } else if text.contains("does not exist") {
        " (create the database and role, or fix their names in --coordinator)"
    } else if text.contains("onnect") || text.contains("refused") || text.contains("timed out") {
        " (cannot connect: check the host and port of --coordinator)"
    } else {
        ""
    };
    format!("{text}{hint}")
}

/// `PGPASSWORD` from the environment, else from the file `VOXSTREAM_PG_ENV_FILE` names.
fn password() -> anyhow::Result<Option<String>> {
    if let Ok(p) = std::env::var("PGPASSWORD") {
        return Ok(Some(p));
    }
    let Some(file) = std::env::var_os(PG_ENV_FILE_VAR) else { return Ok(None) };
    let text = std::fs::read_to_string(&file).with_context(|| {
        format!("cannot read {PG_ENV_FILE_VAR} {}", std::path::Path::new(&file).display())
    })?;
    Ok(crate::objstore::parse_env_file(&text)
        .into_iter()
        .rev()
        .find(|(k, _)| k == "PGPASSWORD")
        .map(|(_, v)| v))
}

/// `postgres://user@host:port/db` of a parsed configuration.
fn describe(config: &tokio_postgres::Config) -> String {
    let hosts: Vec<String> = config
        .get_hosts()
        .iter()
        .enumerate()
        .map(|(i, h)| {
            let host = match h {
                Host::Tcp(name) => name.clone(),
                Host::Unix(path) => path.display().to_string(),
            };
            match config.get_ports().get(i).or(config.get_ports().first()) {
                Some(port) => format!("{host}:{port}"),
                None => host,
            }
        })
        .collect();
    let user = config.get_user().map(|u| format!("{u}@")).unwrap_or_default();
    format!("postgres://{user}{}/{}", hosts.join(","), config.get_dbname().unwrap_or(""))
}

fn db(e: tokio_postgres::Error) -> anyhow::Error {
    anyhow::anyhow!("{}", explain(&e))
}

impl Coordinator {
    /// Connects to `url` (password from `PGPASSWORD` or `VOXSTREAM_PG_ENV_FILE`), creates the
    /// tables when missing, all within `deadline`. Errors name the endpoint and the cause.
    pub async fn connect(url: &str, lease: Duration, deadline: Duration) -> anyhow::Result<Coordinator> {
        let mut config: tokio_postgres::Config = url.parse().map_err(|e| {
            anyhow::anyhow!("--coordinator is not a postgres://user@host:port/database URL: {e}")
        })?;
        let endpoint = describe(&config);
        if config.get_password().is_some() {
            bail!(
                "--coordinator {endpoint}: the URL holds a password; give it in PGPASSWORD (environment) \
                 or in the file {PG_ENV_FILE_VAR} names, never on the command line"
            );
        }
        if config.get_hosts().is_empty() {
            bail!("--coordinator {endpoint}: no host (postgres://user@host:port/database)");
        }
        if let Some(p) = password()? {
            config.password(p);
        }
        config.application_name("voxstream").connect_timeout(deadline);
        let manager =
            Manager::from_config(config, NoTls, ManagerConfig { recycling_method: RecyclingMethod::Fast });
        let pool = Pool::builder(manager)
            .max_size(16)
            .runtime(Runtime::Tokio1)
            .create_timeout(Some(deadline))
            .wait_timeout(Some(Duration::from_secs(30)))
            .build()
            .map_err(|e| anyhow::anyhow!("coordinator {endpoint}: {e}"))?;
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "replica".into());
        let owner = format!("{host}/{}/{:04x}", std::process::id(), rand::random::<u16>());
        let coordinator = Coordinator { pool, endpoint, owner, lease };
        match tokio::time::timeout(deadline, coordinator.create_schema()).await {
            Err(_) => bail!("coordinator {} did not answer within {deadline:?}", coordinator.endpoint),
            Ok(Err(e)) => bail!("coordinator {}: {e:#}", coordinator.endpoint),
            Ok(Ok(())) => Ok(coordinator),
        }
    }

    async fn client(&self) -> anyhow::Result<deadpool_postgres::Object> {
        self.pool.get().await.map_err(|e| anyhow::anyhow!("{}", explain(&e)))
    }

    async fn create_schema(&self) -> anyhow::Result<()> {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&SCHEMA_LOCK]).await.map_err(db)?;
        tx.batch_execute(SCHEMA).await.map_err(db)?;
        tx.commit().await.map_err(db)
    }

    fn lease_secs(&self) -> f64 {
        self.lease.as_secs_f64()
    }

    // ---- jobs ---------------------------------------------------------------------------------

    /// The job as the API shows it: its JSON with the row's state, attempts, error and owner.
    fn job_of(row: &tokio_postgres::Row) -> anyhow::Result<Job> {
        let json: String = row.get("job");
        let mut job: Job =
            serde_json::from_str(&json).context("a job record in the coordinator is unreadable")?;
        let state: String = row.get("state");
        job.state = match state.as_str() {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "done" => JobState::Done,
            "failed" => JobState::Failed,
            _ => JobState::Cancelled,
        };
        job.attempts = row.get::<_, i32>("attempts").max(0) as u32;
        job.error = row.get("error");
        job.builder = row.get("owner");
        job.started_at = row.get::<_, Option<i64>>("started_at").map(|t| t as u64);
        job.finished_at = row.get::<_, Option<i64>>("finished_at").map(|t| t as u64);
        if job.state.is_final() {
            job.eta_seconds = None;
            if job.state == JobState::Done {
                job.fraction = 1.0;
            }
        }
        Ok(job)
    }

    const JOB_COLUMNS: &'static str = "id, job, state, attempts, error, owner, started_at, finished_at";

    pub async fn job(&self, id: &str) -> anyhow::Result<Option<Job>> {
        let client = self.client().await?;
        let sql = format!("SELECT {} FROM voxstream_jobs WHERE id = $1", Self::JOB_COLUMNS);
        let row = client.query_opt(&sql, &[&id]).await.map_err(db)?;
        row.as_ref().map(Self::job_of).transpose()
    }

    /// The newest jobs first (at most 1000).
    pub async fn jobs(&self) -> anyhow::Result<Vec<Job>> {
        let client = self.client().await?;
        let sql = format!(
            "SELECT {} FROM voxstream_jobs ORDER BY created_at DESC, id LIMIT 1000",
            Self::JOB_COLUMNS
        );
        client.query(&sql, &[]).await.map_err(db)?.iter().map(Self::job_of).collect()
    }

    /// Whether a queued or running job will publish `scene_id`.
    pub async fn building(&self, scene_id: &str) -> anyhow::Result<bool> {
        let client = self.client().await?;
        let row = client
            .query_opt(
                "SELECT 1 FROM voxstream_jobs WHERE scene_id = $1 AND state IN ('queued', 'running') LIMIT 1",
                &[&scene_id],
            )
            .await
            .map_err(db)?;
        Ok(row.is_some())
    }

    /// Queued jobs, for the metrics.
    pub async fn queued(&self) -> anyhow::Result<i64> {
        let client = self.client().await?;
        let row = client
            .query_one("SELECT count(*) FROM voxstream_jobs WHERE state = 'queued'", &[])
            .await
            .map_err(db)?;
        Ok(row.get(0))
    }

    /// Cancels a job: a queued one ends at once (the job and `true`), a running one is flagged
    /// and its builder stops at its next heartbeat (the job and `false`).
    pub async fn cancel(&self, id: &str) -> Result<(Job, bool), CancelError> {
        let client = self.client().await.map_err(CancelError::Failed)?;
        let sql = format!(
            "UPDATE voxstream_jobs SET cancel_requested = true,
                 error = CASE WHEN state = 'queued' THEN 'cancelled before it started' ELSE error END,
                 finished_at = CASE WHEN state = 'queued' THEN $2 ELSE finished_at END,
                 state = CASE WHEN state = 'queued' THEN 'cancelled' ELSE state END
             WHERE id = $1 AND state IN ('queued', 'running')
             RETURNING {}",
            Self::JOB_COLUMNS
        );
        let now = crate::catalog::now_unix() as i64;
        if let Some(row) =
            client.query_opt(&sql, &[&id, &now]).await.map_err(|e| CancelError::Failed(db(e)))?
        {
            let job = Self::job_of(&row).map_err(CancelError::Failed)?;
            let ended_now = job.state == JobState::Cancelled;
            return Ok((job, ended_now));
        }
        match self.job(id).await.map_err(CancelError::Failed)? {
            Some(job) => Err(CancelError::Ended(job.state.name())),
            None => Err(CancelError::NotFound),
        }
    }

    /// Ends running jobs whose builders died too often (lease expired, [`crate::jobs::MAX_ATTEMPTS`]
    /// starts) and cancelled ones whose builder died; returns their ids (their uploads can go).
    pub async fn sweep(&self) -> anyhow::Result<Vec<String>> {
        let client = self.client().await?;
        let now = crate::catalog::now_unix() as i64;
        let max = crate::jobs::MAX_ATTEMPTS as i32;
        let rows = client
            .query(
                "UPDATE voxstream_jobs SET
                     state = CASE WHEN cancel_requested THEN 'cancelled' ELSE 'failed' END,
                     error = CASE WHEN cancel_requested THEN 'cancelled'
                         ELSE 'the build was interrupted ' || attempts || ' times (the replica building it \
                               stopped renewing its lease each time); giving up' END,
                     lease_until = NULL, finished_at = $1
                 WHERE (state = 'running' AND lease_until < now() AND (attempts >= $2 OR cancel_requested))
                 RETURNING id",
                &[&now, &max],
            )
            .await
            .map_err(db)?;
        Ok(rows.iter().map(|r| r.get(0)).collect())
    }

    /// Claims the oldest queued job, or a running one whose lease expired (its builder died).
    pub async fn claim(&self) -> anyhow::Result<Option<Claim>> {
        let client = self.client().await?;
        let now = crate::catalog::now_unix() as i64;
        let max = crate::jobs::MAX_ATTEMPTS as i32;
        let sql = format!(
            "UPDATE voxstream_jobs SET state = 'running', owner = $1, lease = lease + 1,
                 lease_until = now() + make_interval(secs => $2), attempts = attempts + 1,
                 started_at = $3, error = NULL
             WHERE id = (
                 SELECT id FROM voxstream_jobs
                 WHERE (state = 'queued' OR (state = 'running' AND lease_until < now()))
                     AND NOT cancel_requested AND attempts < $4
                 ORDER BY created_at, id
                 LIMIT 1
                 FOR UPDATE SKIP LOCKED)
             RETURNING lease, {}",
            Self::JOB_COLUMNS
        );
        let row = client.query_opt(&sql, &[&self.owner, &self.lease_secs(), &now, &max]).await.map_err(db)?;
        match row {
            None => Ok(None),
            Some(row) => Ok(Some(Claim { job: Self::job_of(&row)?, lease: row.get("lease") })),
        }
    }

    /// Renews the lease and records the job's progress. `Ok(None)`: the lease is gone (taken over
    /// after it expired, or the job ended); `Ok(Some(cancel))`: still ours, and whether a cancel
    /// was asked for.
    pub async fn heartbeat(&self, claim: &Claim, progress: &Job) -> anyhow::Result<Option<bool>> {
        let client = self.client().await?;
        let json = serde_json::to_string(progress).expect("job serialises");
        let row = client
            .query_opt(
                "UPDATE voxstream_jobs SET lease_until = now() + make_interval(secs => $4), job = $5
                 WHERE id = $1 AND owner = $2 AND lease = $3 AND state = 'running'
                 RETURNING cancel_requested",
                &[&claim.job.id, &self.owner, &claim.lease, &self.lease_secs(), &json],
            )
            .await
            .map_err(db)?;
        Ok(row.map(|r| r.get(0)))
    }

    /// Fenced publication: locks the job's row, checks the lease is still this replica's and
    /// unexpired, runs `publish` (the manifest PUT) and marks the job done, in one transaction.
    pub async fn publish<F>(&self, claim: &Claim, done: &Job, publish: F) -> Result<(), PublishError>
    where
        F: std::future::Future<Output = anyhow::Result<()>>,
    {
        let mut client = self.client().await.map_err(PublishError::Failed)?;
        let tx = client.transaction().await.map_err(|e| PublishError::Failed(db(e)))?;
        let held = tx
            .query_opt(
                "SELECT 1 FROM voxstream_jobs
                 WHERE id = $1 AND owner = $2 AND lease = $3 AND state = 'running' AND lease_until > now()
                 FOR UPDATE",
                &[&done.id, &self.owner, &claim.lease],
            )
            .await
            .map_err(|e| PublishError::Failed(db(e)))?;
        if held.is_none() {
            return Err(PublishError::LeaseLost);
        }
        // A rename or delete of the scene cannot start while a job of it exists, but a collection
        // may hold the scene's lock for a moment: publish after it.
        tx.execute(SCENE_LOCK_SQL, &[&done.scene_id]).await.map_err(|e| PublishError::Failed(db(e)))?;
        publish.await.map_err(PublishError::Failed)?;
        let json = serde_json::to_string(done).expect("job serialises");
        let now = crate::catalog::now_unix() as i64;
        tx.execute(
            "UPDATE voxstream_jobs SET state = 'done', error = NULL, lease_until = NULL, finished_at = $2, job = $3
             WHERE id = $1",
            &[&done.id, &now, &json],
        )
        .await
        .map_err(|e| PublishError::Failed(db(e)))?;
        tx.commit().await.map_err(|e| PublishError::Failed(db(e)))
    }

    /// Ends a claimed job as failed or cancelled, if the lease is still ours.
    pub async fn finish(&self, claim: &Claim, job: &Job) -> anyhow::Result<bool> {
        let client = self.client().await?;
        let json = serde_json::to_string(job).expect("job serialises");
        let now = crate::catalog::now_unix() as i64;
        let n = client
            .execute(
                "UPDATE voxstream_jobs SET state = $4, error = $5, lease_until = NULL, finished_at = $6, job = $7
                 WHERE id = $1 AND owner = $2 AND lease = $3 AND state = 'running'",
                &[&job.id, &self.owner, &claim.lease, &job.state.name(), &job.error, &now, &json],
            )
            .await
            .map_err(db)?;
        Ok(n == 1)
    }

    /// Gives a claimed job back to the queue (this replica is shutting down): another replica
    /// takes it at once instead of after the lease.
    pub async fn release(&self, claim: &Claim) -> anyhow::Result<()> {
        let client = self.client().await?;
        client
            .execute(
                "UPDATE voxstream_jobs SET state = 'queued', owner = NULL, lease_until = NULL
                 WHERE id = $1 AND owner = $2 AND lease = $3 AND state = 'running'",
                &[&claim.job.id, &self.owner, &claim.lease],
            )
            .await
            .map_err(db)?;
        Ok(())
    }

    // ---- scene edits and garbage collection ---------------------------------------------------

    /// Runs `edit` holding the advisory locks of `ids` (sorted, so two edits never deadlock) in one
    /// transaction, after checking that no job of any of them is queued or running. With
    /// `wait == false` a lock held elsewhere is [`SceneLockError::Busy`] at once (the collector
    /// skips such scenes); otherwise it is waited for up to 10 s.
    pub async fn with_scenes_locked<F, T>(
        &self,
        ids: &[&str],
        wait: bool,
        edit: F,
    ) -> Result<T, SceneLockError>
    where
        F: std::future::Future<Output = T>,
    {
        let failed = |e: anyhow::Error| SceneLockError::Failed(format!("{e:#}"));
        let mut client = self.client().await.map_err(failed)?;
        let tx = client.transaction().await.map_err(|e| failed(db(e)))?;
        tx.batch_execute(&format!("SET LOCAL lock_timeout = '{SCENE_LOCK_WAIT}'"))
            .await
            .map_err(|e| failed(db(e)))?;
        let mut sorted: Vec<&str> = ids.to_vec();
        sorted.sort_unstable();
        sorted.dedup();
        for id in &sorted {
            if wait {
                match tx.execute(SCENE_LOCK_SQL, &[id]).await {
                    Ok(_) => {}
                    Err(e) if e.code() == Some(&SqlState::LOCK_NOT_AVAILABLE) => {
                        return Err(SceneLockError::Busy(id.to_string()));
                    }
                    Err(e) => return Err(failed(db(e))),
                }
            } else {
                let got: bool =
                    tx.query_one(SCENE_TRY_LOCK_SQL, &[id]).await.map_err(|e| failed(db(e)))?.get(0);
                if !got {
                    return Err(SceneLockError::Busy(id.to_string()));
                }
            }
        }
        let ids_owned: Vec<String> = sorted.iter().map(|s| s.to_string()).collect();
        let building = tx
            .query_opt(
                "SELECT scene_id FROM voxstream_jobs WHERE scene_id = ANY($1) AND state IN ('queued', 'running') LIMIT 1",
                &[&ids_owned],
            )
            .await
            .map_err(|e| failed(db(e)))?;
        if let Some(row) = building {
            return Err(SceneLockError::Building(row.get(0)));
        }
        let out = edit.await;
        tx.commit().await.map_err(|e| failed(db(e)))?;
        Ok(out)
    }

    /// Runs `collect` if no other replica is collecting (`Ok(None)` when one is).
    pub async fn with_gc_lock<F, T>(&self, collect: F) -> anyhow::Result<Option<T>>
    where
        F: std::future::Future<Output = T>,
    {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        let got: bool =
            tx.query_one("SELECT pg_try_advisory_xact_lock($1)", &[&GC_LOCK]).await.map_err(db)?.get(0);
        if !got {
            return Ok(None);
        }
        let out = collect.await;
        tx.commit().await.map_err(db)?;
        Ok(Some(out))
    }

    /// The ids of uploads that have a record (unfinished, or complete with their job not ended).
    pub async fn upload_ids(&self) -> anyhow::Result<Vec<String>> {
        let client = self.client().await?;
        let rows = client.query("SELECT id FROM voxstream_uploads", &[]).await.map_err(db)?;
        Ok(rows.iter().map(|r| r.get(0)).collect())
    }

    // ---- uploads ------------------------------------------------------------------------------

    pub async fn create_upload(&self, record: &UploadRecord) -> anyhow::Result<()> {
        let client = self.client().await?;
        let json = serde_json::to_string(record).expect("upload record serialises");
        let length = record.length.map(|l| l as i64);
        client
            .execute(
                "INSERT INTO voxstream_uploads (id, record, length, created_at) VALUES ($1, $2, $3, $4)",
                &[&record.id, &json, &length, &(record.created_at as i64)],
            )
            .await
            .map_err(db)?;
        Ok(())
    }

    /// An upload's record, bytes received and whether it is complete (its job then exists).
    pub async fn upload(&self, id: &str) -> anyhow::Result<Option<UploadStatus>> {
        if !valid_job_id(id) {
            return Ok(None);
        }
        let client = self.client().await?;
        let row = client
            .query_opt("SELECT record, received, complete FROM voxstream_uploads WHERE id = $1", &[&id])
            .await
            .map_err(db)?;
        row.map(|row| {
            let record: UploadRecord = serde_json::from_str(row.get::<_, &str>(0))
                .context("an upload record in the coordinator is unreadable")?;
            Ok(UploadStatus { record, received: row.get::<_, i64>(1) as u64, complete: row.get(2) })
        })
        .transpose()
    }

    /// Appends `body` to upload `id` at `claimed` (its offset so far), never past `limit` bytes,
    /// holding the upload's row lock throughout; parts of at most [`PART_BYTES`] go to the bucket.
    /// What arrived before a cut connection is kept (committed). When the upload is complete,
    /// `make_job` turns it into the job inserted in the same transaction (its `Err`: the upload
    /// cannot be built, and is removed).
    #[allow(clippy::too_many_arguments)]
    pub async fn append<S, E>(
        &self,
        bucket: &Bucket,
        id: &str,
        claimed: Option<u64>,
        limit: u64,
        body: S,
        idle: Duration,
        received_counter: &Counter,
        make_job: impl FnOnce(&UploadRecord, &[u8], u64) -> Result<Job, String>,
    ) -> Result<Appended, AppendError>
    where
        S: Stream<Item = Result<Bytes, E>> + Unpin,
        E: std::fmt::Display,
    {
        let failed = |e: anyhow::Error| AppendError::Failed(format!("{e:#}"));
        let mut client = self.client().await.map_err(failed)?;
        let tx = client.transaction().await.map_err(|e| failed(db(e)))?;
        tx.batch_execute(&format!("SET LOCAL lock_timeout = '{UPLOAD_LOCK_WAIT}'"))
            .await
            .map_err(|e| failed(db(e)))?;
        let row = match tx
            .query_opt(
                "SELECT record, received, head, complete FROM voxstream_uploads WHERE id = $1 FOR UPDATE",
                &[&id],
            )
            .await
        {
            Ok(row) => row,
            Err(e) if e.code() == Some(&SqlState::LOCK_NOT_AVAILABLE) => return Err(AppendError::Busy),
            Err(e) => return Err(failed(db(e))),
        };
        let Some(row) = row else { return Err(AppendError::NotFound) };
        if row.get::<_, bool>(3) {
            return Err(AppendError::Complete);
        }
        let record: UploadRecord = serde_json::from_str(row.get::<_, &str>(0)).map_err(|e| {
            AppendError::Failed(format!("an upload record in the coordinator is unreadable: {e}"))
        })?;
        let current = row.get::<_, i64>(1) as u64;
        let mut head: Vec<u8> = row.get(2);
        if let Some(claimed) = claimed
            && claimed != current
        {
            return Err(AppendError::OffsetMismatch { current });
        }
        let limit = record.length.unwrap_or(limit).min(limit);
        let mut offset = current;
        let mut part: Vec<u8> = Vec::new();
        let mut part_start = current;
        let mut body = body;
        let cut = loop {
            let chunk = match tokio::time::timeout(idle, body.next()).await {
                Err(_) => break Some(format!("no data for {} s", idle.as_secs())),
                Ok(None) => break None,
                Ok(Some(Err(e))) => break Some(e.to_string()),
                Ok(Some(Ok(chunk))) => chunk,
            };
            if offset + chunk.len() as u64 > limit {
                // Rolled back: nothing of this request is kept (its parts are removed with the upload).
                return Err(AppendError::TooLarge { current, limit });
            }
            if head.len() < HEAD_BYTES {
                let n = (HEAD_BYTES - head.len()).min(chunk.len());
                head.extend_from_slice(&chunk[..n]);
            }
            let mut rest = &chunk[..];
            while !rest.is_empty() {
                let n = (PART_BYTES - part.len()).min(rest.len());
                part.extend_from_slice(&rest[..n]);
                rest = &rest[n..];
                if part.len() == PART_BYTES {
                    self.store_part(&tx, bucket, id, part_start, std::mem::take(&mut part)).await?;
                    part_start += PART_BYTES as u64;
                }
            }
            offset += chunk.len() as u64;
            received_counter.inc_by(chunk.len() as u64);
        };
        if !part.is_empty() {
            self.store_part(&tx, bucket, id, part_start, part).await?;
        }
        tx.execute(
            "UPDATE voxstream_uploads SET received = $2, head = $3 WHERE id = $1",
            &[&id, &(offset as i64), &head],
        )
        .await
        .map_err(|e| failed(db(e)))?;
        if let Some(why) = cut {
            tx.commit().await.map_err(|e| failed(db(e)))?;
            return Err(AppendError::Cut { offset, why });
        }
        let complete = record.length.map_or(claimed.is_none(), |len| offset >= len);
        if !complete {
            tx.commit().await.map_err(|e| failed(db(e)))?;
            return Ok(Appended { offset, length: record.length.unwrap_or(offset), job: None });
        }
        if offset == 0 {
            return Err(AppendError::Empty);
        }
        let job = match make_job(&record, &head, offset) {
            Ok(job) => job,
            Err(message) => {
                tx.execute("DELETE FROM voxstream_uploads WHERE id = $1", &[&id])
                    .await
                    .map_err(|e| failed(db(e)))?;
                tx.commit().await.map_err(|e| failed(db(e)))?;
                self.remove_upload_objects(bucket, id).await;
                return Err(AppendError::Unusable(message));
            }
        };
        tx.execute("UPDATE voxstream_uploads SET complete = true WHERE id = $1", &[&id])
            .await
            .map_err(|e| failed(db(e)))?;
        // Not while a rename, delete or collection of the scene runs (they hold its lock).
        match tx.execute(SCENE_LOCK_SQL, &[&job.scene_id]).await {
            Ok(_) => {}
            Err(e) if e.code() == Some(&SqlState::LOCK_NOT_AVAILABLE) => {
                return Err(AppendError::SceneBusy(job.scene_id.clone()));
            }
            Err(e) => return Err(failed(db(e))),
        }
        let json = serde_json::to_string(&job).expect("job serialises");
        let inserted = tx
            .execute(
                "INSERT INTO voxstream_jobs (id, scene_id, state, created_at, job) VALUES ($1, $2, 'queued', $3, $4)",
                &[&job.id, &job.scene_id, &(job.created_at as i64), &json],
            )
            .await;
        match inserted {
            Ok(_) => {}
            Err(e) if e.code() == Some(&SqlState::UNIQUE_VIOLATION) => {
                return Err(AppendError::SceneBusy(job.scene_id.clone()));
            }
            Err(e) => return Err(failed(db(e))),
        }
        tx.commit().await.map_err(|e| failed(db(e)))?;
        Ok(Appended { offset, length: offset, job: Some(job) })
    }

    async fn store_part(
        &self,
        tx: &deadpool_postgres::Transaction<'_>,
        bucket: &Bucket,
        id: &str,
        start: u64,
        bytes: Vec<u8>,
    ) -> Result<(), AppendError> {
        let len = bytes.len() as i64;
        // A unique name: a PATCH that was cut off from the database (so rolled back) but still
        // writes must not overwrite a part another replica committed at the same offset.
        let rel = format!("{}/{start:020}-{:016x}", upload_prefix(id), rand::random::<u64>());
        bucket
            .put(&rel, bytes, "application/octet-stream", "no-store")
            .await
            .map_err(|e| AppendError::Failed(format!("{e:#}")))?;
        tx.execute(
            "INSERT INTO voxstream_upload_parts (upload_id, start_offset, len, object) VALUES ($1, $2, $3, $4)",
            &[&id, &(start as i64), &len, &rel],
        )
        .await
        .map_err(|e| AppendError::Failed(format!("{:#}", db(e))))?;
        Ok(())
    }

    /// The parts of a complete upload, in order: (offset, length, object relative to the prefix).
    pub async fn parts(&self, id: &str) -> anyhow::Result<Vec<(u64, u64, String)>> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT start_offset, len, object FROM voxstream_upload_parts WHERE upload_id = $1 ORDER BY start_offset",
                &[&id],
            )
            .await
            .map_err(db)?;
        Ok(rows.iter().map(|r| (r.get::<_, i64>(0) as u64, r.get::<_, i64>(1) as u64, r.get(2))).collect())
    }

    /// Abandons an unfinished upload (tus DELETE). `Ok(false)`: none such (or already complete).
    pub async fn delete_upload(&self, bucket: &Bucket, id: &str) -> Result<bool, AppendError> {
        let failed = |e: anyhow::Error| AppendError::Failed(format!("{e:#}"));
        let mut client = self.client().await.map_err(failed)?;
        let tx = client.transaction().await.map_err(|e| failed(db(e)))?;
        tx.batch_execute(&format!("SET LOCAL lock_timeout = '{UPLOAD_LOCK_WAIT}'"))
            .await
            .map_err(|e| failed(db(e)))?;
        let n = match tx.execute("DELETE FROM voxstream_uploads WHERE id = $1 AND NOT complete", &[&id]).await
        {
            Ok(n) => n,
            Err(e) if e.code() == Some(&SqlState::LOCK_NOT_AVAILABLE) => return Err(AppendError::Busy),
            Err(e) => return Err(failed(db(e))),
        };
        tx.commit().await.map_err(|e| failed(db(e)))?;
        if n == 1 {
            self.remove_upload_objects(bucket, id).await;
        }
        Ok(n == 1)
    }

    /// Removes an upload's row and objects once its job has ended.
    pub async fn remove_upload(&self, bucket: &Bucket, id: &str) {
        match self.client().await {
            Ok(client) => {
                if let Err(e) = client.execute("DELETE FROM voxstream_uploads WHERE id = $1", &[&id]).await {
                    tracing::warn!(upload = %id, error = %db(e), "cannot remove the upload's record");
                }
            }
            Err(e) => tracing::warn!(upload = %id, error = %e, "cannot remove the upload's record"),
        }
        self.remove_upload_objects(bucket, id).await;
    }

    /// Deletes every object under the upload's folder (committed parts and parts of PATCHes that
    /// were rolled back).
    async fn remove_upload_objects(&self, bucket: &Bucket, id: &str) {
        let prefix = bucket.path(&upload_prefix(id));
        let mut listing = bucket.store.list(Some(&prefix));
        while let Some(item) = listing.next().await {
            let result = match item {
                Ok(meta) => bucket.store.delete(&meta.location).await,
                Err(e) => Err(e),
            };
            if let Err(e) = result {
                tracing::warn!(upload = %id, error = %e, "cannot remove an upload part from the bucket");
            }
        }
    }

    /// Unfinished uploads created before `cutoff` (unix seconds), for expiry.
    pub async fn stale_uploads(&self, cutoff: u64) -> anyhow::Result<Vec<String>> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT id FROM voxstream_uploads WHERE NOT complete AND created_at < $1",
                &[&(cutoff as i64)],
            )
            .await
            .map_err(db)?;
        Ok(rows.iter().map(|r| r.get(0)).collect())
    }
}

/// `.uploads/<id>` under the bucket's prefix: not a scene id, so never listed as a scene.
pub fn upload_prefix(id: &str) -> String {
    format!(".uploads/{id}")
}

pub struct UploadStatus {
    pub record: UploadRecord,
    pub received: u64,
    pub complete: bool,
}

pub struct Appended {
    pub offset: u64,
    pub length: u64,
    /// Set when this request completed the upload.
    pub job: Option<Job>,
}

#[derive(Debug)]
pub enum AppendError {
    NotFound,
    Complete,
    /// Another request holds the upload's lock longer than we wait.
    Busy,
    OffsetMismatch {
        current: u64,
    },
    TooLarge {
        current: u64,
        limit: u64,
    },
    /// The client stopped sending; what arrived up to `offset` is kept.
    Cut {
        offset: u64,
        why: String,
    },
    Empty,
    /// The complete upload cannot be built (its format cannot be told); it was removed.
    Unusable(String),
    /// Another job is publishing the scene.
    SceneBusy(String),
    Failed(String),
}

#[derive(Debug)]
pub enum CancelError {
    NotFound,
    Ended(&'static str),
    Failed(anyhow::Error),
}

/// Why a scene edit or collection did not run.
#[derive(Debug, thiserror::Error)]
pub enum SceneLockError {
    /// Another replica is renaming, deleting or collecting the scene.
    #[error("scene {0:?} is being renamed, deleted or cleaned up by another request; try again")]
    Busy(String),
    /// A job of the scene is queued or running.
    #[error("a build is publishing scene {0:?}; wait for it or cancel it")]
    Building(String),
    #[error("coordinator: {0}")]
    Failed(String),
}

#[derive(Debug)]
pub enum PublishError {
    /// Another replica holds the job now (this one's lease expired and was taken over).
    LeaseLost,
    Failed(anyhow::Error),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_described_without_secrets() {
        let config: tokio_postgres::Config = "postgres://vox:hunter2@db.example:6543/scenes".parse().unwrap();
        assert_eq!(describe(&config), "postgres://vox@db.example:6543/scenes");
        // The port connected to, also when the URL leaves it to the default.
        let config: tokio_postgres::Config = "postgres://vox@127.0.0.1/scenes".parse().unwrap();
        assert_eq!(describe(&config), "postgres://vox@127.0.0.1:5432/scenes");
    }

    #[tokio::test]
    async fn a_password_on_the_command_line_is_refused_without_showing_it() {
        let e = Coordinator::connect(
            "postgres://vox:hunter2@127.0.0.1:1/scenes",
            Duration::from_secs(30),
            Duration::from_secs(5),
        )
        .await
        .err()
        .expect("refused");
        let text = format!("{e:#}");
        assert!(text.contains("PGPASSWORD") && text.contains("postgres://vox@127.0.0.1:1/scenes"), "{text}");
        assert!(!text.contains("hunter2"), "{text}");
        // Control: the same URL without the password gets past that check (to a refused connection).
        let e = Coordinator::connect(
            "postgres://vox@127.0.0.1:1/scenes",
            Duration::from_secs(30),
            Duration::from_secs(5),
        )
        .await
        .err()
        .expect("nothing listens on port 1");
        let text = format!("{e:#}");
        assert!(!text.contains("PGPASSWORD (environment)"), "{text}");
        assert!(text.contains("127.0.0.1:1"), "{text}");
    }
}
