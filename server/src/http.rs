//! HTTP: the scene catalog, manifests and blocks under `/api`, and the viewer's
//! static files everywhere else.
//!
//! Blocks are immutable for a given manifest, so they carry a strong ETag (the
//! blake3 of their bytes, from the manifest) and a year-long immutable cache
//! lifetime. lz4 payloads are never compressed again.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::Router;
use axum::body::Bytes;
use axum::extract::{Path as UrlPath, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::json;
use tower_http::services::ServeDir;
use voxstream_format::{BlockKey, SceneSummary};

use crate::store::{self, StoredScene};

pub const BLOCK_CACHE_CONTROL: &str = "public, max-age=31536000, immutable";

struct LoadedScene {
    stored: StoredScene,
    manifest_json: Bytes,
}

/// What the handlers share: the catalog read at start-up.
#[derive(Clone)]
pub struct AppState {
    scenes: Arc<BTreeMap<String, LoadedScene>>,
    web_dir: Option<PathBuf>,
}

impl AppState {
    /// Reads every published scene of `store_dir`. A damaged scene stops start-up
    /// with its name rather than being served half-readable.
    pub fn load(store_dir: &Path, web_dir: Option<&Path>) -> anyhow::Result<AppState> {
        let mut scenes = BTreeMap::new();
        for stored in store::list_scenes(store_dir)? {
            let manifest_json = Bytes::from(stored.manifest.to_json());
            scenes.insert(stored.id.clone(), LoadedScene { stored, manifest_json });
        }
        Ok(AppState { scenes: Arc::new(scenes), web_dir: web_dir.map(Path::to_path_buf) })
    }

    pub fn scene_ids(&self) -> impl Iterator<Item = &str> {
        self.scenes.keys().map(String::as_str)
    }

    fn scene(&self, id: &str) -> Result<&LoadedScene, ApiError> {
        self.scenes.get(id).ok_or_else(|| ApiError::not_found(format!("no scene with id {id:?}")))
    }
}

/// An error response: a status and a JSON body `{"error": "..."}`.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    message: String,
}

impl ApiError {
    fn not_found(message: String) -> Self {
        Self { status: StatusCode::NOT_FOUND, message }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.status, axum::Json(json!({ "error": self.message }))).into_response()
    }
}

pub fn router(state: AppState) -> Router {
    let api = Router::new()
        .route("/scenes", get(list_scenes))
        .route("/scenes/{id}/manifest", get(get_manifest))
        .route("/scenes/{id}/blocks/{key}", get(get_block))
        .fallback(|| async { ApiError::not_found("no such API route".into()) })
        .with_state(state.clone());
    let app = Router::new().nest("/api", api);
    match &state.web_dir {
        Some(dir) => app.fallback_service(ServeDir::new(dir)),
        None => {
            app.fallback(|| async { ApiError::not_found("this server has no viewer files (--web)".into()) })
        }
    }
}

async fn list_scenes(State(state): State<AppState>) -> axum::Json<Vec<SceneSummary>> {
    axum::Json(state.scenes.values().map(|s| s.stored.manifest.summary(&s.stored.id)).collect())
}

async fn get_manifest(
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id)?;
    // The manifest changes when a scene is rebuilt: always revalidate.
    Ok((
        [(header::CONTENT_TYPE, "application/json"), (header::CACHE_CONTROL, "no-cache")],
        scene.manifest_json.clone(),
    )
        .into_response())
}

async fn get_block(
    State(state): State<AppState>,
    UrlPath((id, key)): UrlPath<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id)?;
    let key: BlockKey = key.parse().map_err(|e: voxstream_format::KeyError| ApiError {
        status: StatusCode::BAD_REQUEST,
        message: e.to_string(),
    })?;
    let entry = scene
        .stored
        .manifest
        .block(&key)
        .ok_or_else(|| ApiError::not_found(format!("scene {id:?} has no block {key}")))?;
    let etag = HeaderValue::from_str(&format!("\"{}\"", entry.hash)).expect("hex hash is a valid header");
    let cache = HeaderValue::from_static(BLOCK_CACHE_CONTROL);
    let matches = headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == etag || t.trim() == "*");
    if matches {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, etag), (header::CACHE_CONTROL, cache)])
            .into_response());
    }
    let path = scene.stored.block_path(&key);
    let bytes = tokio::fs::read(&path).await.map_err(|e| {
        tracing::error!(path = %path.display(), error = %e, "block listed in the manifest cannot be read");
        ApiError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            message: format!("block {key} of scene {id:?} is unreadable"),
        }
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream")),
            (header::ETAG, etag),
            (header::CACHE_CONTROL, cache),
        ],
        bytes,
    )
        .into_response())
}
