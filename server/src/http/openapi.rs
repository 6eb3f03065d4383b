//! The OpenAPI 3.1 document (utoipa), served as JSON only: no UI to download.
//!
//! The handlers' `#[utoipa::path]` attributes give each operation's purpose and
//! its own status codes; [`document`] then makes the whole document exact for
//! the server that serves it, in one place, so that no route can drift:
//!
//! - path parameters get the patterns the handlers enforce (scene ids, job and
//!   upload ids, block and page names);
//! - the tus headers (`Tus-Resumable`, `Upload-Length`, `Upload-Offset`) are
//!   typed as the handlers check them, and bodies are binary, not arrays;
//! - auth follows this server's flags: `401` (and `bearer` security) where a
//!   token is required, `403` on write routes of a `--read-only` server, `429`
//!   on upload creation when a rate limit is set;
//! - every 4xx is documented with its JSON body `{"error": "..."}`, and `431`
//!   (headers over `--max-header-bytes`) on every operation;
//! - limits taken from the configuration (`--max-upload-bytes`,
//!   `--max-resolution`, `--batch-max`) appear as schema bounds.
//!
//! `scripts/schemathesis.sh` checks the result against a running server.

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use serde_json::{Map, Value, json};
use utoipa::OpenApi;
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};

use super::{AppState, jobs, scenes, uploads};
use crate::config::ServerConfig;

/// `store::validate_id`: 1–64 of `[a-z0-9_-]`, not starting with `-` or `_`.
pub const SCENE_ID_PATTERN: &str = "^[a-z0-9][a-z0-9_-]{0,63}$";
/// `jobs::valid_job_id`: job and upload ids.
pub const JOB_ID_PATTERN: &str = "^[0-9a-f]{16}$";
/// A block key `level-x-y-z` as the URL forms of `BlockKey` accept it: level at most
/// `MAX_LEVEL` (24), coordinates of up to 9 digits (every such number fits a u32; the
/// server also takes 10-digit ones that do).
const KEY: &str = "(?:[0-9]|1[0-9]|2[0-4])-[0-9]{1,9}-[0-9]{1,9}-[0-9]{1,9}";
/// No control characters (Rust's `char::is_control`: Unicode Cc).
const NO_CONTROL: &str = r"[^\x00-\x1f\x7f-\x9f]";
/// Neither a control character nor white space (Rust's `char::is_whitespace`).
const VISIBLE: &str = r"[^\x00-\x20\x7f-\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000]";

pub fn block_pattern() -> String {
    format!(r"^{KEY}(?:\.[0-9a-f]{{64}})?$")
}

pub fn page_pattern() -> String {
    format!(r"^{KEY}\.[0-9a-f]{{64}}$")
}

struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme("bearer", SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)));
    }
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "voxstream",
        description = "Upload meshes, follow their builds, browse the catalog and stream voxel blocks. \
            Errors are JSON {\"error\": \"...\"}. Write routes need `Authorization: Bearer <token>` when \
            the server has a token; with --protect-read, every route does. This document describes the \
            server that serves it: its auth, limits and read-only mode."
    ),
    paths(
        scenes::list_scenes,
        scenes::get_scene,
        scenes::patch_scene,
        scenes::delete_scene,
        scenes::get_manifest,
        scenes::get_block,
        scenes::get_page,
        scenes::post_batch,
        crate::thumbnail::get_thumbnail,
        uploads::post_scene,
        uploads::tus_options,
        uploads::tus_create,
        uploads::tus_head,
        uploads::tus_patch,
        uploads::tus_delete,
        jobs::list_jobs,
        jobs::get_job,
        jobs::cancel_job,
        jobs::job_events,
        openapi_json,
        super::healthz,
        super::metrics,
    ),
    modifiers(&BearerAuth),
    tags(
        (name = "scenes", description = "Catalog, manifests and content-addressed blocks"),
        (name = "uploads", description = "POST /api/scenes (single request) and tus 1.0.0 resumable uploads"),
        (name = "jobs", description = "Builds of uploaded meshes"),
        (name = "operations", description = "Health, metrics and this document")
    )
)]
pub struct ApiDoc;

