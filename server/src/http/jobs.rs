//! Build jobs: status, a server-sent event stream of progress, cancel.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::{Path as UrlPath, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures_util::{Stream, StreamExt};
use tokio::sync::watch;

use super::access::{ReadAccess, WriteAccess};
use super::{ApiError, AppState};
use crate::jobs::{Job, JobError, valid_job_id};

fn check_id(id: &str) -> Result<(), ApiError> {
    if valid_job_id(id) {
        Ok(())
    } else {
        Err(ApiError::bad_request(format!("job id {id:?} is malformed: expected 16 hex digits")))
    }
}

#[utoipa::path(get, path = "/api/jobs", tag = "jobs",
    responses((status = 200, description = "All jobs the store remembers, newest first", body = [Job])))]
pub async fn list_jobs(
    _read: ReadAccess,
    State(state): State<AppState>,
) -> Result<axum::Json<Vec<Job>>, ApiError> {
    state.jobs.list().await.map(axum::Json).map_err(job_error)
}

/// A job operation's error as a response (the coordinator unreachable: 503).
pub fn job_error(e: JobError) -> ApiError {
    match e {
        JobError::NotFound(_) => ApiError::not_found(e.to_string()),
        JobError::Ended { .. } => ApiError::new(StatusCode::CONFLICT, e.to_string()),
        JobError::Unavailable(_) => {
            tracing::error!(error = %e, "coordinator request failed");
            ApiError::new(StatusCode::SERVICE_UNAVAILABLE, e.to_string())
        }
    }
}

#[utoipa::path(get, path = "/api/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = Job), (status = 400), (status = 404)))]
pub async fn get_job(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<axum::Json<Job>, ApiError> {
    check_id(&id)?;
    state
        .jobs
        .get(&id)
        .await
        .map_err(job_error)?
        .map(axum::Json)
        .ok_or_else(|| ApiError::not_found(format!("no job with id {id:?}")))
}

#[utoipa::path(delete, path = "/api/jobs/{id}", tag = "jobs", security(("bearer" = [])), params(("id" = String, Path)),
    responses((status = 202, description = "Cancel requested; the job ends as cancelled", body = Job),
        (status = 400), (status = 401), (status = 404), (status = 409, description = "The job already ended")))]
pub async fn cancel_job(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<Response, ApiError> {
    check_id(&id)?;
    match state.jobs.cancel(&id).await {
        Ok(job) => Ok((StatusCode::ACCEPTED, axum::Json(job)).into_response()),
        Err(e) => Err(job_error(e)),
    }
}

fn event(job: &Job) -> Event {
    let name = if job.state.is_final() { job.state.name() } else { "progress" };
    Event::default().event(name).json_data(job).expect("job serialises")
}

/// Current state at once, then every change (at most ten a second), ending
/// after the final state (`done`, `failed` or `cancelled` event) or when the
/// server shuts down.
fn job_stream(rx: watch::Receiver<Job>) -> impl Stream<Item = Event> {
    futures_util::stream::unfold((rx, true, false), |(mut rx, first, ended)| async move {
        if ended {
            return None;
        }
        if !first {
            tokio::time::sleep(Duration::from_millis(100)).await;
            // A closed channel means the job's sender is gone; show the last state and end.
            let _ = rx.changed().await;
        }
        let job = rx.borrow_and_update().clone();
        let ended = job.state.is_final() || rx.has_changed().is_err();
        Some((event(&job), (rx, false, ended)))
    })
}

#[utoipa::path(get, path = "/api/jobs/{id}/events", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, description = "text/event-stream: `progress` events with the Job JSON, then one \
        `done`, `failed` or `cancelled` event, then the stream ends", content_type = "text/event-stream"),
        (status = 400), (status = 404)))]
pub async fn job_events(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<Response, ApiError> {
    check_id(&id)?;
    let rx = state
        .jobs
        .subscribe(&id)
        .await
        .map_err(job_error)?
        .ok_or_else(|| ApiError::not_found(format!("no job with id {id:?}")))?;
    let gauge = state.metrics.sse_streams.clone();
    gauge.inc();
    let guard = scopeguard(move || {
        gauge.dec();
    });
    let stream = job_stream(rx).take_until(state.shutdown.clone().cancelled_owned()).map(move |e| {
        let _ = &guard;
        Ok::<_, Infallible>(e)
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}

/// Runs `f` when dropped (with the stream, however it ends).
fn scopeguard(f: impl FnOnce() + Send + 'static) -> impl Send + Sync + 'static {
    struct Guard<F: FnOnce()>(Option<F>);
    impl<F: FnOnce()> Drop for Guard<F> {
        fn drop(&mut self) {
            if let Some(f) = self.0.take() {
                f()
            }
        }
    }
    // Sync: the closure is only touched in drop, through &mut.
    struct SyncGuard<F: FnOnce()>(std::sync::Mutex<Guard<F>>);
    SyncGuard(std::sync::Mutex::new(Guard(Some(f))))
}
