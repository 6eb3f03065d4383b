//! Where manifest and block bytes come from: the server's HTTP API in the
//! browser, a store's scene directory natively (tests). Only this module knows
//! the difference; everything downstream sees bytes or a [`FetchError`].

use voxstream_format::{BlockKey, PackRange, PageRef};

#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum FetchError {
    #[error("{what} not found")]
    NotFound { what: String },
    #[error("{what}: HTTP {status}")]
    Status { what: String, status: u16 },
    #[error("{what}: {message}")]
    Failed { what: String, message: String },
}

/// A scene's bytes, addressed as the store layout and HTTP API in CONTRACTS.md do.
#[derive(Debug, Clone)]
pub enum BlockSource {
    /// `<store>/<scene-id>/`: `manifest.json`, `pages/<key>.vxh` and the blocks
    /// as ranges of `packs/<hash>.vxp` (or, from older builds, `blocks/<key>.vxb`).
    #[cfg(not(target_arch = "wasm32"))]
    SceneDir(std::path::PathBuf),
    /// `.../api/scenes/<id>`: `/manifest`, `/pages/<key>.<hash>` and the blocks, content-addressed
    /// and cached by the browser as immutable: through the API each at `/blocks/<key>.<hash>`; on
    /// a static site (`static_packs`, from `voxstream publish`) as a range of
    /// `/packs/<hash>.vxp`, at `?r=<start>-<end>` with `Range: bytes=<start>-<end>`.
    #[cfg(target_arch = "wasm32")]
    Http { scene_url: String, static_packs: bool },
}

/// How to GET one block: its URL and, on a static site, its bytes' range of the pack the URL
/// names (inclusive, as HTTP's `Range: bytes=start-end`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockRequest {
    pub url: String,
    pub range: Option<(u64, u64)>,
}

/// The request for a block: its own API URL (immutable when `hash` is given), or, on a static
/// site, its range of its pack with the range also in the query, so each block's URL is its own
/// and no cache mixes two ranges of one pack.
pub fn block_request(
    scene_url: &str,
    static_packs: bool,
    key: BlockKey,
    hash: Option<&str>,
    range: Option<&PackRange>,
) -> BlockRequest {
    match (static_packs, range) {
        (true, Some(r)) if r.bytes > 0 => {
            let (start, end) = (r.offset, r.end() - 1);
            BlockRequest {
                url: format!(
                    "{scene_url}/{}?r={start}-{end}",
                    voxstream_format::hierarchy::pack_path(&r.pack.hash)
                ),
                range: Some((start, end)),
            }
        }
        _ => BlockRequest {
            url: match hash {
                Some(h) => format!("{scene_url}/blocks/{key}.{h}"),
                None => format!("{scene_url}/blocks/{key}"),
            },
            range: None,
        },
    }
}

impl BlockSource {
    pub async fn manifest_bytes(&self) -> Result<Vec<u8>, FetchError> {
        match self {
            #[cfg(not(target_arch = "wasm32"))]
            BlockSource::SceneDir(dir) => read_file(&dir.join("manifest.json"), "manifest"),
            #[cfg(target_arch = "wasm32")]
            BlockSource::Http { scene_url, .. } => {
                http::get_bytes(&format!("{scene_url}/manifest"), "manifest").await
            }
        }
    }

    /// A hierarchy page's bytes (content-addressed like blocks): from its pack range in a scene
    /// folder (`range`, from [`voxstream_format::SceneIndex::page_range`]), by its URL over HTTP.
    pub async fn page_bytes(&self, page: &PageRef, range: Option<&PackRange>) -> Result<Vec<u8>, FetchError> {
        let what = format!("hierarchy page {}", page.root);
        match self {
            #[cfg(not(target_arch = "wasm32"))]
            BlockSource::SceneDir(dir) => match range {
                Some(r) => {
                    read_range(&dir.join(voxstream_format::hierarchy::pack_path(&r.pack.hash)), r, &what)
                }
                None => read_file(&dir.join(voxstream_format::hierarchy::page_path(&page.root)), &what),
            },
            #[cfg(target_arch = "wasm32")]
            BlockSource::Http { scene_url, .. } => {
                let _ = range; // the server (or a static site's page files) answers by page URL
                http::get_bytes(&format!("{scene_url}/pages/{}.{}", page.root, page.hash), &what).await
            }
        }
    }

