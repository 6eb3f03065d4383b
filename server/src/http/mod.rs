//! HTTP: the scene catalog, manifests and blocks, uploads and build jobs under
//! `/api`, operations (`/healthz`, `/metrics`), and the viewer's static files
//! everywhere else. Every error is a JSON `{"error": "..."}`.
//!
//! - [`scenes`]: catalog, manifests, content-addressed blocks, batches.
//! - [`uploads`]: `POST /api/scenes` (one streamed body) and tus 1.0 resumable uploads.
//! - [`jobs`]: job status, SSE progress, cancel.
//! - [`access`]: bearer token, read-only mode, per-IP upload rate limit.
//! - [`openapi`]: the OpenAPI document at `/api/openapi.json`.

pub mod access;
pub mod jobs;
pub mod openapi;
pub mod scenes;
pub mod uploads;
pub mod web;

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{HeaderName, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde_json::json;
use tokio_util::sync::CancellationToken;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::services::ServeDir;
use tower_http::trace::TraceLayer;

use crate::bucket_store::BucketStore;
use crate::catalog::{Catalog, LoadedScene, SceneStore, remove_stale};
use crate::cluster_jobs::ClusterJobs;
use crate::config::{ServeArgs, ServerConfig};
use crate::coordinator::Coordinator;
use crate::jobs::{JobManager, Jobs};
use crate::metrics::Metrics;
use crate::store::validate_id;
use crate::uploads::Uploads;

pub use scenes::{BLOCK_CACHE_CONTROL, MANIFEST_CACHE_CONTROL};

/// What the handlers share.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

pub struct Shared {
    pub config: ServerConfig,
    pub catalog: Arc<Catalog>,
    pub jobs: Jobs,
    pub uploads: Uploads,
    pub metrics: Arc<Metrics>,
    pub upload_limiter: access::RateLimiter,
    /// Cancelled when the server shuts down: ends SSE streams and queued jobs.
    pub shutdown: CancellationToken,
    /// Serialises tus PATCH/HEAD/DELETE on one upload.
    pub upload_locks: std::sync::Mutex<std::collections::HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
    /// A bucket replica's own state folder (job records), removed with the server.
    _state_dir: Option<tempfile::TempDir>,
}

impl std::ops::Deref for AppState {
    type Target = Shared;
    fn deref(&self) -> &Shared {
        &self.0
    }
}

impl AppState {
    /// A read-only server over the scenes of `store_dir` (no jobs are resumed,
    /// nothing is written): what tests and the plain viewer need.
    pub fn load(store_dir: &Path, web_dir: Option<&Path>) -> anyhow::Result<AppState> {
        let mut config = ServerConfig::new(store_dir);
        config.web = web_dir.map(Path::to_path_buf);
        config.read_only = true;
        Self::build(config, CancellationToken::new())
    }

    fn build(config: ServerConfig, shutdown: CancellationToken) -> anyhow::Result<AppState> {
        let catalog = Arc::new(Catalog::open(&config.store)?);
        Ok(Self::with_catalog(config, catalog, shutdown, None, None))
    }

    fn with_catalog(
        config: ServerConfig,
        catalog: Arc<Catalog>,
        shutdown: CancellationToken,
        state_dir: Option<tempfile::TempDir>,
        coordinator: Option<Arc<Coordinator>>,
    ) -> AppState {
        let mut metrics = Metrics::new();
        if let SceneStore::Bucket(bucket) = catalog.scene_store() {
            metrics.register_store_cache(&bucket.metrics);
        }
        let metrics = Arc::new(metrics);
        let jobs = match (coordinator, catalog.scene_store()) {
            (Some(coordinator), SceneStore::Bucket(bucket)) => Jobs::Cluster(ClusterJobs::new(
                coordinator,
                bucket,
                catalog.clone(),
                metrics.clone(),
                config.build_workers,
                config.gc,
                shutdown.clone(),
            )),
            _ => Jobs::Local(JobManager::new(
                catalog.clone(),
                metrics.clone(),
                config.build_workers,
                shutdown.clone(),
            )),
        };
        AppState(Arc::new(Shared {
            upload_limiter: access::RateLimiter::new(config.uploads_per_minute),
            uploads: Uploads::new(&config.store),
            config,
            catalog,
            jobs,
            metrics,
            shutdown,
            upload_locks: Default::default(),
            _state_dir: state_dir,
        }))
    }

    /// A replica over the scenes of a bucket, its catalog listed from the bucket. Without a
    /// coordinator it is read-only (writes answer 403 naming how to build into the bucket); with
    /// one it takes uploads and builds them, once across all replicas. Fails when the first
    /// listing does.
    pub async fn start_bucket(
        mut config: ServerConfig,
        bucket: Arc<BucketStore>,
        coordinator: Option<Arc<Coordinator>>,
        shutdown: CancellationToken,
    ) -> anyhow::Result<AppState> {
        // A --read-only replica never builds, coordinator or not.
        let coordinator = coordinator.filter(|_| !config.read_only);
        config.read_only = coordinator.is_none();
        config.bucket_scenes = true;
        let state_dir = tempfile::Builder::new()
            .prefix("voxstream-replica-")
            .tempdir()
            .map_err(|e| anyhow::anyhow!("cannot create the replica's state folder: {e}"))?;
        config.store = state_dir.path().to_path_buf();
        let catalog = Catalog::open_bucket(bucket, state_dir.path()).await.map_err(anyhow::Error::msg)?;
        let state = Self::with_catalog(config, Arc::new(catalog), shutdown, Some(state_dir), coordinator);
        if let Some(cluster) = state.cluster() {
            cluster.start();
        }
        Ok(state)
    }

    /// The replicas' shared jobs, when this is a bucket replica with a coordinator.
    pub fn cluster(&self) -> Option<&Arc<ClusterJobs>> {
        match &self.jobs {
            Jobs::Cluster(c) => Some(c),
            Jobs::Local(_) => None,
        }
    }

    /// The full server for `config`: removes what interrupted builds left,
    /// resumes interrupted jobs. Call inside the tokio runtime.
    pub fn start(config: ServerConfig, shutdown: CancellationToken) -> anyhow::Result<AppState> {
        if !config.read_only {
            std::fs::create_dir_all(&config.store)
                .map_err(|e| anyhow::anyhow!("cannot create store {}: {e}", config.store.display()))?;
            let removed = remove_stale(&config.store);
            if !removed.is_empty() {
                tracing::info!(?removed, "removed leftovers of interrupted builds");
            }
        }
        let state = Self::build(config, shutdown)?;
        if let (false, Jobs::Local(jobs)) = (state.config.read_only, &state.jobs) {
            let r = jobs.recover();
            if !(r.resumed.is_empty() && r.failed.is_empty() && r.removed_uploads.is_empty()) {
                tracing::info!(resumed = ?r.resumed, failed = ?r.failed, removed_uploads = ?r.removed_uploads, "jobs recovered");
            }
        }
        Ok(state)
    }

    pub fn scene_ids(&self) -> Vec<String> {
        self.catalog.list().iter().map(|s| s.stored.id.clone()).collect()
    }

    /// A published scene; a malformed id is a 400, an unknown one a 404.
    async fn scene(&self, id: &str) -> Result<Arc<LoadedScene>, ApiError> {
        validate_id(id).map_err(|e| ApiError::bad_request(e.to_string()))?;
        self.catalog.find(id).await.ok_or_else(|| ApiError::not_found(format!("no scene with id {id:?}")))
    }

    /// `failure` of a read of `scene`, unless the scene was deleted, renamed or rebuilt while the
    /// request read it: then its files went with it, and the answer is a 404 that says so.
    pub(crate) fn read_failed(&self, scene: &Arc<LoadedScene>, failure: ApiError) -> ApiError {
        if failure.status.is_server_error() && !self.catalog.still_serves(scene) {
            let id = &scene.stored.id;
            tracing::info!(scene = %id, error = %failure.message, "read lost a race with a delete, rename or rebuild");
            return ApiError::not_found(format!(
                "scene {id:?} was deleted, renamed or rebuilt while this request read it; fetch the scene list or manifest again"
            ));
        }
        failure
    }
}

/// An error response: a status and a JSON body `{"error": "..."}`.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
    pub headers: Vec<(HeaderName, HeaderValue)>,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self { status, message: message.into(), headers: Vec::new() }
    }
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, message)
    }
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message)
    }
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, message)
    }
    pub fn with_header(mut self, name: HeaderName, value: HeaderValue) -> Self {
        self.headers.push((name, value));
        self
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut resp = (self.status, axum::Json(json!({ "error": self.message }))).into_response();
        for (k, v) in self.headers {
            resp.headers_mut().insert(k, v);
        }
        resp
    }
}