#[utoipa::path(get, path = "/api/openapi.json", tag = "operations",
    responses((status = 200, description = "This document", content_type = "application/json")))]
pub async fn openapi_json(State(state): State<AppState>) -> Response {
    axum::Json(document(&state.config)).into_response()
}

const METHODS: [&str; 8] = ["get", "put", "post", "delete", "options", "head", "patch", "trace"];

/// The document for a server running with `config`.
pub fn document(config: &ServerConfig) -> Value {
    let mut doc = serde_json::to_value(ApiDoc::openapi()).expect("the OpenAPI document serialises");
    add_aliases(&mut doc);
    add_links(&mut doc);
    add_response_headers(&mut doc);
    let schemas = doc.pointer_mut("/components/schemas").and_then(Value::as_object_mut).expect("schemas");
    schemas.insert(
        "Error".into(),
        json!({
            "type": "object",
            "description": "Every error response's body.",
            "required": ["error"],
            "properties": { "error": { "type": "string" } }
        }),
    );
    schemas.insert(
        "SceneUpdate".into(),
        json!({
            "type": "object",
            "description": "Give a new id, a new display name, or both.",
            "minProperties": 1,
            "additionalProperties": false,
            "properties": {
                "id": { "type": "string", "pattern": SCENE_ID_PATTERN,
                    "description": "New id (the scene's URLs change; the directory is renamed atomically)." },
                "name": { "type": "string", "minLength": 1, "maxLength": 200,
                    "pattern": format!("^{NO_CONTROL}*{VISIBLE}{NO_CONTROL}*$"),
                    "description": "New display name: 1–200 characters, not all white space, no control characters." }
            }
        }),
    );
    schemas.insert(
        "BatchRequest".into(),
        json!({
            "type": "object",
            "required": ["blocks"],
            "additionalProperties": false,
            "properties": {
                "blocks": {
                    "type": "array", "minItems": 1, "maxItems": config.batch_max,
                    "items": { "type": "string", "pattern": block_pattern() },
                    "description": format!("Block names as in block URLs: `level-x-y-z.hash` (or `level-x-y-z`); \
                        at most {} bytes of blocks in all.", scenes::BATCH_MAX_BYTES)
                }
            }
        }),
    );
    let token = config.token.is_some();
    let paths = doc.get_mut("paths").and_then(Value::as_object_mut).expect("paths");
    for (path, item) in paths.iter_mut() {
        let item = item.as_object_mut().expect("path item");
        for method in METHODS {
            let Some(op) = item.get_mut(method).and_then(Value::as_object_mut) else { continue };
            let write = op.contains_key("security");
            // ReadAccess: everything under /api but tus discovery and this document, and /metrics.
            let read = !write
                && method != "options"
                && ((path.starts_with("/api/") && path != "/api/openapi.json") || path == "/metrics");
            // A --read-only server refuses writes (403) before it looks at a token.
            let token_required = token && ((write && !config.read_only) || (read && config.protect_read));
            // A bucket replica without --coordinator is read-only too (config.read_only is set):
            // with one it renames and deletes scenes like a local store, so no 403 there.
            let read_only_refusal = write && config.read_only;
            let rate_limited = config.uploads_per_minute > 0
                && method == "post"
                && matches!(path.as_str(), "/api/scenes" | "/api/uploads");
            // Only the statuses this server can answer with: the handlers' attributes list them all.
            let responses = op.get_mut("responses").and_then(Value::as_object_mut).expect("responses");
            for (status, applies) in
                [("401", token_required), ("403", read_only_refusal), ("429", rate_limited)]
            {
                if !applies {
                    responses.remove(status);
                }
            }
            if token_required {
                op.insert("security".into(), json!([{ "bearer": [] }]));
                add_response(op, "401", "Authorization: Bearer <token> is missing or wrong");
            } else {
                op.remove("security");
            }
            if read_only_refusal && config.bucket_scenes {
                add_response(
                    op,
                    "403",
                    "This replica serves a bucket read-only (no --coordinator, or --read-only)",
                );
            } else if read_only_refusal {
                add_response(op, "403", "This server is read-only (--read-only)");
            }
            if rate_limited {
                add_response(
                    op,
                    "429",
                    "Too many uploads from this client; Retry-After says when to try again",
                );
            }
            add_response(op, "431", "Request line and headers are larger than --max-header-bytes");
            fix_parameters(path, method, op, config);
            fix_body(path, method, op);
            error_bodies(method, op);
        }
    }
    doc
}