    /// [`BlockSource::page_bytes`], abortable through `signal` in the browser.
    #[cfg(target_arch = "wasm32")]
    pub async fn page_bytes_with(
        &self,
        page: &PageRef,
        signal: Option<&web_sys::AbortSignal>,
    ) -> Result<Vec<u8>, FetchError> {
        let BlockSource::Http { scene_url, .. } = self;
        let what = format!("hierarchy page {}", page.root);
        http::get_bytes_with(&format!("{scene_url}/pages/{}.{}", page.root, page.hash), &what, signal).await
    }

    /// [`BlockSource::block_bytes`], abortable through `signal` in the browser.
    #[cfg(target_arch = "wasm32")]
    pub async fn block_bytes_with(
        &self,
        key: BlockKey,
        hash: Option<&str>,
        range: Option<&PackRange>,
        signal: Option<&web_sys::AbortSignal>,
    ) -> Result<Vec<u8>, FetchError> {
        let request = self.block_request(key, hash, range);
        http::get_block(&request, &format!("block {key}"), signal).await
    }

    /// How to GET a block (see [`block_request`]).
    #[cfg(target_arch = "wasm32")]
    pub fn block_request(
        &self,
        key: BlockKey,
        hash: Option<&str>,
        range: Option<&PackRange>,
    ) -> BlockRequest {
        let BlockSource::Http { scene_url, static_packs } = self;
        block_request(scene_url, *static_packs, key, hash, range)
    }

    /// A block's bytes; `hash` is its blake3 from the manifest, which makes the
    /// URL immutable (without it the server answers with a revalidated URL).
    /// `range` is where the scene keeps it (`SceneIndex::pack_range`; `None`: its own file):
    /// read from a store directory or, on a static site, a range request; the API server
    /// finds it itself.
    pub async fn block_bytes(
        &self,
        key: BlockKey,
        hash: Option<&str>,
        range: Option<&PackRange>,
    ) -> Result<Vec<u8>, FetchError> {
        match self {
            #[cfg(not(target_arch = "wasm32"))]
            BlockSource::SceneDir(dir) => {
                let _ = hash; // the store path has no hash; decode checks the block against the manifest
                let what = format!("block {key}");
                match range {
                    Some(r) => {
                        read_range(&dir.join(voxstream_format::hierarchy::pack_path(&r.pack.hash)), r, &what)
                    }
                    None => read_file(&dir.join("blocks").join(format!("{key}.vxb")), &what),
                }
            }
            #[cfg(target_arch = "wasm32")]
            BlockSource::Http { .. } => self.block_bytes_with(key, hash, range, None).await,
        }
    }
}

#[cfg(not(target_arch = "wasm32"))]
fn read_file(path: &std::path::Path, what: &str) -> Result<Vec<u8>, FetchError> {
    std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => FetchError::NotFound { what: format!("{what} ({})", path.display()) },
        _ => FetchError::Failed { what: what.to_string(), message: format!("{}: {e}", path.display()) },
    })
}

/// One block's range of a pack file.
#[cfg(not(target_arch = "wasm32"))]
fn read_range(path: &std::path::Path, range: &PackRange, what: &str) -> Result<Vec<u8>, FetchError> {
    use std::io::{Read, Seek, SeekFrom};
    let mut file = std::fs::File::open(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => FetchError::NotFound { what: format!("{what} ({})", path.display()) },
        _ => FetchError::Failed { what: what.to_string(), message: format!("{}: {e}", path.display()) },
    })?;
    let mut bytes = vec![0u8; range.bytes as usize];
    file.seek(SeekFrom::Start(range.offset)).and_then(|_| file.read_exact(&mut bytes)).map_err(|e| {
        FetchError::Failed {
            what: what.to_string(),
            message: format!("{} at bytes {}..{}: {e}", path.display(), range.offset, range.end()),
        }
    })?;
    Ok(bytes)
}