/// Reads a small JSON body (at most `limit` bytes) with errors as JSON.
pub async fn read_json<T: serde::de::DeserializeOwned>(body: Body, limit: usize) -> Result<T, ApiError> {
    let bytes = axum::body::to_bytes(body, limit).await.map_err(|_| {
        ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, format!("the JSON body is larger than {limit} bytes"))
    })?;
    serde_json::from_slice(&bytes).map_err(|e| ApiError::bad_request(format!("invalid JSON body: {e}")))
}

pub const JSON_BODY_LIMIT: usize = 256 * 1024;

pub fn router(state: AppState) -> Router {
    let api = Router::new()
        .route("/scenes", get(scenes::list_scenes).post(uploads::post_scene))
        .route("/scenes/{id}", get(scenes::get_scene).patch(scenes::patch_scene).delete(scenes::delete_scene))
        .route("/scenes/{id}/manifest", get(scenes::get_manifest))
        .route("/scenes/{id}/thumbnail.png", get(crate::thumbnail::get_thumbnail))
        .route("/scenes/{id}/blocks/batch", post(scenes::post_batch))
        .route("/scenes/{id}/blocks/{block}", get(scenes::get_block))
        .route("/scenes/{id}/pages/{page}", get(scenes::get_page))
        .route("/uploads", post(uploads::tus_create).options(uploads::tus_options))
        .route(
            "/uploads/{id}",
            axum::routing::head(uploads::tus_head)
                .patch(uploads::tus_patch)
                .delete(uploads::tus_delete)
                .options(uploads::tus_options),
        )
        .route("/jobs", get(jobs::list_jobs))
        .route("/jobs/{id}", get(jobs::get_job).delete(jobs::cancel_job))
        .route("/jobs/{id}/cancel", post(jobs::cancel_job))
        .route("/jobs/{id}/events", get(jobs::job_events))
        .route("/openapi.json", get(openapi::openapi_json))
        .fallback(|| async { ApiError::not_found("no such API route") });
    let mut app =
        Router::new().nest("/api", api).route("/healthz", get(healthz)).route("/metrics", get(metrics));
    app = match &state.config.web {
        Some(dir) => app.fallback_service(ServeDir::new(dir)),
        None => app.fallback(web::serve_embedded),
    };
    let mut app = app
        .layer(middleware::from_fn_with_state(state.clone(), record_metrics))
        .layer(DefaultBodyLimit::max(JSON_BODY_LIMIT))
        .with_state(state.clone());
    if let Some(cors) = cors_layer(&state.config.cors_origins) {
        app = app.layer(cors);
    }
    app.layer(middleware::from_fn_with_state(state.clone(), limit_headers)).layer(TraceLayer::new_for_http())
}