/// Routes served by a handler already in the document under another path or method.
fn add_aliases(doc: &mut Value) {
    let paths = doc.get_mut("paths").and_then(Value::as_object_mut).expect("paths");
    let mut options = paths["/api/uploads"]["options"].clone();
    options["operationId"] = json!("tus_options_upload");
    options["parameters"] =
        json!([{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }]);
    paths["/api/uploads/{id}"]["options"] = options;
    let mut cancel = paths["/api/jobs/{id}"]["delete"].clone();
    cancel["operationId"] = json!("cancel_job_post");
    cancel["description"] = json!("The same as DELETE /api/jobs/{id}, for clients that cannot send DELETE.");
    paths.insert("/api/jobs/{id}/cancel".into(), json!({ "post": cancel }));
}

/// OpenAPI links: how one response names what the next request uses (a client's
/// walk from the catalog to blocks, and from an upload to its job); schemathesis'
/// stateful phase follows them.
fn add_links(doc: &mut Value) {
    let link = |op: &str, params: Value| json!({ "operationId": op, "parameters": params });
    let upload_id = json!({ "id": "$response.header.Location#regex:/api/uploads/([0-9a-f]+)" });
    let job_from_body = json!({ "id": "$response.body#/id" });
    let first_scene = json!({ "id": "$response.body#/0/id" });
    let this_id = json!({ "id": "$request.path.id" });
    let links = [
        (
            "/api/scenes",
            "get",
            "200",
            json!({
                "GetScene": link("get_scene", first_scene.clone()),
                "GetManifest": link("get_manifest", first_scene.clone()),
                "GetThumbnail": link("get_thumbnail", first_scene),
            }),
        ),
        (
            "/api/scenes/{id}",
            "get",
            "200",
            json!({
                "GetManifest": link("get_manifest", this_id.clone()),
                "RenameScene": link("patch_scene", this_id.clone()),
            }),
        ),
        (
            "/api/scenes/{id}",
            "patch",
            "200",
            json!({
                "GetScene": link("get_scene", json!({ "id": "$response.body#/id" })),
            }),
        ),
        (
            "/api/scenes/{id}/manifest",
            "get",
            "200",
            json!({
                "GetRootBlock": link("get_block", json!({ "id": "$request.path.id", "block": "$response.body#/root/key" })),
            }),
        ),
        (
            "/api/scenes",
            "post",
            "202",
            json!({
                "GetJob": link("get_job", job_from_body.clone()),
                "JobEvents": link("job_events", job_from_body.clone()),
                "CancelJob": link("cancel_job", job_from_body),
            }),
        ),
        (
            "/api/uploads",
            "post",
            "201",
            json!({
                "UploadOffset": link("tus_head", upload_id.clone()),
                "AppendChunk": link("tus_patch", upload_id.clone()),
                "AbandonUpload": link("tus_delete", upload_id),
            }),
        ),
        (
            "/api/uploads/{id}",
            "patch",
            "204",
            json!({
                "UploadOffset": link("tus_head", this_id),
            }),
        ),
    ];
    for (path, method, status, l) in links {
        let response = doc
            .pointer_mut(&format!("/paths/{}/{method}/responses/{status}", path.replace('/', "~1")))
            .unwrap_or_else(|| panic!("no {status} response for {method} {path}"));
        response["links"] = l;
    }
}

