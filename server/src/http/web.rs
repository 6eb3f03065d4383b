//! The viewer's files. By default they are the ones embedded in the binary at compile time
//! (rust-embed over `viewer-wasm/dist`, chosen by `server/build.rs`), so one `voxstream` binary
//! serves its own viewer; `--web <dir>` serves a folder instead (viewer development).
//!
//! A binary compiled before `scripts/build-web.sh` built the viewer embeds nothing: it answers
//! `/` (and every other non-API path) with a 404 page that says how to build the viewer.

use std::borrow::Cow;

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};

/// The viewer bundle compiled into the binary (`viewer-wasm/dist` at build time).
#[derive(rust_embed::RustEmbed)]
#[folder = "$VOXSTREAM_EMBED_WEB_DIR"]
pub struct EmbeddedViewer;

/// Revalidated on every use: the files change when the binary does.
pub const VIEWER_CACHE_CONTROL: &str = "no-cache";

/// Whether this binary embeds a viewer (`index.html` is among its files).
pub fn has_embedded_viewer() -> bool {
    EmbeddedViewer::get("index.html").is_some()
}

/// Every embedded file's path (relative, `/`-separated), sorted.
pub fn embedded_files() -> Vec<String> {
    let mut all: Vec<String> = EmbeddedViewer::iter().map(Cow::into_owned).collect();
    all.sort();
    all
}

/// One embedded file's bytes.
pub fn embedded_file(path: &str) -> Option<Cow<'static, [u8]>> {
    EmbeddedViewer::get(path).map(|f| f.data)
}

const NOT_BUILT: &str = "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>voxstream: no viewer</title></head>\n\
<body><h1>This voxstream binary has no viewer</h1>\n\
<p>It was compiled before the viewer was built, so it embeds no viewer files. The API under \
<a href=\"/api/scenes\">/api/scenes</a> works.</p>\n\
<p>Build the viewer with <code>bash scripts/build-web.sh</code>, then the server again \
(<code>cargo build --release -p voxstream</code>), or serve a built viewer folder with \
<code>voxstream serve --web viewer-wasm/dist</code>.</p></body></html>\n";

/// `GET`/`HEAD` for a path outside `/api`: the embedded file, `index.html` for a folder.
pub async fn serve_embedded(method: Method, uri: Uri, headers: HeaderMap) -> Response {
    if method != Method::GET && method != Method::HEAD {
        return super::ApiError::new(StatusCode::METHOD_NOT_ALLOWED, "the viewer's files are read-only")
            .with_header(header::ALLOW, HeaderValue::from_static("GET, HEAD"))
            .into_response();
    }
    let mut path = uri.path().trim_start_matches('/').to_string();
    if path.is_empty() || path.ends_with('/') {
        path.push_str("index.html");
    }
    let Some(file) = EmbeddedViewer::get(&path) else {
        if !has_embedded_viewer() {
            return (
                StatusCode::NOT_FOUND,
                [(header::CONTENT_TYPE, "text/html; charset=utf-8"), (header::CACHE_CONTROL, "no-store")],
                NOT_BUILT,
            )
                .into_response();
        }
        return super::ApiError::not_found(format!("no viewer file /{path}")).into_response();
    };
    let etag = HeaderValue::from_str(&format!("\"{}\"", hex(&file.metadata.sha256_hash())))
        .expect("hex is a valid header value");
    let mime = HeaderValue::from_str(file.metadata.mimetype())
        .unwrap_or(HeaderValue::from_static("application/octet-stream"));
    let cache = HeaderValue::from_static(VIEWER_CACHE_CONTROL);
    let matches = headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == etag || t.trim() == "*");
    if matches {
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag), (header::CACHE_CONTROL, cache)])
            .into_response();
    }
    let len = file.data.len();
    let body = if method == Method::HEAD { Body::empty() } else { Body::from(file.data) };
    let mut resp =
        ([(header::CONTENT_TYPE, mime), (header::ETAG, etag), (header::CACHE_CONTROL, cache)], body)
            .into_response();
    resp.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    resp
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
