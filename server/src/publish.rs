//! `voxstream publish`: a scene and the viewer as a self-contained static site that any static
//! file host (nginx, `python3 -m http.server`, a bucket with website hosting) serves with no
//! voxstream process.
//!
//! The site repeats the API's layout for the manifest and pages and copies the store's packs as
//! they are, so a scene is a few files (a pack holds 256 blocks), not one per block:
//!
//! ```text
//! <to>/index.html                            the viewer page, with <meta name="voxstream-scene" content="<id>">
//!                                            and <meta name="voxstream-static" content="packs">
//! <to>/viewer.css, pkg/…, upload.*           the rest of the viewer's files
//! <to>/api/scenes/<id>/manifest              the manifest JSON (as stored)
//! <to>/api/scenes/<id>/pages/<key>.<hash>    every hierarchy page, content-addressed
//! <to>/api/scenes/<id>/packs/<hash>.vxp      every pack, content-addressed
//! <to>/.voxstream-publish                    marker: this folder is a publish (so it may be replaced)
//! ```
//!
//! The `voxstream-static` meta tells the viewer there is no API: it reads a block as
//! `packs/<hash>.vxp?r=<start>-<end>` with `Range: bytes=<start>-<end>`. The query makes each
//! block's URL its own, so no cache mixes two ranges of one file (Potree 2's loaders learned
//! this), and a host that ignores Range and answers 200 with the whole pack still works (the
//! viewer slices it and checks the block's hash). The viewer fetches with URLs relative to its
//! page, so the site works in any folder of a host.
//! Every pack is checked against its hash and every block in it against the block's hash, and
//! every page against its hash, before it is written. The site is written
//! into `<to>.tmp-*` beside `<to>` and renamed into place only when complete; an existing
//! publish at `<to>` is replaced whole (never a folder that is not a publish).

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use futures_util::FutureExt;
use rayon::prelude::*;
use voxstream_format::hierarchy::{content_hash, pack_path};
use voxstream_format::{PackRef, PageRef, load_scene_index};

use crate::store::{self, StoredScene};

/// Marks a folder written by `voxstream publish`.
pub const PUBLISH_MARKER: &str = ".voxstream-publish";

/// What a publish wrote.
#[derive(Debug, Clone)]
pub struct PublishReport {
    pub id: String,
    pub to: PathBuf,
    pub files: u64,
    pub bytes: u64,
    pub blocks: u64,
    pub pages: u64,
    pub packs: u64,
}

/// Where the viewer's files come from.
pub enum ViewerFiles<'a> {
    /// The ones embedded in this binary.
    Embedded,
    /// A built viewer folder (`--web`).
    Dir(&'a Path),
}

/// Publishes scene `id` of the local store `store` as a static site at `to`.
pub fn publish(store: &Path, id: &str, to: &Path, viewer: ViewerFiles) -> anyhow::Result<PublishReport> {
    let scene = store::open_scene(store, id)
        .with_context(|| format!("cannot open scene {id:?} in {}", store.display()))?;
    let files = viewer_files(viewer)?;
    if to.exists() {
        let marked = to.join(PUBLISH_MARKER).is_file();
        let empty =
            fs::read_dir(to).with_context(|| format!("cannot read {}", to.display()))?.next().is_none();
        if !marked && !empty {
            bail!(
                "{} exists and is not a voxstream publish (no {PUBLISH_MARKER}): refusing to replace it; \
                 name a new folder or remove it",
                to.display()
            );
        }
    }
    let parent = match to.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    fs::create_dir_all(&parent).with_context(|| format!("cannot create {}", parent.display()))?;
    let name = to.file_name().and_then(|n| n.to_str()).context("--to must name a folder")?;
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let _ = fs::remove_dir_all(&tmp);
    let result = write_site(&tmp, &scene, &files).and_then(|report| {
        replace_dir(&tmp, to)?;
        Ok(PublishReport { to: to.to_path_buf(), ..report })
    });
    if result.is_err() {
        let _ = fs::remove_dir_all(&tmp);
    }
    result
}

fn viewer_files(viewer: ViewerFiles) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    let mut files = Vec::new();
    match viewer {
        ViewerFiles::Embedded => {
            if !crate::http::web::has_embedded_viewer() {
                bail!(
                    "this voxstream binary embeds no viewer (it was compiled before scripts/build-web.sh built \
                     viewer-wasm/dist): build the viewer and then voxstream again, or pass --web <viewer folder>"
                );
            }
            for path in crate::http::web::embedded_files() {
                let bytes = crate::http::web::embedded_file(&path).context("embedded file vanished")?;
                files.push((path, bytes.into_owned()));
            }
        }
        ViewerFiles::Dir(dir) => {
            if !dir.join("index.html").is_file() {
                bail!("{} has no index.html: build the viewer with scripts/build-web.sh", dir.display());
            }
            collect_dir(dir, dir, &mut files)?;
        }
    }
    Ok(files)
}

