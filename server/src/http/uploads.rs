//! Uploads: bodies are streamed to `<store>/.uploads/<id>/data`, never held
//! in memory, and each complete upload becomes a build job of the same id.
//!
//! Two ways in:
//! - `POST /api/scenes?filename=scan.ply` with the mesh as the body: one
//!   request, not resumable (a cut connection discards it).
//! - tus 1.0.0 core + creation + termination under `/api/uploads` for large
//!   files over unreliable links: `POST` (Upload-Length, Upload-Metadata)
//!   creates, `PATCH` (Upload-Offset, `application/offset+octet-stream`)
//!   appends, `HEAD` tells the offset to resume from, `DELETE` abandons.
//!   The upload survives dropped connections and server restarts.
//!
//! On bucket replicas with a coordinator, the same protocol keeps its state in PostgreSQL and its
//! bytes in the bucket ([`crate::coordinator`]), so an upload can continue on any replica.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path as UrlPath, Query, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use base64::Engine;
use futures_util::StreamExt;
use serde::Deserialize;
use tokio::io::AsyncWriteExt;

use super::access::{UploadPermit, WriteAccess};
use super::{ApiError, AppState};
use crate::catalog::now_unix;
use crate::coordinator::{AppendError, Appended};
use crate::jobs::{Job, JobState, Jobs, new_id, parse_topology, valid_job_id};
use crate::store::{id_from_file_stem, validate_id};
use crate::uploads::{UploadRecord, detect_format};

pub const TUS_VERSION: &str = "1.0.0";
const OFFSET_CONTENT_TYPE: &str = "application/offset+octet-stream";

fn h(name: &'static str) -> HeaderName {
    HeaderName::from_static(name)
}

/// What an upload asks for, from the query (POST /api/scenes) or Upload-Metadata (tus).
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct UploadOptions {
    /// The mesh's file name; its extension tells the format when the bytes do not.
    pub filename: Option<String>,
    /// Scene id to publish; defaults to the file name's stem.
    pub id: Option<String>,
    /// Level-0 voxels per edge (a power of two up to --max-resolution); matched to the scan when absent.
    pub resolution: Option<u32>,
    /// conservative, 26-separating or 6-separating.
    pub topology: Option<String>,
    /// Replace a scene of the same id (otherwise 409).
    #[serde(default)]
    pub replace: bool,
}

/// Checks the options before any byte is stored; returns the record to create.
async fn plan_upload(
    state: &AppState,
    opts: UploadOptions,
    content_type: Option<String>,
    length: Option<u64>,
    resumable: bool,
) -> Result<UploadRecord, ApiError> {
    let max = state.config.max_upload_bytes;
    if let Some(len) = length {
        if len > max {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("the upload is {len} bytes; this server takes at most {max}"),
            ));
        }
        if len == 0 {
            return Err(ApiError::bad_request("the upload is empty"));
        }
    }
    if let Some(name) = &opts.filename
        && (name.is_empty() || name.chars().count() > 255 || name.chars().any(char::is_control))
    {
        return Err(ApiError::bad_request("filename must be 1–255 characters without control characters"));
    }
    let scene_id = match (&opts.id, &opts.filename) {
        (Some(id), _) => {
            validate_id(id).map_err(|e| ApiError::bad_request(e.to_string()))?;
            id.clone()
        }
        (None, Some(name)) => id_from_file_stem(std::path::Path::new(name)),
        (None, None) => "scene".to_string(),
    };
    // None: matched to the scan (auto), up to --max-resolution.
    let resolution = opts.resolution.or(state.config.resolution);
    if let Some(resolution) = resolution
        && (!resolution.is_power_of_two() || resolution < 64 || resolution > state.config.max_resolution)
    {
        return Err(ApiError::bad_request(format!(
            "resolution {resolution} must be a power of two from 64 to {}",
            state.config.max_resolution
        )));
    }
    let topology = opts.topology.unwrap_or_else(|| "conservative".into());
    if parse_topology(&topology).is_none() {
        return Err(ApiError::bad_request(format!(
            "topology {topology:?} is not conservative, 26-separating or 6-separating"
        )));
    }
    if state.jobs.building(&scene_id).await.map_err(super::jobs::job_error)? {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("a build is already publishing scene {scene_id:?}"),
        ));
    }
    if !opts.replace && state.catalog.contains(&scene_id) {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("scene {scene_id:?} exists: pass replace=true to rebuild it, or choose another id"),
        ));
    }
    Ok(UploadRecord {
        id: new_id(),
        length,
        file_name: opts.filename,
        content_type,
        scene_id,
        resolution,
        topology,
        replace: opts.replace,
        resumable,
        created_at: now_unix(),
    })
}