#[cfg(target_arch = "wasm32")]
pub(crate) mod http {
    use super::FetchError;
    use wasm_bindgen::{JsCast, JsValue};
    use wasm_bindgen_futures::JsFuture;

    fn js_message(v: &JsValue) -> String {
        v.as_string()
            .or_else(|| v.dyn_ref::<js_sys::Error>().map(|e| String::from(e.message())))
            .unwrap_or_else(|| format!("{v:?}"))
    }

    /// GET `url` and return the body; non-2xx statuses are errors.
    pub async fn get_bytes(url: &str, what: &str) -> Result<Vec<u8>, FetchError> {
        get_bytes_with(url, what, None).await
    }

    /// [`get_bytes`] that `signal` can abort.
    pub async fn get_bytes_with(
        url: &str,
        what: &str,
        signal: Option<&web_sys::AbortSignal>,
    ) -> Result<Vec<u8>, FetchError> {
        let failed = |e: JsValue| FetchError::Failed { what: what.to_string(), message: js_message(&e) };
        let window = web_sys::window().ok_or_else(|| failed(JsValue::from_str("no window")))?;
        let init = web_sys::RequestInit::new();
        if let Some(signal) = signal {
            init.set_signal(Some(signal));
        }
        let response: web_sys::Response = JsFuture::from(window.fetch_with_str_and_init(url, &init))
            .await
            .map_err(failed)?
            .dyn_into()
            .map_err(failed)?;
        match response.status() {
            200..=299 => {}
            404 => return Err(FetchError::NotFound { what: what.to_string() }),
            status => return Err(FetchError::Status { what: what.to_string(), status }),
        }
        let buffer = JsFuture::from(response.array_buffer().map_err(failed)?).await.map_err(failed)?;
        Ok(js_sys::Uint8Array::new(&buffer).to_vec())
    }

    /// A block's bytes: a plain GET, or a range request whose answer may be a 206 with the
    /// range or a 200 with the whole pack (a host that ignores Range), then sliced here. The
    /// same rules as web/block-fetch.js, which the decode workers use.
    pub async fn get_block(
        request: &super::BlockRequest,
        what: &str,
        signal: Option<&web_sys::AbortSignal>,
    ) -> Result<Vec<u8>, FetchError> {
        let Some((start, end)) = request.range else {
            return get_bytes_with(&request.url, what, signal).await;
        };
        let failed = |e: JsValue| FetchError::Failed { what: what.to_string(), message: js_message(&e) };
        let window = web_sys::window().ok_or_else(|| failed(JsValue::from_str("no window")))?;
        let init = web_sys::RequestInit::new();
        if let Some(signal) = signal {
            init.set_signal(Some(signal));
        }
        let headers = web_sys::Headers::new().map_err(failed)?;
        headers.set("Range", &format!("bytes={start}-{end}")).map_err(failed)?;
        init.set_headers(&headers);
        let response: web_sys::Response = JsFuture::from(window.fetch_with_str_and_init(&request.url, &init))
            .await
            .map_err(failed)?
            .dyn_into()
            .map_err(failed)?;
        let status = response.status();
        match status {
            200 | 206 => {}
            404 => return Err(FetchError::NotFound { what: what.to_string() }),
            status => return Err(FetchError::Status { what: what.to_string(), status }),
        }
        let buffer = JsFuture::from(response.array_buffer().map_err(failed)?).await.map_err(failed)?;
        let body = js_sys::Uint8Array::new(&buffer).to_vec();
        super::slice_range_answer(status, body, start, end)
            .map_err(|message| FetchError::Failed { what: what.to_string(), message })
    }
}