fn collect_dir(root: &Path, dir: &Path, out: &mut Vec<(String, Vec<u8>)>) -> anyhow::Result<()> {
    for entry in fs::read_dir(dir).with_context(|| format!("cannot read {}", dir.display()))? {
        let entry = entry?;
        let path = entry.path();
        if entry.file_type()?.is_dir() {
            collect_dir(root, &path, out)?;
        } else {
            let rel = path.strip_prefix(root)?.to_string_lossy().replace('\\', "/");
            out.push((rel, fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?));
        }
    }
    Ok(())
}

/// index.html with the scene named as the page's default, and marked as a static site (blocks
/// are range reads of packs, there is no API).
pub fn index_with_scene(html: &[u8], id: &str) -> anyhow::Result<Vec<u8>> {
    let html = std::str::from_utf8(html).context("the viewer's index.html is not UTF-8")?;
    let at = html.find("<head>").context("the viewer's index.html has no <head>")? + "<head>".len();
    // Scene ids are [a-z0-9_-]: nothing to escape.
    Ok(format!(
        "{}\n  <meta name=\"voxstream-scene\" content=\"{id}\">\n  <meta name=\"voxstream-static\" content=\"packs\">{}",
        &html[..at],
        &html[at..]
    )
    .into_bytes())
}

/// A block as its pack holds it: key, hash and byte range.
type PackedBlock = (voxstream_format::BlockKey, String, u64, u64);

/// A pack's bytes, checked against its name and length, and each of its `blocks` against
/// the block's hash.
fn read_checked_pack(scene: &StoredScene, pack: &PackRef, blocks: &[PackedBlock]) -> anyhow::Result<Vec<u8>> {
    let id = &scene.id;
    let path = scene.pack_path(&pack.hash);
    let bytes = fs::read(&path).with_context(|| format!("scene {id:?}: cannot read {}", path.display()))?;
    if bytes.len() as u64 != pack.bytes {
        bail!(
            "scene {id:?}: {} is truncated or grown: {} bytes, its pages say {} (damaged store)",
            pack_path(&pack.hash),
            bytes.len(),
            pack.bytes
        );
    }
    if content_hash(&bytes) != pack.hash {
        bail!("scene {id:?}: {} does not match its hash (damaged store)", pack_path(&pack.hash));
    }
    for (key, hash, start, end) in blocks {
        if content_hash(&bytes[*start as usize..*end as usize]) != *hash {
            bail!("block {key} of scene {id:?} differs from its hash in the hierarchy (damaged store)");
        }
    }
    Ok(bytes)
}

/// Every pack the scene's hierarchy names, in a fixed order, with the blocks each holds.
fn scene_packs(scene: &StoredScene) -> anyhow::Result<Vec<(PackRef, Vec<PackedBlock>)>> {
    let mut by_pack: std::collections::HashMap<String, Vec<PackedBlock>> = Default::default();
    let index = scene.index.read();
    for e in scene.blocks() {
        let r = index.pack_range(&e.key).with_context(|| {
            format!("scene {:?}: block {} is in no pack (rebuild the scene)", scene.id, e.key)
        })?;
        by_pack.entry(r.pack.hash.clone()).or_default().push((e.key, e.hash.clone(), r.offset, r.end()));
    }
    let mut packs: Vec<(PackRef, Vec<PackedBlock>)> =
        index.packs().map(|p| (p.clone(), by_pack.remove(&p.hash).unwrap_or_default())).collect();
    packs.sort_by(|a, b| a.0.hash.cmp(&b.0.hash));
    Ok(packs)
}

fn write_file(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut f = fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    f.write_all(bytes).with_context(|| format!("cannot write {}", path.display()))?;
    f.sync_all().with_context(|| format!("cannot sync {}", path.display()))
}

