//! Catalog, manifests and blocks.
//!
//! Block URLs are content-addressed: `/api/scenes/{id}/blocks/{key}.{hash}`
//! with the blake3 hash from the manifest. Such a URL names bytes that can
//! never change, so it is cached for a year as immutable, with a strong ETag;
//! a hash the scene does not have (e.g. after a rebuild) is a 404. The bare
//! `/blocks/{key}` form still works but must be revalidated (`no-cache`). The
//! served bytes are checked against the hash, so a URL never serves other
//! content. lz4 payloads are never compressed again.

use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use voxstream_format::{BlockEntry, BlockKey};

use super::access::{ReadAccess, WriteAccess};
use super::{ApiError, AppState, JSON_BODY_LIMIT, read_json};
use crate::catalog::{CatalogError, LoadedScene, SceneMeta};
use crate::store::{BlockReadError, StoreError, validate_id};

pub const BLOCK_CACHE_CONTROL: &str = "public, max-age=31536000, immutable";
/// Manifests and key-only block URLs change when a scene is rebuilt.
pub const MANIFEST_CACHE_CONTROL: &str = "no-cache";
/// Most bytes one batch response may carry.
pub const BATCH_MAX_BYTES: u64 = 64 << 20;

#[utoipa::path(get, path = "/api/scenes", tag = "scenes",
    responses((status = 200, description = "Published scenes, sorted by id", body = [SceneMeta])))]
pub async fn list_scenes(_read: ReadAccess, State(state): State<AppState>) -> axum::Json<Vec<SceneMeta>> {
    axum::Json(state.catalog.list().iter().map(|s| s.meta.clone()).collect())
}

#[utoipa::path(get, path = "/api/scenes/{id}", tag = "scenes",
    params(("id" = String, Path, description = "Scene id: [a-z0-9_-]{1,64}")),
    responses((status = 200, body = SceneMeta), (status = 400, description = "Malformed id"),
        (status = 404, description = "No such scene")))]
pub async fn get_scene(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<axum::Json<SceneMeta>, ApiError> {
    Ok(axum::Json(state.scene(&id).await?.meta.clone()))
}

#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SceneUpdate {
    /// New id (the scene's URLs change; a local scene's directory is renamed atomically, a bucket
    /// scene's objects are copied and its new manifest written last).
    pub id: Option<String>,
    /// New display name.
    pub name: Option<String>,
}

#[utoipa::path(patch, path = "/api/scenes/{id}", tag = "scenes", security(("bearer" = [])),
    params(("id" = String, Path)), request_body = SceneUpdate,
    responses((status = 200, body = SceneMeta), (status = 400), (status = 401), (status = 404),
        (status = 409, description = "The new id is taken or a build is publishing the scene")))]
pub async fn patch_scene(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    body: Body,
) -> Result<axum::Json<SceneMeta>, ApiError> {
    state.scene(&id).await?;
    let update: SceneUpdate = read_json(body, JSON_BODY_LIMIT).await?;
    if let Some(new_id) = &update.id {
        validate_id(new_id).map_err(|e| ApiError::bad_request(e.to_string()))?;
        if state.jobs.building(new_id).await.map_err(super::jobs::job_error)? {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                format!("a build is publishing scene {new_id:?}"),
            ));
        }
    }
    if let Some(name) = &update.name
        && (name.trim().is_empty() || name.chars().count() > 200 || name.chars().any(char::is_control))
    {
        return Err(ApiError::bad_request("name must be 1–200 characters without control characters"));
    }
    if update.id.is_none() && update.name.is_none() {
        return Err(ApiError::bad_request("give \"id\" (new id) and/or \"name\" (display name)"));
    }
    if state.jobs.building(&id).await.map_err(super::jobs::job_error)? {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("a build is publishing scene {id:?}; wait or cancel it"),
        ));
    }
    let name = update.name.as_deref().map(str::trim);
    if let Some(cluster) = state.cluster() {
        // A bucket scene, fenced through the coordinator (the checks above are repeated there,
        // under the scenes' locks).
        let scene = state
            .catalog
            .rename_in_bucket(&cluster.coordinator, &id, update.id.as_deref(), name)
            .await
            .map_err(catalog_error)?;
        return Ok(axum::Json(scene.meta.clone()));
    }
    let catalog = state.catalog.clone();
    let scene = tokio::task::spawn_blocking(move || {
        catalog.rename(&id, update.id.as_deref(), update.name.as_deref().map(str::trim))
    })
    .await
    .map_err(|e| ApiError::internal(e.to_string()))?
    .map_err(catalog_error)?;
    Ok(axum::Json(scene.meta.clone()))
}