enum ReceiveError {
    TooLarge,
    /// The client stopped sending (error or idle timeout).
    Cut(String),
    Io(std::io::Error),
}

/// Appends the body to `file` starting at `offset`, never past `limit` total
/// bytes; returns the new offset. What arrived is synced before returning,
/// also when the connection was cut.
async fn receive(
    state: &AppState,
    body: Body,
    file: &mut tokio::fs::File,
    mut offset: u64,
    limit: u64,
) -> (u64, Result<(), ReceiveError>) {
    let mut stream = body.into_data_stream();
    let idle = state.config.upload_idle;
    let result = loop {
        let chunk = match tokio::time::timeout(idle, stream.next()).await {
            Err(_) => break Err(ReceiveError::Cut(format!("no data for {} s", idle.as_secs()))),
            Ok(None) => break Ok(()),
            Ok(Some(Err(e))) => break Err(ReceiveError::Cut(e.to_string())),
            Ok(Some(Ok(chunk))) => chunk,
        };
        if offset + chunk.len() as u64 > limit {
            break Err(ReceiveError::TooLarge);
        }
        if let Err(e) = file.write_all(&chunk).await {
            break Err(ReceiveError::Io(e));
        }
        offset += chunk.len() as u64;
        state.metrics.upload_bytes.inc_by(chunk.len() as u64);
    };
    if let Err(e) = file.sync_data().await {
        return (offset, Err(ReceiveError::Io(e)));
    }
    (offset, result)
}

fn io_error(e: std::io::Error) -> ApiError {
    tracing::error!(error = %e, "upload storage failed");
    ApiError::internal(format!("cannot store the upload: {e}"))
}

/// Turns a complete upload into a queued job.
async fn start_job(state: &AppState, record: UploadRecord, bytes: u64) -> Result<Job, ApiError> {
    let uploads = state.uploads.clone();
    let rec = record.clone();
    let finished = tokio::task::spawn_blocking(move || uploads.finish(&rec))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?;
    let input = match finished {
        Ok(input) => input,
        Err(message) => {
            state.uploads.remove(&record.id);
            return Err(ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, message));
        }
    };
    let input_file = input.file_name().and_then(|f| f.to_str()).unwrap_or_default().to_string();
    let job = new_job(state, &record, input_file, bytes);
    tracing::info!(job = %job.id, scene = %job.scene_id, bytes, "upload complete; build queued");
    match &state.jobs {
        Jobs::Local(jobs) => Ok(jobs.submit(job)),
        // Coordinated replicas queue jobs in the coordinator (`Coordinator::append`), never here.
        Jobs::Cluster(_) => Err(ApiError::internal("a local upload finished on a coordinated replica")),
    }
}

/// The queued job of a complete upload whose input is `input_file`.
fn new_job(state: &AppState, record: &UploadRecord, input_file: String, bytes: u64) -> Job {
    Job {
        id: record.id.clone(),
        scene_id: record.scene_id.clone(),
        state: JobState::Queued,
        stage: None,
        fraction: 0.0,
        eta_seconds: None,
        triangles_per_second: 0.0,
        error: None,
        input_file,
        input_bytes: bytes,
        resolution: record.resolution,
        max_resolution: state.config.max_resolution,
        topology: record.topology.clone(),
        created_at: now_unix(),
        started_at: None,
        finished_at: None,
        attempts: 0,
        builder: None,
        input_blake3: None,
    }
}