fn cors_layer(origins: &[String]) -> Option<CorsLayer> {
    if origins.is_empty() {
        return None;
    }
    let allow = if origins.iter().any(|o| o == "*") {
        AllowOrigin::any()
    } else {
        AllowOrigin::list(origins.iter().filter_map(|o| HeaderValue::from_str(o).ok()))
    };
    let h = |s: &'static str| HeaderName::from_static(s);
    Some(
        CorsLayer::new()
            .allow_origin(allow)
            .allow_methods([
                Method::GET,
                Method::HEAD,
                Method::POST,
                Method::PATCH,
                Method::DELETE,
                Method::OPTIONS,
            ])
            .allow_headers([
                header::AUTHORIZATION,
                header::CONTENT_TYPE,
                header::IF_NONE_MATCH,
                h("tus-resumable"),
                h("upload-length"),
                h("upload-offset"),
                h("upload-metadata"),
            ])
            .expose_headers([
                header::ETAG,
                header::LOCATION,
                h("tus-resumable"),
                h("tus-version"),
                h("upload-offset"),
                h("upload-length"),
                h("voxstream-job"),
            ])
            .max_age(Duration::from_secs(3600)),
    )
}

/// 431 for requests whose headers are larger than `--max-header-bytes`.
async fn limit_headers(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let size: usize = req.headers().iter().map(|(k, v)| k.as_str().len() + v.len() + 4).sum::<usize>()
        + req.uri().to_string().len();
    if size > state.config.max_header_bytes {
        return ApiError::new(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            format!("request line and headers are {size} bytes; at most {}", state.config.max_header_bytes),
        )
        .into_response();
    }
    next.run(req).await
}

async fn record_metrics(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req.extensions().get::<MatchedPath>().map_or("other", |p| p.as_str()).to_string();
    let method = req.method().to_string();
    let start = Instant::now();
    let resp = next.run(req).await;
    let m = &state.metrics;
    let status = resp.status().as_u16().to_string();
    m.http_requests
        .get_or_create(&Metrics::labels(&[("method", &method), ("route", &route), ("status", &status)]))
        .inc();
    m.http_request_seconds
        .get_or_create(&Metrics::labels(&[("route", &route)]))
        .observe(start.elapsed().as_secs_f64());
    if let Some(len) = resp.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse().ok())
    {
        m.http_response_bytes.inc_by(len);
    }
    resp
}

#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses((status = 200, description = "The server runs and its store is readable")))]
pub async fn healthz(State(state): State<AppState>) -> Response {
    let store = match state.catalog.scene_store() {
        // The bucket answered at start and its listing is re-read every few seconds.
        SceneStore::Bucket(_) => Ok(()),
        SceneStore::Local(dir) => std::fs::metadata(dir).map(|_| ()),
    };
    match store {
        Ok(_) => axum::Json(json!({ "status": "ok", "scenes": state.catalog.list().len() })).into_response(),
        Err(e) => {
            ApiError::new(StatusCode::SERVICE_UNAVAILABLE, format!("store unreadable: {e}")).into_response()
        }
    }
}