/// Headers a response always carries (schemathesis checks that they are there).
fn add_response_headers(doc: &mut Value) {
    let text = |d: &str| json!({ "required": true, "description": d, "schema": { "type": "string" } });
    let digits = |d: &str| json!({ "required": true, "description": d, "schema": { "type": "string", "pattern": "^[0-9]+$" } });
    let tus = || text("1.0.0");
    let etag = || text("The blake3 hash in quotes (strong)");
    let cache =
        || text("Cache-Control: a year and immutable for content-addressed URLs, no-cache for key-only ones");
    let headers = [
        ("/api/scenes", "post", "202", json!({ "Location": text("/api/jobs/{id}: the build's job") })),
        (
            "/api/uploads",
            "options",
            "204",
            json!({
                "Tus-Resumable": tus(), "Tus-Version": text("1.0.0"),
                "Tus-Extension": text("creation,termination"), "Tus-Max-Size": digits("--max-upload-bytes"),
            }),
        ),
        (
            "/api/uploads/{id}",
            "options",
            "204",
            json!({
                "Tus-Resumable": tus(), "Tus-Version": text("1.0.0"),
                "Tus-Extension": text("creation,termination"), "Tus-Max-Size": digits("--max-upload-bytes"),
            }),
        ),
        (
            "/api/uploads",
            "post",
            "201",
            json!({
                "Location": text("/api/uploads/{id}: where to PATCH, HEAD and DELETE"), "Tus-Resumable": tus(),
            }),
        ),
        (
            "/api/uploads/{id}",
            "head",
            "200",
            json!({
                "Upload-Offset": digits("Bytes stored: where to resume"), "Upload-Length": digits("Total bytes"),
                "Tus-Resumable": tus(),
            }),
        ),
        (
            "/api/uploads/{id}",
            "patch",
            "204",
            json!({
                "Upload-Offset": digits("The new offset"), "Upload-Length": digits("Total bytes"), "Tus-Resumable": tus(),
            }),
        ),
        ("/api/uploads/{id}", "delete", "204", json!({ "Tus-Resumable": tus() })),
        (
            "/api/scenes/{id}/blocks/{block}",
            "get",
            "200",
            json!({ "ETag": etag(), "Cache-Control": cache() }),
        ),
        (
            "/api/scenes/{id}/blocks/{block}",
            "get",
            "304",
            json!({ "ETag": etag(), "Cache-Control": cache() }),
        ),
        ("/api/scenes/{id}/pages/{page}", "get", "200", json!({ "ETag": etag(), "Cache-Control": cache() })),
        ("/api/scenes/{id}/pages/{page}", "get", "304", json!({ "ETag": etag(), "Cache-Control": cache() })),
    ];
    for (path, method, status, h) in headers {
        let response = doc
            .pointer_mut(&format!("/paths/{}/{method}/responses/{status}", path.replace('/', "~1")))
            .unwrap_or_else(|| panic!("no {status} response for {method} {path}"));
        response["headers"] = h;
    }
}

fn add_response(op: &mut Map<String, Value>, status: &str, description: &str) {
    let responses = op.entry("responses").or_insert_with(|| json!({})).as_object_mut().expect("responses");
    let entry = responses.entry(status).or_insert_with(|| json!({}));
    if entry.get("description").and_then(Value::as_str).is_none_or(str::is_empty) {
        entry["description"] = json!(description);
    }
}