/// With a coordinator: the job of a complete upload whose first bytes are `head`, or why the
/// format cannot be told (415).
fn cluster_job(state: &AppState, record: &UploadRecord, head: &[u8], bytes: u64) -> Result<Job, String> {
    let format = detect_format(head, record.file_name.as_deref(), record.content_type.as_deref())?;
    let job = new_job(state, record, format!("{}.{format}", record.scene_id), bytes);
    tracing::info!(job = %job.id, scene = %job.scene_id, bytes, "upload complete; build queued for the replicas");
    Ok(job)
}

fn coordinator_error(e: anyhow::Error) -> ApiError {
    tracing::error!(error = %format!("{e:#}"), "coordinator request failed");
    ApiError::new(StatusCode::SERVICE_UNAVAILABLE, format!("the coordinator is unavailable: {e:#}"))
}

/// An append's failure as tus answers it (`post`: a plain POST, where too large is 413).
fn append_error(id: &str, e: AppendError, post: bool) -> ApiError {
    match e {
        AppendError::NotFound => ApiError::not_found(format!("no upload with id {id:?}")),
        AppendError::Complete => {
            ApiError::new(StatusCode::CONFLICT, format!("upload {id} is already complete"))
        }
        AppendError::Busy => {
            ApiError::new(StatusCode::LOCKED, format!("upload {id} is busy with another request"))
        }
        AppendError::OffsetMismatch { current } => ApiError::new(
            StatusCode::CONFLICT,
            format!("Upload-Offset differs from the {current} bytes the server has: resume from {current}"),
        )
        .with_header(h("upload-offset"), HeaderValue::from(current)),
        AppendError::TooLarge { limit, .. } if post => {
            ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, format!("the upload is larger than {limit} bytes"))
        }
        AppendError::TooLarge { current, limit } => ApiError::bad_request(format!(
            "the body runs past Upload-Length {limit}; nothing of this request was kept"
        ))
        .with_header(h("upload-offset"), HeaderValue::from(current)),
        AppendError::Cut { offset, why } if post => ApiError::bad_request(format!(
            "the upload was cut off after {offset} bytes ({why}); use /api/uploads (tus) to resume"
        )),
        AppendError::Cut { offset, why } => {
            tracing::info!(upload = %id, offset, %why, "upload interrupted; it can resume on any replica");
            ApiError::bad_request(format!("the body was cut off at offset {offset} ({why})"))
                .with_header(h("upload-offset"), HeaderValue::from(offset))
        }
        AppendError::Empty => ApiError::bad_request("the upload is empty"),
        AppendError::Unusable(message) => ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, message),
        AppendError::SceneBusy(scene) => ApiError::new(
            StatusCode::CONFLICT,
            format!("a build is already publishing scene {scene:?}, or it is being renamed or deleted"),
        ),
        AppendError::Failed(message) => {
            tracing::error!(upload = %id, error = %message, "storing the upload failed");
            ApiError::new(StatusCode::SERVICE_UNAVAILABLE, format!("cannot store the upload: {message}"))
        }
    }
}

fn job_created(job: Job) -> Response {
    let location = HeaderValue::from_str(&format!("/api/jobs/{}", job.id)).expect("hex id");
    (StatusCode::ACCEPTED, [(header::LOCATION, location)], axum::Json(job)).into_response()
}

fn header_str(headers: &HeaderMap, name: HeaderName) -> Option<String> {
    headers.get(name).and_then(|v| v.to_str().ok()).map(str::to_string)
}

#[utoipa::path(post, path = "/api/scenes", tag = "uploads", security(("bearer" = [])),
    params(UploadOptions),
    request_body(content = Vec<u8>, description = "The mesh file (OBJ, PLY, STL, glTF, GLB), streamed to disk",
        content_type = "application/octet-stream"),
    responses(
        (status = 202, description = "Upload stored; build queued (Location: the job)", body = Job),
        (status = 400, description = "Bad options, empty body or the connection was cut"),
        (status = 401), (status = 403),
        (status = 409, description = "The scene exists (use replace=true) or is being built"),
        (status = 413, description = "Larger than --max-upload-bytes"),
        (status = 415, description = "The mesh format cannot be told"),
        (status = 429, description = "Too many uploads from this client")))]