/// The block's bytes from the answer to `Range: bytes=start-end`: a 206 must be exactly the
/// range; a 200 (the host ignored Range) is the whole pack, sliced here.
pub fn slice_range_answer(status: u16, mut body: Vec<u8>, start: u64, end: u64) -> Result<Vec<u8>, String> {
    let want = end.saturating_sub(start) + 1;
    match status {
        206 if body.len() as u64 == want => Ok(body),
        206 => Err(format!("HTTP 206 with {} bytes, asked for {want}", body.len())),
        _ if (body.len() as u64) <= end => {
            Err(format!("the pack is {} bytes, the block ends at byte {end}", body.len()))
        }
        _ => {
            body.truncate(end as usize + 1);
            Ok(body.split_off(start as usize))
        }
    }
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;

    #[test]
    fn static_sites_name_a_range_of_the_pack_in_the_url() {
        let pack = voxstream_format::PackRef { hash: "cd".repeat(32), bytes: 100 };
        let range = PackRange { pack, offset: 10, bytes: 5 };
        let key = BlockKey::new(0, 1, 2, 3);
        let api = block_request("api/scenes/k", false, key, Some("ab"), Some(&range));
        assert_eq!(api, BlockRequest { url: "api/scenes/k/blocks/0-1-2-3.ab".into(), range: None });
        let site = block_request("api/scenes/k", true, key, Some("ab"), Some(&range));
        let url = format!("api/scenes/k/packs/{}.vxp?r=10-14", "cd".repeat(32));
        assert_eq!(site, BlockRequest { url, range: Some((10, 14)) });
        // A 206 must be the range; a 200 is the whole pack, sliced; a short pack is an error.
        let pack_bytes: Vec<u8> = (0..100).collect();
        assert_eq!(
            slice_range_answer(206, pack_bytes[10..15].to_vec(), 10, 14).unwrap(),
            &pack_bytes[10..15]
        );
        assert!(slice_range_answer(206, pack_bytes[10..16].to_vec(), 10, 14).is_err());
        assert_eq!(slice_range_answer(200, pack_bytes.clone(), 10, 14).unwrap(), &pack_bytes[10..15]);
        assert!(slice_range_answer(200, pack_bytes[..14].to_vec(), 10, 14).is_err());
    }

    #[test]
    fn scene_dir_reads_the_store_layout() {
        let dir = std::env::temp_dir().join(format!("voxstream-fetch-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("blocks")).unwrap();
        std::fs::write(dir.join("manifest.json"), b"{}").unwrap();
        std::fs::write(dir.join("blocks/2-0-1-0.vxb"), b"xyz").unwrap();
        let src = BlockSource::SceneDir(dir.clone());
        assert_eq!(pollster::block_on(src.manifest_bytes()).unwrap(), b"{}");
        assert_eq!(
            pollster::block_on(src.block_bytes(BlockKey::new(2, 0, 1, 0), Some("ab"), None)).unwrap(),
            b"xyz"
        );
        let missing = pollster::block_on(src.block_bytes(BlockKey::new(0, 0, 0, 0), None, None)).unwrap_err();
        assert!(matches!(missing, FetchError::NotFound { .. }), "{missing}");
        // A packed block: its range of the pack.
        let hash = "ab".repeat(32);
        std::fs::create_dir_all(dir.join("packs")).unwrap();
        std::fs::write(dir.join(format!("packs/{hash}.vxp")), b"0123456789").unwrap();
        let pack = voxstream_format::PackRef { hash, bytes: 10 };
        let range = PackRange { pack: pack.clone(), offset: 3, bytes: 4 };
        assert_eq!(
            pollster::block_on(src.block_bytes(BlockKey::new(1, 0, 0, 0), None, Some(&range))).unwrap(),
            b"3456"
        );
        let past = PackRange { pack, offset: 8, bytes: 4 };
        let short = pollster::block_on(src.block_bytes(BlockKey::new(1, 0, 0, 0), None, Some(&past)));
        assert!(matches!(short, Err(FetchError::Failed { .. })), "{short:?}");
        std::fs::remove_dir_all(dir).unwrap();
    }
}