fn write_site(
    dir: &Path,
    scene: &StoredScene,
    viewer: &[(String, Vec<u8>)],
) -> anyhow::Result<PublishReport> {
    let id = &scene.id;
    let mut report = PublishReport {
        id: id.clone(),
        to: dir.to_path_buf(),
        files: 0,
        bytes: 0,
        blocks: 0,
        pages: 0,
        packs: 0,
    };
    let add = |path: &Path, bytes: &[u8], report: &mut PublishReport| -> anyhow::Result<()> {
        write_file(path, bytes)?;
        report.files += 1;
        report.bytes += bytes.len() as u64;
        Ok(())
    };
    for (rel, bytes) in viewer {
        let bytes = if rel == "index.html" { index_with_scene(bytes, id)? } else { bytes.clone() };
        add(&dir.join(rel), &bytes, &mut report)?;
    }
    let scene_dir = dir.join("api/scenes").join(id);
    // The manifest as stored (its hash names nothing; it is the scene's one mutable file).
    let manifest = fs::read(scene.dir().join("manifest.json")).context("cannot read the manifest")?;
    add(&scene_dir.join("manifest"), &manifest, &mut report)?;
    for (r, bytes) in &scene_pages(scene)? {
        add(&scene_dir.join("pages").join(format!("{}.{}", r.root, r.hash)), bytes, &mut report)?;
        report.pages += 1;
    }
    // Packs as the store has them, in parallel, each and every block in it checked.
    let packs = scene_packs(scene)?;
    let packs_dir = scene_dir.join("packs");
    fs::create_dir_all(&packs_dir).with_context(|| format!("cannot create {}", packs_dir.display()))?;
    let bytes: u64 = packs
        .par_iter()
        .map(|(p, blocks)| -> anyhow::Result<u64> {
            let data = read_checked_pack(scene, p, blocks)?;
            write_file(&scene_dir.join(pack_path(&p.hash)), &data)?;
            Ok(data.len() as u64)
        })
        .sum::<anyhow::Result<u64>>()?;
    report.blocks = scene.blocks().len() as u64;
    report.packs = packs.len() as u64;
    report.files += report.packs;
    report.bytes += bytes;
    add(&dir.join(PUBLISH_MARKER), format!("scene {id}\n").as_bytes(), &mut report)?;
    for d in [&packs_dir, &scene_dir, dir] {
        fs::File::open(d)
            .and_then(|f| f.sync_all())
            .with_context(|| format!("cannot sync {}", d.display()))?;
    }
    Ok(report)
}

/// Every hierarchy page of the scene with its bytes, each checked against its reference.
fn scene_pages(scene: &StoredScene) -> anyhow::Result<Vec<(PageRef, Vec<u8>)>> {
    let mut pages: Vec<(PageRef, Vec<u8>)> = Vec::new();
    load_scene_index(&scene.manifest, |r, range| {
        let bytes = match range {
            Some(range) => crate::store::read_pack_range(scene.dir(), &range)?,
            None => fs::read(scene.page_path(&r.root))?,
        };
        pages.push((r.clone(), bytes.clone()));
        Ok::<_, std::io::Error>(bytes)
    })
    .map_err(|e| anyhow::anyhow!("scene {:?}: {e}", scene.id))?;
    Ok(pages)
}

/// Content-Type of a site file by its extension.
pub fn content_type(rel: &str) -> &'static str {
    match rel.rsplit_once('.').map(|(_, ext)| ext) {
        Some("html") => "text/html; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("js" | "mjs") => "text/javascript; charset=utf-8",
        Some("wasm") => "application/wasm",
        Some("json") => "application/json",
        Some("png") => "image/png",
        Some("svg") => "image/svg+xml",
        _ => "application/octet-stream",
    }
}

/// Objects written at once by [`publish_to_bucket`] (each at most one pack, ≤ 8 MiB, or one page
/// in memory).
pub const BUCKET_CONCURRENCY: usize = 8;