pub async fn post_scene(
    _write: WriteAccess,
    _permit: UploadPermit,
    State(state): State<AppState>,
    opts: Result<Query<UploadOptions>, QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let Query(opts) =
        opts.map_err(|e| ApiError::bad_request(format!("bad upload options: {}", e.body_text())))?;
    let length = header_str(&headers, header::CONTENT_LENGTH).and_then(|v| v.parse().ok());
    let mut opts = opts;
    if opts.filename.is_none() {
        opts.filename = header_str(&headers, h("x-filename"));
    }
    let record = plan_upload(&state, opts, header_str(&headers, header::CONTENT_TYPE), length, false).await?;
    if let Some(cluster) = state.cluster() {
        let (coordinator, bucket) = (&cluster.coordinator, cluster.bucket());
        coordinator.create_upload(&record).await.map_err(coordinator_error)?;
        let appended = coordinator
            .append(
                bucket,
                &record.id,
                None,
                state.config.max_upload_bytes,
                body.into_data_stream(),
                state.config.upload_idle,
                &state.metrics.upload_bytes,
                |rec, head, n| cluster_job(&state, rec, head, n),
            )
            .await;
        return match appended {
            Ok(Appended { job: Some(job), .. }) => Ok(job_created(job)),
            Ok(Appended { offset, .. }) => {
                coordinator.remove_upload(bucket, &record.id).await;
                Err(ApiError::bad_request(format!(
                    "the body ended after {offset} of its Content-Length bytes"
                )))
            }
            Err(e) => {
                // Not resumable: whatever arrived goes.
                if !matches!(e, AppendError::Unusable(_)) {
                    coordinator.remove_upload(bucket, &record.id).await;
                }
                Err(append_error(&record.id, e, true))
            }
        };
    }
    state.uploads.create(&record).map_err(io_error)?;
    let path = state.uploads.data_path(&record.id);
    let mut file = tokio::fs::OpenOptions::new().append(true).open(&path).await.map_err(io_error)?;
    let (received, result) = receive(&state, body, &mut file, 0, state.config.max_upload_bytes).await;
    drop(file);
    let fail = |e: ApiError| {
        state.uploads.remove(&record.id);
        Err(e)
    };
    match result {
        Ok(()) if received == 0 => return fail(ApiError::bad_request("the upload is empty")),
        Ok(()) => {}
        Err(ReceiveError::TooLarge) => {
            return fail(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("the upload is larger than {} bytes", state.config.max_upload_bytes),
            ));
        }
        Err(ReceiveError::Cut(why)) => {
            return fail(ApiError::bad_request(format!(
                "the upload was cut off after {received} bytes ({why}); use /api/uploads (tus) to resume"
            )));
        }
        Err(ReceiveError::Io(e)) => return fail(io_error(e)),
    }
    Ok(job_created(start_job(&state, record, received).await?))
}

fn tus_headers() -> [(HeaderName, HeaderValue); 2] {
    [
        (h("tus-resumable"), HeaderValue::from_static(TUS_VERSION)),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-store")),
    ]
}

fn require_tus(headers: &HeaderMap) -> Result<(), ApiError> {
    match headers.get("tus-resumable").and_then(|v| v.to_str().ok()) {
        Some(TUS_VERSION) => Ok(()),
        other => Err(ApiError::new(
            StatusCode::PRECONDITION_FAILED,
            format!("Tus-Resumable must be {TUS_VERSION} (got {:?})", other.unwrap_or("nothing")),
        )
        .with_header(h("tus-version"), HeaderValue::from_static(TUS_VERSION))),
    }
}

#[utoipa::path(options, path = "/api/uploads", tag = "uploads",
    responses((status = 204, description = "tus discovery: Tus-Version, Tus-Extension (creation, termination), Tus-Max-Size")))]
pub async fn tus_options(State(state): State<AppState>) -> Response {
    let max = HeaderValue::from(state.config.max_upload_bytes);
    (
        StatusCode::NO_CONTENT,
        [
            (h("tus-resumable"), HeaderValue::from_static(TUS_VERSION)),
            (h("tus-version"), HeaderValue::from_static(TUS_VERSION)),
            (h("tus-extension"), HeaderValue::from_static("creation,termination")),
            (h("tus-max-size"), max),
        ],
    )
        .into_response()
}