/// Every 4xx response carries `{"error": "..."}` (none for HEAD, which has no body).
fn error_bodies(method: &str, op: &mut Map<String, Value>) {
    let Some(responses) = op.get_mut("responses").and_then(Value::as_object_mut) else { return };
    for (status, response) in responses.iter_mut() {
        let response = response.as_object_mut().expect("response");
        if response.get("description").and_then(Value::as_str).is_none_or(str::is_empty) {
            response.insert("description".into(), json!(default_description(status)));
        }
        if status.starts_with('4') {
            if method == "head" {
                response.remove("content");
            } else {
                response.insert(
                    "content".into(),
                    json!({ "application/json": { "schema": { "$ref": "#/components/schemas/Error" } } }),
                );
            }
        }
    }
}

fn default_description(status: &str) -> &'static str {
    match status {
        "400" => "Malformed request",
        "401" => "Authorization: Bearer <token> is missing or wrong",
        "403" => "This server is read-only",
        "404" => "Not found",
        "409" => "Conflict with the current state",
        "412" => "Tus-Resumable is missing or not 1.0.0",
        "413" => "Larger than this server accepts",
        "415" => "Unsupported media type",
        "423" => "Another request is writing this upload",
        "429" => "Too many requests",
        _ => "See the operation's description",
    }
}

fn header(name: &str, required: bool, schema: Value, description: &str) -> Value {
    json!({ "name": name, "in": "header", "required": required, "schema": schema, "description": description })
}

fn tus_resumable() -> Value {
    header(
        "Tus-Resumable",
        true,
        json!({ "type": "string", "enum": ["1.0.0"] }),
        "The tus protocol version: 1.0.0",
    )
}

fn if_none_match() -> Value {
    header(
        "If-None-Match",
        false,
        json!({ "type": "string" }),
        "ETags from an earlier response (or *): 304 when one matches",
    )
}

/// Path parameter patterns and header/query schemas as the handlers check them.
fn fix_parameters(path: &str, method: &str, op: &mut Map<String, Value>, config: &ServerConfig) {
    let mut params: Vec<Value> = op.get("parameters").and_then(Value::as_array).cloned().unwrap_or_default();
    for p in &mut params {
        let name = p["name"].as_str().unwrap_or_default().to_string();
        let schema = match (p["in"].as_str(), name.as_str()) {
            // tus discovery answers any id.
            (Some("path"), "id") if method == "options" => json!({ "type": "string" }),
            (Some("path"), "id") if path.starts_with("/api/scenes/") => {
                json!({ "type": "string", "pattern": SCENE_ID_PATTERN })
            }
            (Some("path"), "id") => json!({ "type": "string", "pattern": JOB_ID_PATTERN }),
            (Some("path"), "block") => json!({ "type": "string", "pattern": block_pattern() }),
            (Some("path"), "page") => json!({ "type": "string", "pattern": page_pattern() }),
            (Some("query"), "id") => json!({ "type": "string", "pattern": SCENE_ID_PATTERN }),
            (Some("query"), "filename") => json!({
                "type": "string", "minLength": 1, "maxLength": 255, "pattern": format!("^{NO_CONTROL}+$")
            }),
            (Some("query"), "resolution") => {
                let mut r = 64u32;
                let mut allowed = Vec::new();
                while r <= config.max_resolution {
                    allowed.push(r);
                    r *= 2;
                }
                json!({ "type": "integer", "enum": allowed })
            }
            (Some("query"), "topology") => {
                json!({ "type": "string", "enum": ["conservative", "26-separating", "6-separating"] })
            }
            (Some("query"), "replace") => json!({ "type": "boolean", "default": false }),
            (Some("header"), "Tus-Resumable") => json!({ "type": "string", "enum": ["1.0.0"] }),
            // Header values are text: the integers are patterns, so that a checker reads them as sent.
            (Some("header"), "Upload-Length") => {
                json!({ "type": "string", "pattern": uint_pattern(1, config.max_upload_bytes) })
            }
            (Some("header"), "Upload-Offset") => {
                json!({ "type": "string", "pattern": uint_pattern(0, config.max_upload_bytes) })
            }
            (Some("header"), _) => json!({ "type": "string" }),
            _ => continue,
        };
        p["schema"] = schema;
        if p["in"] == "header" && name != "Upload-Metadata" {
            p["required"] =
                json!(name == "Tus-Resumable" || name == "Upload-Length" || name == "Upload-Offset");
        }
    }
    match (path, method) {
        (
            "/api/scenes/{id}/blocks/{block}"
            | "/api/scenes/{id}/pages/{page}"
            | "/api/scenes/{id}/thumbnail.png",
            "get",
        ) => params.push(if_none_match()),
        ("/api/scenes", "post") => params.push(header(
            "X-Filename",
            false,
            json!({ "type": "string", "minLength": 1, "maxLength": 255, "pattern": "^[\\x20-\\x7e]+$" }),
            "The mesh's file name when the query has no filename",
        )),
        ("/api/uploads/{id}", "head" | "delete") if !params.iter().any(|p| p["name"] == "Tus-Resumable") => {
            params.push(tus_resumable())
        }
        _ => {}
    }
    if !params.is_empty() {
        op.insert("parameters".into(), Value::Array(params));
    }
}