/// Publishes scene `id` of the local store `store` to a bucket (S3, R2, MinIO, Garage with
/// website hosting) in the layout of [`publish`]: packs, pages and the viewer's files first,
/// [`BUCKET_CONCURRENCY`] at a time, then the manifest, then `index.html`. Packs and pages are
/// content-addressed, so an
/// earlier publish at the same prefix keeps working until the manifest (one atomic PUT) switches
/// to the new scene; a failed publish leaves the earlier one as it was.
pub async fn publish_to_bucket(
    store: &Path,
    id: &str,
    bucket: &crate::objstore::Bucket,
    viewer: ViewerFiles<'_>,
) -> anyhow::Result<PublishReport> {
    use futures_util::{StreamExt, TryStreamExt};
    const IMMUTABLE: &str = "public, max-age=31536000, immutable";
    const REVALIDATE: &str = "no-cache";
    let scene = std::sync::Arc::new(
        store::open_scene(store, id)
            .with_context(|| format!("cannot open scene {id:?} in {}", store.display()))?,
    );
    let files = viewer_files(viewer)?;
    let pages = scene_pages(&scene)?;
    let scene_prefix = format!("api/scenes/{id}");
    let mut report = PublishReport {
        id: id.to_string(),
        to: PathBuf::from(format!("s3://{}/{}", bucket.bucket, bucket.prefix)),
        files: 0,
        bytes: 0,
        blocks: 0,
        pages: pages.len() as u64,
        packs: 0,
    };
    // 1. Content-addressed objects and the viewer's files (not index.html).
    let packs = scene_packs(&scene)?;
    report.packs = packs.len() as u64;
    let pack_puts = futures_util::stream::iter(packs.into_iter().map(|(p, blocks)| {
        let rel = format!("{scene_prefix}/{}", pack_path(&p.hash));
        let scene = scene.clone();
        async move {
            let data = tokio::task::spawn_blocking(move || read_checked_pack(&scene, &p, &blocks)).await??;
            let n = data.len() as u64;
            bucket.put(&rel, data, "application/octet-stream", IMMUTABLE).await?;
            Ok::<u64, anyhow::Error>(n)
        }
        .boxed()
    }));
    let page_puts = futures_util::stream::iter(pages.into_iter().map(|(r, bytes)| {
        let rel = format!("{scene_prefix}/pages/{}.{}", r.root, r.hash);
        async move {
            let n = bytes.len() as u64;
            bucket.put(&rel, bytes, "application/octet-stream", IMMUTABLE).await?;
            Ok(n)
        }
        .boxed()
    }));
    let mut index_html = None;
    let mut viewer_puts = Vec::new();
    for (rel, bytes) in files {
        if rel == "index.html" {
            index_html = Some(index_with_scene(&bytes, id)?);
            continue;
        }
        viewer_puts.push(
            async move {
                let n = bytes.len() as u64;
                bucket.put(&rel, bytes, content_type(&rel), REVALIDATE).await?;
                Ok(n)
            }
            .boxed(),
        );
    }
    let index_html = index_html.context("the viewer has no index.html")?;
    let (count, bytes) = pack_puts
        .chain(page_puts)
        .chain(futures_util::stream::iter(viewer_puts))
        .buffer_unordered(BUCKET_CONCURRENCY)
        .try_fold((0u64, 0u64), |(c, b), n| async move { Ok((c + 1, b + n)) })
        .await?;
    report.blocks = scene.blocks().len() as u64;
    report.files += count;
    report.bytes += bytes;
    // 2. The scene's one mutable pointer, then the page that names it.
    let manifest = fs::read(scene.dir().join("manifest.json")).context("cannot read the manifest")?;
    report.bytes += manifest.len() as u64 + index_html.len() as u64;
    bucket.put(&format!("{scene_prefix}/manifest"), manifest, "application/json", REVALIDATE).await?;
    bucket.put("index.html", index_html, "text/html; charset=utf-8", REVALIDATE).await?;
    report.files += 2;
    Ok(report)
}

/// Moves the finished site `tmp` to `to`, replacing an earlier publish there.
fn replace_dir(tmp: &Path, to: &Path) -> anyhow::Result<()> {
    if to.exists() {
        let old = to.with_file_name(format!(
            ".{}.old-{}",
            to.file_name().and_then(|n| n.to_str()).unwrap_or("site"),
            std::process::id()
        ));
        fs::rename(to, &old)
            .with_context(|| format!("cannot move the earlier publish {} aside", to.display()))?;
        if let Err(e) = fs::rename(tmp, to) {
            let _ = fs::rename(&old, to);
            return Err(e).with_context(|| format!("cannot publish {}", to.display()));
        }
        let _ = fs::remove_dir_all(&old);
    } else {
        fs::rename(tmp, to).with_context(|| format!("cannot publish {}", to.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_gets_the_scene() {
        let html = b"<!doctype html>\n<html><head>\n<title>x</title></head><body></body></html>";
        let out = String::from_utf8(index_with_scene(html, "koala").unwrap()).unwrap();
        assert!(
            out.contains(
                "<head>\n  <meta name=\"voxstream-scene\" content=\"koala\">\n  \
                 <meta name=\"voxstream-static\" content=\"packs\">\n<title>"
            ),
            "{out}"
        );
        assert!(index_with_scene(b"<html><body></body></html>", "koala").is_err());
    }
}