/// `key base64,key base64` (tus Upload-Metadata).
fn parse_metadata(value: &str) -> Result<HashMap<String, String>, ApiError> {
    let mut out = HashMap::new();
    for pair in value.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (key, encoded) = pair.split_once(' ').unwrap_or((pair, ""));
        let bytes = base64::engine::general_purpose::STANDARD.decode(encoded.trim()).map_err(|e| {
            ApiError::bad_request(format!("Upload-Metadata value of {key:?} is not base64: {e}"))
        })?;
        let text = String::from_utf8(bytes)
            .map_err(|_| ApiError::bad_request(format!("Upload-Metadata value of {key:?} is not UTF-8")))?;
        out.insert(key.to_string(), text);
    }
    Ok(out)
}

#[utoipa::path(post, path = "/api/uploads", tag = "uploads", security(("bearer" = [])),
    params(
        ("Tus-Resumable" = String, Header, description = "1.0.0"),
        ("Upload-Length" = u64, Header, description = "Total bytes"),
        ("Upload-Metadata" = Option<String>, Header,
            description = "tus metadata: filename, filetype, id, resolution, topology, replace (values base64)")),
    responses(
        (status = 201, description = "Created; Location: /api/uploads/{id}"),
        (status = 400), (status = 401), (status = 409), (status = 412, description = "Wrong Tus-Resumable"),
        (status = 413), (status = 429)))]
pub async fn tus_create(
    _write: WriteAccess,
    _permit: UploadPermit,
    State(state): State<AppState>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    require_tus(&headers)?;
    if headers.contains_key("upload-defer-length") {
        return Err(ApiError::bad_request("Upload-Defer-Length is not supported: send Upload-Length"));
    }
    let length: u64 = header_str(&headers, h("upload-length"))
        .ok_or_else(|| ApiError::bad_request("Upload-Length is required"))?
        .parse()
        .map_err(|_| ApiError::bad_request("Upload-Length must be a non-negative integer"))?;
    let meta = match header_str(&headers, h("upload-metadata")) {
        Some(v) => parse_metadata(&v)?,
        None => HashMap::new(),
    };
    let resolution = match meta.get("resolution") {
        Some(r) => {
            Some(r.parse().map_err(|_| ApiError::bad_request(format!("resolution {r:?} is not a number")))?)
        }
        None => None,
    };
    let opts = UploadOptions {
        filename: meta.get("filename").cloned(),
        id: meta.get("id").cloned(),
        resolution,
        topology: meta.get("topology").cloned(),
        replace: meta.get("replace").is_some_and(|v| v == "true" || v == "1"),
    };
    let record = plan_upload(&state, opts, meta.get("filetype").cloned(), Some(length), true).await?;
    match state.cluster() {
        Some(cluster) => cluster.coordinator.create_upload(&record).await.map_err(coordinator_error)?,
        None => state.uploads.create(&record).map_err(io_error)?,
    }
    let location = HeaderValue::from_str(&format!("/api/uploads/{}", record.id)).expect("hex id");
    Ok((StatusCode::CREATED, tus_headers(), [(header::LOCATION, location)]).into_response())
}

fn upload_lock(state: &AppState, id: &str) -> Arc<tokio::sync::Mutex<()>> {
    state.upload_locks.lock().expect("upload locks").entry(id.to_string()).or_default().clone()
}

/// Drops a finished upload's lock entry; a request still waiting on it will
/// find the upload gone.
fn forget_lock(state: &AppState, id: &str) {
    state.upload_locks.lock().expect("upload locks").remove(id);
}

/// Waits for a PATCH still running on the same upload (e.g. one whose client
/// vanished and whose last bytes are being synced).
async fn lock_upload(state: &AppState, id: &str) -> Result<tokio::sync::OwnedMutexGuard<()>, ApiError> {
    if !valid_job_id(id) {
        return Err(ApiError::not_found(format!("no upload with id {id:?}")));
    }
    tokio::time::timeout(Duration::from_secs(10), upload_lock(state, id).lock_owned())
        .await
        .map_err(|_| ApiError::new(StatusCode::LOCKED, format!("upload {id} is busy with another request")))
}