fn catalog_error(e: CatalogError) -> ApiError {
    match &e {
        CatalogError::NotFound(_) => ApiError::not_found(e.to_string()),
        CatalogError::Exists(_) => ApiError::new(StatusCode::CONFLICT, e.to_string()),
        CatalogError::ReadOnlyBucket(_) => ApiError::new(StatusCode::FORBIDDEN, e.to_string()),
        CatalogError::Busy(_) => ApiError::new(StatusCode::CONFLICT, e.to_string()),
        CatalogError::Unavailable(_) => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, e.to_string()),
        CatalogError::Store(crate::store::StoreError::BadId(_)) => ApiError::bad_request(e.to_string()),
        _ => {
            tracing::error!(error = %e, "catalog change failed");
            ApiError::internal(e.to_string())
        }
    }
}

#[utoipa::path(delete, path = "/api/scenes/{id}", tag = "scenes", security(("bearer" = [])),
    params(("id" = String, Path)),
    responses((status = 204, description = "Deleted"), (status = 400), (status = 401), (status = 404), (status = 409)))]
pub async fn delete_scene(
    _write: WriteAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<StatusCode, ApiError> {
    state.scene(&id).await?;
    if state.jobs.building(&id).await.map_err(super::jobs::job_error)? {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("a build is publishing scene {id:?}; cancel it first"),
        ));
    }
    if let Some(cluster) = state.cluster() {
        state.catalog.delete_in_bucket(&cluster.coordinator, &id).await.map_err(catalog_error)?;
        return Ok(StatusCode::NO_CONTENT);
    }
    let catalog = state.catalog.clone();
    tokio::task::spawn_blocking(move || catalog.delete(&id))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(catalog_error)?;
    Ok(StatusCode::NO_CONTENT)
}

#[utoipa::path(get, path = "/api/scenes/{id}/manifest", tag = "scenes",
    params(("id" = String, Path)),
    responses((status = 200, description = "voxstream_format::Manifest as JSON", content_type = "application/json"),
        (status = 400), (status = 404)))]
pub async fn get_manifest(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id).await?;
    Ok((
        [(header::CONTENT_TYPE, "application/json"), (header::CACHE_CONTROL, MANIFEST_CACHE_CONTROL)],
        scene.manifest_json.clone(),
    )
        .into_response())
}

/// Whether `If-None-Match` names `etag` (or `*`).
fn etag_matches(headers: &HeaderMap, etag: &HeaderValue) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == etag || t.trim() == "*")
}

/// `key` or `key.hash` → the scene's entry (its hierarchy pages read on the way when needed); a
/// key or hash the scene lacks is a 404.
async fn find_block(
    state: &AppState,
    scene: &Arc<LoadedScene>,
    name: &str,
) -> Result<(BlockEntry, bool), ApiError> {
    let (key_text, hash) = match name.split_once('.') {
        Some((k, h)) => (k, Some(h)),
        None => (name, None),
    };
    let key: BlockKey = key_text.parse().map_err(|e: voxstream_format::KeyError| {
        ApiError::bad_request(format!("{e} (block URLs are <level-x-y-z> or <level-x-y-z>.<blake3 hex>)"))
    })?;
    let id = &scene.stored.id;
    let entry = scene
        .stored
        .entry(&key)
        .await
        .map_err(|e| state.read_failed(scene, store_error(id, e)))?
        .ok_or_else(|| ApiError::not_found(format!("scene {id:?} has no block {key}")))?;
    if let Some(h) = hash
        && h != entry.hash
    {
        return Err(ApiError::not_found(format!(
            "scene {id:?} has no block {key} with hash {h:?} (rebuilt? fetch the manifest again)"
        )));
    }
    Ok((entry, hash.is_some()))
}

