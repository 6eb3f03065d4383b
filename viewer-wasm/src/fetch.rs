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
    /// `.../api/scenes/<id>`: `/manifest` and `/blocks/<key>.<hash>` (content-addressed,
    /// cached by the browser as immutable).
    #[cfg(target_arch = "wasm32")]
    Http { scene_url: String },
}

impl BlockSource {
    pub async fn manifest_bytes(&self) -> Result<Vec<u8>, FetchError> {
        match self {
            #[cfg(not(target_arch = "wasm32"))]
            BlockSource::SceneDir(dir) => read_file(&dir.join("manifest.json"), "manifest"),
            #[cfg(target_arch = "wasm32")]
            BlockSource::Http { scene_url } => {
                http::get_bytes(&format!("{scene_url}/manifest"), "manifest").await
            }
        }
    }

    /// A hierarchy page's bytes (content-addressed like blocks).
    pub async fn page_bytes(&self, page: &PageRef) -> Result<Vec<u8>, FetchError> {
        let what = format!("hierarchy page {}", page.root);
        match self {
            #[cfg(not(target_arch = "wasm32"))]
            BlockSource::SceneDir(dir) => {
                read_file(&dir.join(voxstream_format::hierarchy::page_path(&page.root)), &what)
            }
            #[cfg(target_arch = "wasm32")]
            BlockSource::Http { scene_url } => {
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
        let BlockSource::Http { scene_url } = self;
        let what = format!("hierarchy page {}", page.root);
        http::get_bytes_with(&format!("{scene_url}/pages/{}.{}", page.root, page.hash), &what, signal).await
    }

    /// [`BlockSource::block_bytes`], abortable through `signal` in the browser.
    #[cfg(target_arch = "wasm32")]
    pub async fn block_bytes_with(
        &self,
        key: BlockKey,
        hash: Option<&str>,
        signal: Option<&web_sys::AbortSignal>,
    ) -> Result<Vec<u8>, FetchError> {
        http::get_bytes_with(&self.block_url(key, hash), &format!("block {key}"), signal).await
    }

    /// The URL of a block (immutable when `hash` is given).
    #[cfg(target_arch = "wasm32")]
    pub fn block_url(&self, key: BlockKey, hash: Option<&str>) -> String {
        let BlockSource::Http { scene_url } = self;
        match hash {
            Some(h) => format!("{scene_url}/blocks/{key}.{h}"),
            None => format!("{scene_url}/blocks/{key}"),
        }
    }

    /// A block's bytes; `hash` is its blake3 from the manifest, which makes the
    /// URL immutable (without it the server answers with a revalidated URL).
    /// `range` is where a store directory keeps it (`SceneIndex::pack_range`;
    /// `None`: its own file); the server finds that itself.
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
            BlockSource::Http { scene_url } => {
                let _ = range;
                let url = match hash {
                    Some(h) => format!("{scene_url}/blocks/{key}.{h}"),
                    None => format!("{scene_url}/blocks/{key}"),
                };
                http::get_bytes(&url, &format!("block {key}")).await
            }
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
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;

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