fn offset_headers(offset: u64, length: u64) -> [(HeaderName, HeaderValue); 2] {
    [(h("upload-offset"), HeaderValue::from(offset)), (h("upload-length"), HeaderValue::from(length))]
}

#[utoipa::path(head, path = "/api/uploads/{id}", tag = "uploads", security(("bearer" = [])),
    params(("id" = String, Path)),
    responses((status = 200, description = "Upload-Offset: bytes stored, where to resume; Upload-Length; \
        Voxstream-Job once complete"), (status = 404), (status = 412)))]
pub async fn tus_head(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    require_tus(&headers)?;
    if let Some(cluster) = state.cluster() {
        // The offset committed by the last PATCH, on whichever replica it ran.
        if let Some(upload) = cluster.coordinator.upload(&id).await.map_err(coordinator_error)?
            && !upload.complete
        {
            let length = upload.record.length.unwrap_or(upload.received);
            return Ok((tus_headers(), offset_headers(upload.received, length)).into_response());
        }
        return complete_upload_head(&state, &id).await;
    }
    let _guard = lock_upload(&state, &id).await?;
    if let Some(record) = state.uploads.load(&id) {
        let offset = state.uploads.offset(&id).map_err(io_error)?;
        return Ok((tus_headers(), offset_headers(offset, record.length.unwrap_or(offset))).into_response());
    }
    complete_upload_head(&state, &id).await
}

/// HEAD of an upload that became a job: its whole length, and the job.
async fn complete_upload_head(state: &AppState, id: &str) -> Result<Response, ApiError> {
    if !valid_job_id(id) {
        return Err(ApiError::not_found(format!("no upload with id {id:?}")));
    }
    match state.jobs.get(id).await.map_err(super::jobs::job_error)? {
        Some(job) => Ok((
            tus_headers(),
            offset_headers(job.input_bytes, job.input_bytes),
            [(h("voxstream-job"), HeaderValue::from_str(&job.id).expect("hex id"))],
        )
            .into_response()),
        None => Err(ApiError::not_found(format!("no upload with id {id:?}"))),
    }
}

#[utoipa::path(patch, path = "/api/uploads/{id}", tag = "uploads", security(("bearer" = [])),
    params(("id" = String, Path), ("Upload-Offset" = u64, Header, description = "Must equal the stored offset"),
        ("Tus-Resumable" = String, Header)),
    request_body(content = Vec<u8>, content_type = "application/offset+octet-stream"),
    responses(
        (status = 204, description = "Stored; Upload-Offset is the new offset. When it reaches Upload-Length \
            the build is queued and Voxstream-Job names the job"),
        (status = 400, description = "Missing Upload-Offset, body past Upload-Length, cut connection"),
        (status = 404), (status = 409, description = "Upload-Offset differs from the stored offset"),
        (status = 412), (status = 415, description = "Wrong Content-Type, or the mesh format cannot be told"),
        (status = 423, description = "Another request is writing this upload")))]