/// The decimal texts Rust's `u64::from_str` reads as a number from `min` (0 or 1) to `max`:
/// an optional `+`, any leading zeros, then the digits.
pub fn uint_pattern(min: u64, max: u64) -> String {
    let digits: Vec<u32> = max.to_string().bytes().map(|b| u32::from(b - b'0')).collect();
    let k = digits.len();
    let mut alts = Vec::new();
    if min == 0 {
        alts.push("0".to_string());
    }
    // Fewer digits than max.
    if k > 1 {
        alts.push(if k == 2 { "[1-9]".to_string() } else { format!("[1-9][0-9]{{0,{}}}", k - 2) });
    }
    // As many digits: max's first i digits, a smaller one, then anything.
    for i in 0..k {
        let lo = if i == 0 { 1 } else { 0 };
        if digits[i] > lo {
            let prefix: String = digits[..i].iter().map(|d| char::from_digit(*d, 10).unwrap()).collect();
            let range =
                if digits[i] - 1 == lo { lo.to_string() } else { format!("[{lo}-{}]", digits[i] - 1) };
            let rest = if k - i - 1 > 0 { format!("[0-9]{{{}}}", k - i - 1) } else { String::new() };
            alts.push(format!("{prefix}{range}{rest}"));
        }
    }
    alts.push(max.to_string());
    format!(r"^\+?0*(?:{})$", alts.join("|"))
}