/// A hierarchy read error as a response: a scene that vanished under this replica is a 404
/// (fetch the manifest again), a damaged one a 500.
fn store_error(id: &str, e: StoreError) -> ApiError {
    match e {
        StoreError::Gone { .. } => ApiError::not_found(e.to_string()),
        e => {
            tracing::error!(scene = %id, error = %e, "hierarchy page cannot be read");
            ApiError::internal(e.to_string())
        }
    }
}

/// A block read error as a response: a damaged store is a 500, changed bytes a 404.
fn block_error(scene: &LoadedScene, entry: &BlockEntry, e: BlockReadError) -> ApiError {
    let id = &scene.stored.id;
    match e {
        BlockReadError::Unreadable { .. } => {
            tracing::error!(scene = %id, error = %e, "block listed in the hierarchy cannot be read");
            ApiError::internal(format!("scene {id:?}: {e}"))
        }
        BlockReadError::Changed { .. } => {
            tracing::warn!(scene = %id, block = %entry.key, "block bytes differ from the hierarchy's hash (replaced or damaged)");
            ApiError::not_found(format!(
                "block {} of scene {id:?} changed on disk; fetch the manifest again",
                entry.key
            ))
        }
    }
}

#[utoipa::path(get, path = "/api/scenes/{id}/blocks/{block}", tag = "scenes",
    params(("id" = String, Path), ("block" = String, Path,
        description = "<level-x-y-z>.<blake3 hex from the manifest> (immutable), or <level-x-y-z> (revalidated)")),
    responses(
        (status = 200, description = "Encoded block (voxstream_format::decode_block); strong ETag", content_type = "application/octet-stream"),
        (status = 304, description = "If-None-Match matched"),
        (status = 400, description = "Malformed id or key"),
        (status = 404, description = "No such scene, block or hash")))]
pub async fn get_block(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath((id, block)): UrlPath<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id).await?;
    let (entry, addressed) = find_block(&state, &scene, &block).await?;
    let etag = HeaderValue::from_str(&format!("\"{}\"", entry.hash))
        .map_err(|_| ApiError::internal(format!("scene {id:?} has a malformed block hash")))?;
    let cache =
        HeaderValue::from_static(if addressed { BLOCK_CACHE_CONTROL } else { MANIFEST_CACHE_CONTROL });
    if etag_matches(&headers, &etag) {
        return Ok(not_modified(etag, cache));
    }
    let bytes = scene
        .stored
        .read_block_async(&entry)
        .await
        .map_err(|e| state.read_failed(&scene, block_error(&scene, &entry, e)))?;
    state.metrics.blocks_served.inc();
    state.metrics.block_bytes_served.inc_by(bytes.len() as u64);
    Ok(octet_stream(etag, cache, bytes))
}

fn not_modified(etag: HeaderValue, cache: HeaderValue) -> Response {
    (StatusCode::NOT_MODIFIED, [(header::ETAG, etag), (header::CACHE_CONTROL, cache)]).into_response()
}

/// Encoded bytes (a block or a page) with their strong ETag and cache policy.
fn octet_stream(etag: HeaderValue, cache: HeaderValue, bytes: Bytes) -> Response {
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream")),
            (header::ETAG, etag),
            (header::CACHE_CONTROL, cache),
        ],
        bytes,
    )
        .into_response()
}