pub async fn tus_patch(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    require_tus(&headers)?;
    if header_str(&headers, header::CONTENT_TYPE).as_deref() != Some(OFFSET_CONTENT_TYPE) {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            format!("PATCH bodies must be Content-Type: {OFFSET_CONTENT_TYPE}"),
        ));
    }
    let claimed: u64 = header_str(&headers, h("upload-offset"))
        .ok_or_else(|| ApiError::bad_request("Upload-Offset is required"))?
        .parse()
        .map_err(|_| ApiError::bad_request("Upload-Offset must be a non-negative integer"))?;
    if let Some(cluster) = state.cluster() {
        if !valid_job_id(&id) {
            return Err(ApiError::not_found(format!("no upload with id {id:?}")));
        }
        // The upload's row lock serialises PATCHes across replicas.
        let appended = cluster
            .coordinator
            .append(
                cluster.bucket(),
                &id,
                Some(claimed),
                state.config.max_upload_bytes,
                body.into_data_stream(),
                state.config.upload_idle,
                &state.metrics.upload_bytes,
                |rec, head, n| cluster_job(&state, rec, head, n),
            )
            .await;
        let appended = match appended {
            Ok(appended) => appended,
            // Its job ended and the upload's state is gone: still "complete", as on a local store.
            Err(AppendError::NotFound)
                if state.jobs.get(&id).await.map_err(super::jobs::job_error)?.is_some() =>
            {
                return Err(append_error(&id, AppendError::Complete, false));
            }
            Err(e) => return Err(append_error(&id, e, false)),
        };
        let mut response =
            (StatusCode::NO_CONTENT, tus_headers(), offset_headers(appended.offset, appended.length))
                .into_response();
        if let Some(job) = appended.job {
            response
                .headers_mut()
                .insert(h("voxstream-job"), HeaderValue::from_str(&job.id).expect("hex id"));
        }
        return Ok(response);
    }
    let _guard = lock_upload(&state, &id).await?;
    let Some(record) = state.uploads.load(&id) else {
        return Err(match state.jobs.get(&id).await.map_err(super::jobs::job_error)? {
            Some(_) => ApiError::new(StatusCode::CONFLICT, format!("upload {id} is already complete")),
            None => ApiError::not_found(format!("no upload with id {id:?}")),
        });
    };
    let length = record.length.unwrap_or(state.config.max_upload_bytes);
    let path = state.uploads.data_path(&id);
    let mut file = tokio::fs::OpenOptions::new().append(true).open(&path).await.map_err(io_error)?;
    let current = file.metadata().await.map_err(io_error)?.len();
    if claimed != current {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("Upload-Offset is {claimed} but the server has {current} bytes: resume from {current}"),
        )
        .with_header(h("upload-offset"), HeaderValue::from(current)));
    }
    let (offset, result) = receive(&state, body, &mut file, current, length).await;
    match result {
        Ok(()) => {}
        Err(ReceiveError::TooLarge) => {
            file.set_len(current).await.map_err(io_error)?;
            return Err(ApiError::bad_request(format!(
                "the body runs past Upload-Length {length}; nothing of this request was kept"
            ))
            .with_header(h("upload-offset"), HeaderValue::from(current)));
        }
        Err(ReceiveError::Cut(why)) => {
            tracing::info!(upload = %id, offset, %why, "upload interrupted; it can resume");
            return Err(ApiError::bad_request(format!("the body was cut off at offset {offset} ({why})"))
                .with_header(h("upload-offset"), HeaderValue::from(offset)));
        }
        Err(ReceiveError::Io(e)) => return Err(io_error(e)),
    }
    drop(file);
    if offset < length {
        return Ok((StatusCode::NO_CONTENT, tus_headers(), offset_headers(offset, length)).into_response());
    }
    let job = start_job(&state, record, offset).await;
    forget_lock(&state, &id);
    let job = job?;
    Ok((
        StatusCode::NO_CONTENT,
        tus_headers(),
        offset_headers(offset, length),
        [(h("voxstream-job"), HeaderValue::from_str(&job.id).expect("hex id"))],
    )
        .into_response())
}

#[utoipa::path(delete, path = "/api/uploads/{id}", tag = "uploads", security(("bearer" = [])),
    params(("id" = String, Path)),
    responses((status = 204, description = "The partial upload is removed"), (status = 404), (status = 412)))]
pub async fn tus_delete(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    require_tus(&headers)?;
    if let Some(cluster) = state.cluster() {
        if !valid_job_id(&id) {
            return Err(ApiError::not_found(format!("no unfinished upload with id {id:?}")));
        }
        return match cluster.coordinator.delete_upload(cluster.bucket(), &id).await {
            Ok(true) => Ok((StatusCode::NO_CONTENT, tus_headers()).into_response()),
            Ok(false) => Err(ApiError::not_found(format!("no unfinished upload with id {id:?}"))),
            Err(e) => Err(append_error(&id, e, false)),
        };
    }
    let _guard = lock_upload(&state, &id).await?;
    if state.uploads.load(&id).is_none() {
        return Err(ApiError::not_found(format!("no unfinished upload with id {id:?}")));
    }
    state.uploads.remove(&id);
    forget_lock(&state, &id);
    Ok((StatusCode::NO_CONTENT, tus_headers()).into_response())
}