/// Binary bodies are bytes (utoipa renders `Vec<u8>` as an array of integers).
fn fix_body(path: &str, method: &str, op: &mut Map<String, Value>) {
    let media = match (path, method) {
        ("/api/scenes", "post") => "application/octet-stream",
        ("/api/uploads/{id}", "patch") => "application/offset+octet-stream",
        ("/api/scenes/{id}", "patch") | ("/api/scenes/{id}/blocks/batch", "post") => {
            if let Some(body) = op.get_mut("requestBody") {
                body["required"] = json!(true);
            }
            add_response(op, "413", "The JSON body is larger than the server reads (256 KiB)");
            return;
        }
        _ => return,
    };
    op.insert(
        "requestBody".into(),
        json!({
            "required": true,
            "content": { media: { "schema": { "type": "string", "format": "binary" } } }
        }),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uint_patterns_match_exactly_the_range() {
        for max in [1u64, 9, 10, 17, 100, 999, 1000, 17_179_869_184] {
            for min in [0u64, 1] {
                let re = regex::Regex::new(&uint_pattern(min, max)).unwrap();
                let probe = (0..=200u64).chain([max.saturating_sub(1), max, max + 1, max * 10, max * 10 + 9]);
                for n in probe {
                    assert_eq!(re.is_match(&n.to_string()), (min..=max).contains(&n), "{min}..={max}: {n}");
                }
                assert!(re.is_match(&format!("+00{max}")));
                assert!(!re.is_match("-1") && !re.is_match("") && !re.is_match("1 "));
            }
        }
    }

    #[test]
    fn every_path_parameter_has_a_pattern_and_every_4xx_a_json_body() {
        let mut config = ServerConfig::new(std::path::Path::new("/nonexistent"));
        config.token = Some("t".into());
        let doc = document(&config);
        for (path, item) in doc["paths"].as_object().unwrap() {
            for (method, op) in item.as_object().unwrap() {
                for p in op["parameters"].as_array().into_iter().flatten() {
                    if p["in"] == "path" && method != "options" {
                        assert!(p["schema"]["pattern"].is_string(), "{method} {path}: {p}");
                    }
                }
                for (status, r) in op["responses"].as_object().unwrap() {
                    if status.starts_with('4') && method != "head" {
                        assert_eq!(
                            r["content"]["application/json"]["schema"]["$ref"], "#/components/schemas/Error",
                            "{method} {path} {status}"
                        );
                    }
                }
            }
        }
        let ids: Vec<&str> = doc["paths"]
            .as_object()
            .unwrap()
            .values()
            .flat_map(|item| item.as_object().unwrap().values())
            .filter_map(|op| op["operationId"].as_str())
            .collect();
        let mut unique = ids.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), ids.len(), "operationIds are unique: {ids:?}");
        for item in doc["paths"].as_object().unwrap().values() {
            for op in item.as_object().unwrap().values() {
                for r in op["responses"].as_object().unwrap().values() {
                    for l in r["links"].as_object().into_iter().flat_map(|l| l.values()) {
                        assert!(ids.contains(&l["operationId"].as_str().unwrap()), "{l}");
                    }
                }
            }
        }
        assert!(doc["paths"]["/api/jobs/{id}/cancel"]["post"].is_object());
        assert!(doc["paths"]["/api/uploads/{id}"]["options"].is_object());
        assert!(doc["paths"]["/api/uploads"]["post"]["responses"]["401"].is_object());
        assert!(doc["paths"]["/api/scenes"]["get"]["responses"]["401"].is_null(), "reads are public");
        assert!(doc["paths"]["/api/scenes"]["post"]["responses"]["403"].is_null(), "not read-only");

        let mut config = ServerConfig::new(std::path::Path::new("/nonexistent"));
        config.read_only = true;
        config.uploads_per_minute = 0;
        let doc = document(&config);
        let upload = &doc["paths"]["/api/scenes"]["post"];
        assert!(upload["responses"]["403"].is_object() && upload["responses"]["401"].is_null(), "{upload}");
        assert!(upload["responses"]["429"].is_null() && upload["security"].is_null(), "{upload}");
    }

    /// A bucket replica with a coordinator renames and deletes (no 403 declared); without one it is
    /// read-only, and every write route declares the 403 with the bucket's reason.
    #[test]
    fn bucket_replicas_declare_403_only_where_it_happens() {
        let mut config = ServerConfig::new(std::path::Path::new("/nonexistent"));
        config.bucket_scenes = true;
        let doc = document(&config);
        for method in ["patch", "delete"] {
            let op = &doc["paths"]["/api/scenes/{id}"][method];
            assert!(op["responses"]["403"].is_null(), "{method}: {op}");
            assert!(op["responses"]["409"].is_object(), "{method}: {op}");
        }
        assert!(doc["paths"]["/api/uploads"]["post"]["responses"]["403"].is_null());
        config.read_only = true;
        let doc = document(&config);
        for (path, method) in
            [("/api/scenes/{id}", "patch"), ("/api/scenes/{id}", "delete"), ("/api/uploads", "post")]
        {
            let refusal = &doc["paths"][path][method]["responses"]["403"];
            assert!(
                refusal["description"].as_str().unwrap().contains("bucket"),
                "{method} {path}: {refusal}"
            );
        }
    }
}