#[utoipa::path(get, path = "/metrics", tag = "operations",
    responses((status = 200, description = "Prometheus/OpenMetrics text", content_type = "application/openmetrics-text")))]
pub async fn metrics(_read: access::ReadAccess, State(state): State<AppState>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")],
        state.metrics.render(),
    )
        .into_response()
}

/// `voxstream serve`: refuses exposed writing, serves until SIGTERM or
/// ctrl-c, then ends SSE streams, stops builds (they resume on the next
/// start) and waits for both at most `--shutdown-secs`.
pub fn serve_command(args: ServeArgs) -> anyhow::Result<()> {
    args.check_exposure().map_err(anyhow::Error::msg)?;
    let location = crate::objstore::parse_location(&args.store.to_string_lossy())
        .map_err(|e| anyhow::anyhow!("--store {e}"))?;
    if args.coordinator.is_some() && matches!(location, crate::objstore::Location::Local(_)) {
        anyhow::bail!(
            "--coordinator is for replicas of an s3://bucket/prefix store; a local store's server builds on its own"
        );
    }
    let config = args.config();
    if let Some(w) = &config.web
        && !w.join("index.html").is_file()
    {
        anyhow::bail!("{} has no index.html: build the viewer with scripts/build-web.sh", w.display());
    }
    let rt = tokio::runtime::Runtime::new()?;
    let timeout = config.shutdown_timeout;
    let result = rt.block_on(async move {
        let shutdown = CancellationToken::new();
        let state = match location {
            crate::objstore::Location::Local(_) => AppState::start(config, shutdown.clone())?,
            crate::objstore::Location::S3 { bucket, prefix } => {
                // Unreachable endpoint, refused credentials, missing bucket: one error naming the
                // endpoint and the cause, before anything listens.
                let bucket =
                    crate::objstore::connect(&bucket, &prefix, crate::objstore::START_CHECK_DEADLINE).await?;
                let bucket = Arc::new(BucketStore::new(bucket, args.cache_size));
                let coordinator = match &args.coordinator {
                    // Unreachable, refused or misnamed: one error naming the endpoint, before anything listens.
                    Some(url) => Some(Arc::new(
                        Coordinator::connect(
                            url,
                            Duration::from_secs(args.lease_secs.max(1)),
                            crate::objstore::START_CHECK_DEADLINE,
                        )
                        .await?,
                    )),
                    None => None,
                };
                if let Some(c) = &coordinator {
                    tracing::info!(coordinator = %c.endpoint, replica = %c.owner, lease_secs = args.lease_secs, "builds coordinated");
                }
                let state = AppState::start_bucket(config, bucket, coordinator, shutdown.clone()).await?;
                tokio::spawn(relist_periodically(
                    state.catalog.clone(),
                    Duration::from_secs(args.relist_secs.max(1)),
                    shutdown.clone(),
                ));
                state
            }
        };
        tracing::info!(store = %state.catalog.scene_store(), scenes = ?state.scene_ids(), "catalog loaded");
        let listener = tokio::net::TcpListener::bind(args.addr)
            .await
            .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", args.addr))?;
        let local = listener.local_addr()?;
        tracing::info!("serving on http://{local}");
        // One stdout line for scripts and tests that start the server on port 0.
        println!("listening on http://{local}");
        let signal = shutdown.clone();
        tokio::spawn(async move {
            wait_for_signal().await;
            tracing::info!("shutting down");
            signal.cancel();
        });
        let app = router(state.clone()).into_make_service_with_connect_info::<std::net::SocketAddr>();
        let serve = axum::serve(listener, app).with_graceful_shutdown(shutdown.clone().cancelled_owned());
        let deadline = async {
            shutdown.cancelled().await;
            tokio::time::sleep(timeout).await;
        };
        tokio::select! {
            r = serve => r?,
            () = deadline => tracing::warn!("connections still open after {timeout:?}; closing them"),
        }
        state.jobs.shutdown(timeout).await;
        anyhow::Ok(())
    });
    // Builds cut short by shutdown check their cancel flag between stages; do not wait on them forever.
    rt.shutdown_timeout(Duration::from_secs(1));
    result
}

/// Re-reads a bucket's listing every `every`, so scenes published by other processes appear (and
/// replaced ones change) on every replica.
async fn relist_periodically(catalog: Arc<Catalog>, every: Duration, shutdown: CancellationToken) {
    let mut tick = crate::ticker::every(every).await;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = shutdown.cancelled() => return,
        }
        if let Err(e) = catalog.relist().await {
            tracing::warn!(error = %e, "bucket listing failed; serving the scenes listed before");
        }
    }
}

async fn wait_for_signal() {
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .expect("installing a SIGTERM handler");
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