#[utoipa::path(get, path = "/api/scenes/{id}/pages/{page}", tag = "scenes",
    params(("id" = String, Path), ("page" = String, Path,
        description = "<root level-x-y-z>.<blake3 hex> as the manifest or a parent page names it (immutable)")),
    responses(
        (status = 200, description = "Encoded hierarchy page (voxstream_format::HierarchyPage); strong ETag", content_type = "application/octet-stream"),
        (status = 304, description = "If-None-Match matched"),
        (status = 400, description = "Malformed id or page name"),
        (status = 404, description = "No such scene, page or hash")))]
pub async fn get_page(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath((id, page)): UrlPath<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id).await?;
    let malformed = || ApiError::bad_request("page URLs are <level-x-y-z>.<blake3 hex>".to_string());
    let (key_text, hash) = page.split_once('.').ok_or_else(malformed)?;
    let root: BlockKey = key_text.parse().map_err(|_| malformed())?;
    if hash.len() != 64 || !hash.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(malformed());
    }
    let etag = HeaderValue::from_str(&format!("\"{hash}\"")).map_err(|_| malformed())?;
    let cache = HeaderValue::from_static(BLOCK_CACHE_CONTROL);
    let bytes = scene
        .stored
        .read_page(&root, hash)
        .await
        .map_err(|e| state.read_failed(&scene, store_error(&id, e)))?
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "scene {id:?} has no page {root} with hash {hash:?} (rebuilt? fetch the manifest again)"
            ))
        })?;
    if etag_matches(&headers, &etag) {
        return Ok(not_modified(etag, cache));
    }
    Ok(octet_stream(etag, cache, bytes))
}

#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct BatchRequest {
    /// Block names as in block URLs: `level-x-y-z.hash` (or `level-x-y-z`).
    pub blocks: Vec<String>,
}

#[utoipa::path(post, path = "/api/scenes/{id}/blocks/batch", tag = "scenes",
    params(("id" = String, Path)), request_body = BatchRequest,
    responses(
        (status = 200, description = "For each requested block in order: u32 little-endian length, then the encoded bytes",
            content_type = "application/octet-stream"),
        (status = 400, description = "Malformed request, too many blocks or too many bytes"),
        (status = 404, description = "A block or hash the scene does not have")))]
pub async fn post_batch(
    _read: ReadAccess,
    State(state): State<AppState>,
    UrlPath(id): UrlPath<String>,
    body: Body,
) -> Result<Response, ApiError> {
    let scene = state.scene(&id).await?;
    let request: BatchRequest = read_json(body, JSON_BODY_LIMIT).await?;
    let max = state.config.batch_max;
    if request.blocks.is_empty() || request.blocks.len() > max {
        return Err(ApiError::bad_request(format!(
            "ask for 1 to {max} blocks per batch (got {})",
            request.blocks.len()
        )));
    }
    let mut entries = Vec::with_capacity(request.blocks.len());
    for name in &request.blocks {
        entries.push(find_block(&state, &scene, name).await?.0);
    }
    let total: u64 = entries.iter().map(|e| 4 + e.bytes as u64).sum();
    if total > BATCH_MAX_BYTES {
        return Err(ApiError::bad_request(format!(
            "the batch would be {total} bytes; at most {BATCH_MAX_BYTES}: ask for fewer blocks"
        )));
    }
    let blocks = scene.stored.read_blocks(entries.clone()).await.map_err(|e| {
        let key = match &e {
            BlockReadError::Unreadable { key, .. } | BlockReadError::Changed { key } => *key,
        };
        let entry = entries.iter().find(|x| x.key == key).unwrap_or(&entries[0]);
        state.read_failed(&scene, block_error(&scene, entry, e))
    })?;
    let mut body = Vec::with_capacity(total as usize);
    for bytes in &blocks {
        body.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        body.extend_from_slice(bytes);
    }
    state.metrics.blocks_served.inc_by(request.blocks.len() as u64);
    state.metrics.block_bytes_served.inc_by(body.len() as u64);
    Ok((
        [(header::CONTENT_TYPE, "application/octet-stream"), (header::CACHE_CONTROL, "no-store")],
        Bytes::from(body),
    )
        .into_response())
}
