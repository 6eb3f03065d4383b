//! The HTTP API on an ephemeral port: catalog, content-addressed blocks and
//! batches, uploads (single request and tus, including a resume after a cut
//! connection), jobs with SSE, renames and deletes, access rules, limits and
//! operations. Every error is checked to be a JSON body with the right status.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use base64::Engine;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;
use voxstream::config::ServerConfig;
use voxstream::http::{AppState, BLOCK_CACHE_CONTROL, router};
use voxstream::pipeline::{BuildOptions, Resolution, build_scene};
use voxstream_format::{BlockKey, Manifest, SceneSummary, decode_block};

const TOKEN: &str = "s3cret-token";

/// A closed box with a notch, written as OBJ: enough to give several blocks and levels.
fn box_obj() -> String {
    let mut obj = String::new();
    let v = [
        [0., 0., 0.],
        [4., 0., 0.],
        [4., 3., 0.],
        [0., 3., 0.],
        [0., 0., 2.],
        [4., 0., 2.],
        [4., 3., 2.],
        [0., 3., 2.],
    ];
    for p in v {
        obj += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    obj += "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 8 7\nf 4 7 3\nf 1 5 8\nf 1 8 4\nf 2 3 7\nf 2 7 6\n";
    obj
}

fn write_test_mesh(path: &Path) {
    std::fs::write(path, box_obj()).unwrap();
}

fn koala() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")
}

struct Server {
    base: String,
    addr: SocketAddr,
    state: AppState,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

async fn start_with(config: ServerConfig) -> Server {
    let shutdown = CancellationToken::new();
    let state = AppState::start(config, shutdown.clone()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let app = router(state.clone()).into_make_service_with_connect_info::<SocketAddr>();
    let token = shutdown.clone();
    let task = tokio::spawn(async move {
        axum::serve(listener, app).with_graceful_shutdown(token.cancelled_owned()).await.unwrap()
    });
    Server { base: format!("http://{addr}"), addr, state, shutdown, task }
}

fn config(store: &Path) -> ServerConfig {
    let mut c = ServerConfig::new(store);
    c.token = Some(TOKEN.into());
    c.resolution = Some(64);
    c.max_resolution = 2048;
    c
}

/// The compatible read-only server the browser test uses.
async fn start_read_only(store: &Path) -> String {
    let state = AppState::load(store, None).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, router(state)).await.unwrap() });
    format!("http://{addr}")
}

async fn json_error(resp: reqwest::Response, status: u16) -> String {
    let url = resp.url().clone();
    assert_eq!(resp.status().as_u16(), status, "{url}");
    assert_eq!(resp.headers()["content-type"], "application/json", "{url}");
    let body: serde_json::Value = resp.json().await.unwrap();
    body["error"].as_str().expect("JSON body has an error string").to_string()
}

fn http() -> reqwest::Client {
    reqwest::Client::new()
}

fn auth(r: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
    r.bearer_auth(TOKEN)
}

async fn upload(base: &str, query: &str, body: impl Into<reqwest::Body>) -> reqwest::Response {
    auth(http().post(format!("{base}/api/scenes?{query}"))).body(body).send().await.unwrap()
}

/// Follows a job's SSE stream to its end; returns (event name, job JSON) pairs.
async fn follow_events(base: &str, job: &str) -> Vec<(String, serde_json::Value)> {
    let mut resp = http().get(format!("{base}/api/jobs/{job}/events")).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "text/event-stream");
    let mut text = String::new();
    let read = async {
        while let Some(chunk) = resp.chunk().await.unwrap() {
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    };
    tokio::time::timeout(Duration::from_secs(60), read).await.expect("the event stream ends");
    parse_events(&text)
}

fn parse_events(text: &str) -> Vec<(String, serde_json::Value)> {
    text.split("\n\n")
        .filter_map(|block| {
            let mut name = None;
            let mut data = None;
            for line in block.lines() {
                if let Some(v) = line.strip_prefix("event:") {
                    name = Some(v.trim().to_string());
                }
                if let Some(v) = line.strip_prefix("data:") {
                    data = Some(serde_json::from_str(v.trim()).unwrap());
                }
            }
            Some((name?, data?))
        })
        .collect()
}

async fn wait_job(base: &str, job: &str) -> serde_json::Value {
    for _ in 0..600 {
        let j: serde_json::Value =
            http().get(format!("{base}/api/jobs/{job}")).send().await.unwrap().json().await.unwrap();
        if ["done", "failed", "cancelled"].contains(&j["state"].as_str().unwrap()) {
            return j;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("job {job} did not end");
}

/// A stored scene: its manifest and every block entry of its pages, sorted by key.
struct OnDisk {
    manifest: Manifest,
    index: voxstream_format::SceneIndex,
    blocks: Vec<voxstream_format::BlockEntry>,
    page_bytes: u64,
}

impl std::ops::Deref for OnDisk {
    type Target = Manifest;
    fn deref(&self) -> &Manifest {
        &self.manifest
    }
}

/// A block's bytes as the store keeps them, read without the server's code:
/// its range of the pack its page names.
fn block_on_disk(store: &Path, id: &str, index: &voxstream_format::SceneIndex, key: &BlockKey) -> Vec<u8> {
    let r = index.pack_range(key).unwrap_or_else(|| panic!("block {key} is not packed"));
    let pack =
        std::fs::read(store.join(id).join(voxstream_format::hierarchy::pack_path(&r.pack.hash))).unwrap();
    assert_eq!(pack.len() as u64, r.pack.bytes, "pack {} of block {key}", r.pack.hash);
    pack[r.offset as usize..r.end() as usize].to_vec()
}

/// Every page of a stored scene decodes, and every block it lists decodes and matches its hash.
fn assert_scene_complete(store: &Path, id: &str) -> OnDisk {
    let scene = voxstream::store::open_scene(store, id).unwrap();
    let blocks: Vec<_> = scene.blocks();
    assert_eq!(blocks.len() as u64, scene.manifest.block_count());
    for e in &blocks {
        let bytes = block_on_disk(store, id, &scene.index.read(), &e.key);
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), e.hash);
        assert_eq!(decode_block(&bytes).unwrap().key, e.key);
    }
    OnDisk {
        page_bytes: scene.index.read().page_bytes_loaded(),
        manifest: scene.manifest,
        index: scene.index.read().clone(),
        blocks,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_what_the_store_holds() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("Box Scan.obj");
    write_test_mesh(&mesh);
    let store = dir.path().join("store");
    let report = build_scene(
        &mesh,
        &store,
        &BuildOptions { resolution: Resolution::Explicit(256), ..Default::default() },
    )
    .unwrap();
    assert_eq!(report.id, "box-scan");
    assert_eq!(report.levels, 3);
    let base = start_read_only(&store).await;
    let http = http();

    let scenes: Vec<SceneSummary> =
        http.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert_eq!(scenes.len(), 1);
    assert_eq!(scenes[0].id, "box-scan");
    assert_eq!(scenes[0].triangles, 12);
    assert_eq!(scenes[0].blocks, report.blocks);
    assert_eq!(scenes[0].bytes, report.bytes);

    let on_disk = Manifest::from_json(&std::fs::read(store.join("box-scan/manifest.json")).unwrap()).unwrap();
    let served = http.get(format!("{base}/api/scenes/box-scan/manifest")).send().await.unwrap();
    assert_eq!(served.status(), 200);
    assert_eq!(served.headers()["cache-control"], "no-cache");
    let served = Manifest::from_json(&served.bytes().await.unwrap()).unwrap();
    assert_eq!(served, on_disk);
    // The hierarchy as the viewer reads it: pages over HTTP, immutable, checked against their hashes.
    let mut index = voxstream_format::SceneIndex::new(&served);
    loop {
        let next = index.missing_pages().next().cloned();
        let Some(r) = next else { break };
        let url = format!("{base}/api/scenes/box-scan/pages/{}.{}", r.root, r.hash);
        let resp = http.get(&url).send().await.unwrap();
        assert_eq!(resp.status(), 200, "{url}");
        assert_eq!(resp.headers()["cache-control"], BLOCK_CACHE_CONTROL);
        let etag = resp.headers()["etag"].to_str().unwrap().to_string();
        let bytes = resp.bytes().await.unwrap();
        let again = http.get(&url).header("if-none-match", &etag).send().await.unwrap();
        assert_eq!(again.status(), 304);
        index.insert_page(voxstream_format::HierarchyPage::decode(&bytes, &r).unwrap()).unwrap();
    }
    let wrong_page = format!("{base}/api/scenes/box-scan/pages/{}.{}", served.root.key, "0".repeat(64));
    json_error(http.get(&wrong_page).send().await.unwrap(), 404).await;
    json_error(http.get(format!("{base}/api/scenes/box-scan/pages/nonsense")).send().await.unwrap(), 400)
        .await;
    let mut served_blocks: Vec<_> = index.blocks().cloned().collect();
    served_blocks.sort_by_key(|b| b.key);
    assert_eq!(served_blocks, assert_scene_complete(&store, "box-scan").blocks);
    assert!(served_blocks.len() > 8, "expected several blocks, got {}", served_blocks.len());

    for entry in &served_blocks {
        let url = format!("{base}/api/scenes/box-scan/blocks/{}.{}", entry.key, entry.hash);
        let resp = http.get(&url).send().await.unwrap();
        assert_eq!(resp.status(), 200, "{url}");
        let etag = resp.headers()["etag"].to_str().unwrap().to_string();
        assert_eq!(etag, format!("\"{}\"", entry.hash));
        assert_eq!(resp.headers()["cache-control"], BLOCK_CACHE_CONTROL);
        assert_eq!(resp.headers()["content-type"], "application/octet-stream");
        assert!(resp.headers().get("content-encoding").is_none());
        let bytes = resp.bytes().await.unwrap();
        let file = block_on_disk(&store, "box-scan", &index, &entry.key);
        assert_eq!(&bytes[..], &file[..]);
        let block = decode_block(&bytes).unwrap();
        assert_eq!(block.key, entry.key);
        assert_eq!(block.voxels.len() as u32, entry.voxels);
        assert_eq!(block.face_count(), entry.faces);
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), entry.hash);

        let again = http.get(&url).header("if-none-match", &etag).send().await.unwrap();
        assert_eq!(again.status(), 304);
        assert_eq!(again.headers()["etag"].to_str().unwrap(), etag);
        assert!(again.bytes().await.unwrap().is_empty());

        // The key-only form serves the same bytes but must be revalidated.
        let plain =
            http.get(format!("{base}/api/scenes/box-scan/blocks/{}", entry.key)).send().await.unwrap();
        assert_eq!(plain.status(), 200);
        assert_eq!(plain.headers()["cache-control"], "no-cache");
        assert_eq!(plain.headers()["etag"].to_str().unwrap(), etag);
        assert_eq!(&plain.bytes().await.unwrap()[..], &file[..]);
    }
    let first = &served_blocks[0];
    let wrong = "0".repeat(64);
    let e = json_error(
        http.get(format!("{base}/api/scenes/box-scan/blocks/{}.{wrong}", first.key)).send().await.unwrap(),
        404,
    )
    .await;
    assert!(e.contains("hash"), "{e}");

    let e = json_error(http.get(format!("{base}/api/scenes/nope/manifest")).send().await.unwrap(), 404).await;
    assert!(e.contains("nope"), "{e}");
    let e = json_error(http.get(format!("{base}/api/scenes/nope/blocks/0-0-0-0")).send().await.unwrap(), 404)
        .await;
    assert!(e.contains("nope"));
    let e = json_error(
        http.get(format!("{base}/api/scenes/box-scan/blocks/0-99-0-0")).send().await.unwrap(),
        404,
    )
    .await;
    assert!(e.contains("0-99-0-0"), "{e}");
    let e = json_error(
        http.get(format!("{base}/api/scenes/box-scan/blocks/..%2fmanifest.json")).send().await.unwrap(),
        400,
    )
    .await;
    assert!(e.contains("level-x-y-z"), "{e}");
    let e =
        json_error(http.get(format!("{base}/api/scenes/..%2f..%2fetc/manifest")).send().await.unwrap(), 400)
            .await;
    assert!(e.contains("invalid"), "{e}");
    json_error(http.get(format!("{base}/api/scenes/Box/manifest")).send().await.unwrap(), 400).await;
    json_error(http.get(format!("{base}/api/nothing-here")).send().await.unwrap(), 404).await;
    // No --web: the embedded viewer answers outside /api; a file it lacks is a 404.
    assert_eq!(http.get(format!("{base}/no-such-file.js")).send().await.unwrap().status(), 404);
    // The compatible server is read-only.
    let e = json_error(upload(&base, "filename=b.obj", box_obj()).await, 403).await;
    assert!(e.contains("read-only"), "{e}");
}

#[tokio::test]
async fn rebuild_replaces_a_scene_atomically_and_bad_input_leaves_no_trace() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    let store = dir.path().join("store");
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() })
        .unwrap();
    let first = std::fs::read(store.join("box/manifest.json")).unwrap();
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(128), ..Default::default() })
        .unwrap();
    let second = Manifest::from_json(&std::fs::read(store.join("box/manifest.json")).unwrap()).unwrap();
    assert_ne!(first, second.to_json());
    assert_eq!(second.grid.resolution, 128);

    let bad = dir.path().join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nv 1 0 0\nf 1 2 3\n").unwrap();
    let err = build_scene(&bad, &store, &BuildOptions::default()).unwrap_err();
    assert!(err.to_string().contains("vertex"), "{err}");
    let names: Vec<String> =
        std::fs::read_dir(&store).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    assert_eq!(names, vec!["box".to_string()], "no temp or partial scene left behind");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_builds_a_scene_and_streams_progress() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = start_with(config(&store)).await;
    let resp =
        upload(&s.base, "filename=Koala%20Scan.obj&resolution=512", std::fs::read(koala()).unwrap()).await;
    assert_eq!(resp.status(), 202);
    let location = resp.headers()["location"].to_str().unwrap().to_string();
    let job: serde_json::Value = resp.json().await.unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/api/jobs/{id}"));
    assert_eq!(job["scene_id"], "koala-scan");
    assert_eq!(job["input_file"], "koala-scan.obj");
    assert_eq!(job["input_bytes"], std::fs::metadata(koala()).unwrap().len());

    let events = follow_events(&s.base, &id).await;
    let (last, final_job) = events.last().unwrap();
    assert_eq!(last, "done", "{events:?}");
    assert_eq!(final_job["state"], "done");
    assert_eq!(final_job["fraction"], 1.0);
    assert_eq!(final_job["attempts"], 1);
    let fractions: Vec<f64> = events.iter().map(|(_, j)| j["fraction"].as_f64().unwrap()).collect();
    assert!(fractions.windows(2).all(|w| w[0] <= w[1]), "{fractions:?}");
    assert!(events.iter().any(|(n, j)| n == "progress" && j["stage"].is_string()), "{events:?}");
    // A finished job's stream is one final event.
    let again = follow_events(&s.base, &id).await;
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].0, "done");

    let scenes: Vec<serde_json::Value> =
        http().get(format!("{}/api/scenes", s.base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(scenes.len(), 1);
    let meta = &scenes[0];
    assert_eq!(meta["id"], "koala-scan");
    assert_eq!(meta["source_format"], "obj");
    assert_eq!(meta["source_file"], "koala-scan.obj");
    assert_eq!(meta["triangles"], 99994);
    assert_eq!(meta["resolution"], 512);
    assert!(meta["built_at"].as_u64().unwrap() > 1_600_000_000);
    assert!(meta["build_seconds"].as_f64().unwrap() > 0.0);
    let m = assert_scene_complete(&store, "koala-scan");
    let on_disk: u64 = m.blocks.iter().map(|b| b.bytes as u64).sum::<u64>()
        + std::fs::metadata(store.join("koala-scan/manifest.json")).unwrap().len()
        + m.page_bytes;
    assert_eq!(meta["bytes_on_disk"], on_disk);
    for a in 0..3 {
        let (lo, hi) = (meta["bounds_min"][a].as_f64().unwrap(), meta["bounds_max"][a].as_f64().unwrap());
        assert!(lo < hi && lo >= m.grid.origin[a] - 1e-9, "axis {a}: {lo}..{hi}");
    }
    let one: serde_json::Value =
        http().get(format!("{}/api/scenes/koala-scan", s.base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(&one, meta);
    // The same mesh built by the CLI gives the same blocks.
    let cli_store = dir.path().join("cli");
    let copy = dir.path().join("koala-scan.obj");
    std::fs::copy(koala(), &copy).unwrap();
    build_scene(
        &copy,
        &cli_store,
        &BuildOptions { resolution: Resolution::Explicit(512), ..Default::default() },
    )
    .unwrap();
    let cli = assert_scene_complete(&cli_store, "koala-scan");
    assert_eq!(cli.blocks, m.blocks);
    let metrics = http().get(format!("{}/metrics", s.base)).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains(r#"voxstream_job_seconds_count{outcome="done"} 1"#), "{metrics}");
    assert!(
        metrics
            .contains(&format!("voxstream_upload_bytes_total {}", std::fs::metadata(koala()).unwrap().len()))
    );
    // The upload is gone, the job record stays.
    assert!(!store.join(".uploads").join(&id).exists());
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(store.join(".jobs").join(format!("{id}.json"))).unwrap())
            .unwrap();
    assert_eq!(record["state"], "done");
    let listed: Vec<serde_json::Value> =
        http().get(format!("{}/api/jobs", s.base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(listed.len(), 1);

    // Same id again: 409 unless replace=true.
    let e = json_error(upload(&s.base, "filename=koala-scan.obj", box_obj()).await, 409).await;
    assert!(e.contains("replace"), "{e}");
    let resp = upload(&s.base, "filename=x.obj&id=koala-scan&replace=true&resolution=64", box_obj()).await;
    assert_eq!(resp.status(), 202);
    let job: serde_json::Value = resp.json().await.unwrap();
    assert_eq!(wait_job(&s.base, job["id"].as_str().unwrap()).await["state"], "done");
    let m = assert_scene_complete(&store, "koala-scan");
    assert_eq!(m.source.triangles, 12);
    let meta: serde_json::Value =
        http().get(format!("{}/api/scenes/koala-scan", s.base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(meta["triangles"], 12, "the catalog shows the rebuilt scene");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_uploads_get_4xx_or_a_failed_job_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut c = config(&store);
    c.max_upload_bytes = 4000;
    c.max_header_bytes = 2000;
    let s = start_with(c).await;
    let base = &s.base;

    let e = json_error(upload(base, "filename=photo.png", &b"\x89PNG\r\n\x1a\n...."[..]).await, 415).await;
    assert!(e.contains("mesh format"), "{e}");
    let e = json_error(upload(base, "filename=a.obj", Vec::<u8>::new()).await, 400).await;
    assert!(e.contains("empty"), "{e}");
    let e = json_error(upload(base, "filename=big.obj", vec![b'#'; 5000]).await, 413).await;
    assert!(e.contains("4000"), "{e}");
    let e = json_error(upload(base, "filename=a.obj&resolution=100", box_obj()).await, 400).await;
    assert!(e.contains("power of two"), "{e}");
    let e = json_error(upload(base, "filename=a.obj&resolution=4096", box_obj()).await, 400).await;
    assert!(e.contains("2048"), "{e}");
    let e = json_error(upload(base, "filename=a.obj&topology=blobby", box_obj()).await, 400).await;
    assert!(e.contains("blobby"), "{e}");
    let e = json_error(upload(base, "filename=a.obj&id=Bad%20Id", box_obj()).await, 400).await;
    assert!(e.contains("invalid"), "{e}");
    let e = json_error(upload(base, "resolution=x", box_obj()).await, 400).await;
    assert!(!e.is_empty());

    // Oversized without Content-Length: counted while streaming (raw chunked request).
    let chunked = raw_request(
        s.addr,
        &format!(
            "POST /api/scenes?filename=c.obj HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n\
             Transfer-Encoding: chunked\r\nConnection: close\r\n\r\n"
        ),
        &[b"fa0\r\n".as_slice(), &[b'#'; 4000], b"\r\nfa0\r\n", &[b'#'; 4000], b"\r\n0\r\n\r\n"].concat(),
    )
    .await;
    assert!(chunked.starts_with("HTTP/1.1 413"), "{chunked}");

    // Headers beyond the limit.
    let resp =
        http().get(format!("{base}/api/scenes")).header("x-big", "y".repeat(3000)).send().await.unwrap();
    let e = json_error(resp, 431).await;
    assert!(e.contains("2000"), "{e}");

    // A well-formed request with a broken mesh: accepted, the job fails with the parser's reason.
    let resp = upload(base, "filename=broken.obj", &b"v 0 0 0\nv 1 0 0\nf 1 2 3\n"[..]).await;
    assert_eq!(resp.status(), 202);
    let job: serde_json::Value = resp.json().await.unwrap();
    let job = wait_job(base, job["id"].as_str().unwrap()).await;
    assert_eq!(job["state"], "failed");
    assert!(job["error"].as_str().unwrap().contains("vertex"), "{job}");
    let events = follow_events(base, job["id"].as_str().unwrap()).await;
    assert_eq!(events.last().unwrap().0, "failed");

    // Nothing was published and no upload is left.
    let scenes: Vec<serde_json::Value> =
        http().get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert!(scenes.is_empty());
    assert_eq!(std::fs::read_dir(store.join(".uploads")).unwrap().count(), 0);
    let names: Vec<String> =
        std::fs::read_dir(&store).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    assert!(names.iter().all(|n| n == ".jobs" || n == ".uploads"), "{names:?}");

    // Bad and unknown job ids.
    json_error(http().get(format!("{base}/api/jobs/XYZ")).send().await.unwrap(), 400).await;
    json_error(http().get(format!("{base}/api/jobs/0123456789abcdef")).send().await.unwrap(), 404).await;
    json_error(http().get(format!("{base}/api/jobs/0123456789abcdef/events")).send().await.unwrap(), 404)
        .await;
    json_error(auth(http().delete(format!("{base}/api/jobs/0123456789abcdef"))).send().await.unwrap(), 404)
        .await;
    let e = json_error(
        auth(http().delete(format!("{base}/api/jobs/{}", job["id"].as_str().unwrap()))).send().await.unwrap(),
        409,
    )
    .await;
    assert!(e.contains("failed"), "{e}");
}

/// Sends raw bytes, returns what the server answered before closing.
async fn raw_request(addr: SocketAddr, head: &str, body: &[u8]) -> String {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    tcp.write_all(head.as_bytes()).await.unwrap();
    let _ = tcp.write_all(body).await; // the server may answer and close early
    let mut out = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(10), tcp.read_to_end(&mut out)).await;
    String::from_utf8_lossy(&out).into_owned()
}

fn tus(r: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
    auth(r).header("tus-resumable", "1.0.0")
}

fn b64(s: &str) -> String {
    base64::engine::general_purpose::STANDARD.encode(s)
}

async fn head_offset(base: &str, location: &str) -> u64 {
    let resp = tus(http().head(format!("{base}{location}"))).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["cache-control"], "no-store");
    resp.headers()["upload-offset"].to_str().unwrap().parse().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tus_upload_resumes_after_a_cut_connection() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = start_with(config(&store)).await;
    let base = &s.base;
    let mesh = std::fs::read(koala()).unwrap();
    let len = mesh.len();

    let opts = http().request(reqwest::Method::OPTIONS, format!("{base}/api/uploads")).send().await.unwrap();
    assert_eq!(opts.status(), 204);
    assert_eq!(opts.headers()["tus-version"], "1.0.0");
    assert!(opts.headers()["tus-extension"].to_str().unwrap().contains("creation"));

    let e = json_error(
        auth(http().post(format!("{base}/api/uploads"))).header("upload-length", "10").send().await.unwrap(),
        412,
    )
    .await;
    assert!(e.contains("Tus-Resumable"), "{e}");
    let e = json_error(tus(http().post(format!("{base}/api/uploads"))).send().await.unwrap(), 400).await;
    assert!(e.contains("Upload-Length"), "{e}");
    let e = json_error(
        tus(http().post(format!("{base}/api/uploads")))
            .header("upload-length", "10")
            .header("upload-metadata", "filename !!!")
            .send()
            .await
            .unwrap(),
        400,
    )
    .await;
    assert!(e.contains("base64"), "{e}");

    let created = tus(http().post(format!("{base}/api/uploads")))
        .header("upload-length", len.to_string())
        .header("upload-metadata", format!("filename {},resolution {}", b64("scan.obj"), b64("128")))
        .send()
        .await
        .unwrap();
    assert_eq!(created.status(), 201);
    let location = created.headers()["location"].to_str().unwrap().to_string();
    assert!(location.starts_with("/api/uploads/"), "{location}");
    assert_eq!(head_offset(base, &location).await, 0);

    let patch = |offset: usize, body: Vec<u8>| {
        tus(http().patch(format!("{base}{location}")))
            .header("content-type", "application/offset+octet-stream")
            .header("upload-offset", offset.to_string())
            .body(body)
    };
    // First part, whole.
    let first = 1_000_000;
    let resp = patch(0, mesh[..first].to_vec()).send().await.unwrap();
    assert_eq!(resp.status(), 204);
    assert_eq!(resp.headers()["upload-offset"], first.to_string().as_str());
    assert_eq!(head_offset(base, &location).await, first as u64);

    // Second part: the connection drops after 700 kB of a 2 MB body.
    let cut_at = 700_000;
    let mut tcp = tokio::net::TcpStream::connect(s.addr).await.unwrap();
    let head = format!(
        "PATCH {location} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\nTus-Resumable: 1.0.0\r\n\
         Content-Type: application/offset+octet-stream\r\nUpload-Offset: {first}\r\nContent-Length: 2000000\r\n\r\n"
    );
    tcp.write_all(head.as_bytes()).await.unwrap();
    tcp.write_all(&mesh[first..first + cut_at]).await.unwrap();
    tcp.flush().await.unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    drop(tcp);
    // HEAD waits for the interrupted PATCH to finish, then tells what arrived.
    let offset = head_offset(base, &location).await as usize;
    assert_eq!(offset, first + cut_at, "everything sent before the cut is kept");

    // Wrong offset: 409 telling the right one. A small body: the server answers from the headers
    // and closes, and a client still writing megabytes would see a broken pipe instead.
    let resp = patch(first, mesh[first..first + 1024].to_vec()).send().await.unwrap();
    assert_eq!(
        resp.headers().get("upload-offset").map(|v| v.to_str().unwrap()),
        Some(offset.to_string().as_str())
    );
    let e = json_error(resp, 409).await;
    assert!(e.contains(&offset.to_string()), "{e}");
    // Wrong content type and past the end.
    let e = json_error(
        tus(http().patch(format!("{base}{location}")))
            .header("upload-offset", offset.to_string())
            .body(vec![1u8])
            .send()
            .await
            .unwrap(),
        415,
    )
    .await;
    assert!(e.contains("offset+octet-stream"), "{e}");
    let mut too_long = mesh[offset..].to_vec();
    too_long.extend_from_slice(b"extra");
    let e = json_error(patch(offset, too_long).send().await.unwrap(), 400).await;
    assert!(e.contains("Upload-Length"), "{e}");
    assert_eq!(head_offset(base, &location).await as usize, offset, "a rejected PATCH keeps nothing");

    // Resume from HEAD's offset to the end: the build is queued.
    let resp = patch(offset, mesh[offset..].to_vec()).send().await.unwrap();
    assert_eq!(resp.status(), 204);
    assert_eq!(resp.headers()["upload-offset"], len.to_string().as_str());
    let job_id = resp.headers()["voxstream-job"].to_str().unwrap().to_string();
    assert_eq!(format!("/api/uploads/{job_id}"), location);
    let job = wait_job(base, &job_id).await;
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["scene_id"], "scan");
    // The reassembled file built exactly what the original builds.
    let m = assert_scene_complete(&store, "scan");
    let copy = dir.path().join("scan.obj");
    std::fs::write(&copy, &mesh).unwrap();
    build_scene(
        &copy,
        &dir.path().join("cli"),
        &BuildOptions { resolution: Resolution::Explicit(128), ..Default::default() },
    )
    .unwrap();
    assert_eq!(assert_scene_complete(&dir.path().join("cli"), "scan").blocks, m.blocks);
    // After completion: PATCH is a conflict, HEAD names the job.
    let e = json_error(patch(len, vec![1]).send().await.unwrap(), 409).await;
    assert!(e.contains("already complete"), "{e}");
    let done = tus(http().head(format!("{base}{location}"))).send().await.unwrap();
    assert_eq!(done.headers()["upload-offset"], len.to_string().as_str());
    assert_eq!(done.headers()["voxstream-job"], job_id.as_str());

    // Termination.
    let created = tus(http().post(format!("{base}/api/uploads")))
        .header("upload-length", "100")
        .header("upload-metadata", format!("filename {}", b64("t.obj")))
        .send()
        .await
        .unwrap();
    let loc = created.headers()["location"].to_str().unwrap().to_string();
    assert_eq!(tus(http().delete(format!("{base}{loc}"))).send().await.unwrap().status(), 204);
    let gone = tus(http().head(format!("{base}{loc}"))).send().await.unwrap();
    assert_eq!(gone.status(), 404);
    json_error(tus(http().delete(format!("{base}{loc}"))).send().await.unwrap(), 404).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn access_rules_token_read_only_and_protected_reads() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() })
        .unwrap();
    let s = start_with(config(&store)).await;
    let base = &s.base;
    let c = http();
    let writes = [
        c.post(format!("{base}/api/scenes?filename=a.obj")).body(box_obj()),
        c.patch(format!("{base}/api/scenes/box")).body(r#"{"name":"x"}"#),
        c.delete(format!("{base}/api/scenes/box")),
        c.post(format!("{base}/api/uploads")).header("tus-resumable", "1.0.0").header("upload-length", "5"),
        c.delete(format!("{base}/api/jobs/0123456789abcdef")),
        c.post(format!("{base}/api/jobs/0123456789abcdef/cancel")),
    ];
    for w in writes {
        let w2 = w.try_clone().unwrap();
        let resp = w.send().await.unwrap();
        assert_eq!(resp.headers()["www-authenticate"], "Bearer realm=\"voxstream\"");
        let e = json_error(resp, 401).await;
        assert!(e.contains("Bearer"), "{e}");
        let resp = w2.bearer_auth("wrong-token").send().await.unwrap();
        json_error(resp, 401).await;
    }
    assert!(store.join("box/manifest.json").exists(), "nothing changed");
    // Reads are public by default.
    assert_eq!(c.get(format!("{base}/api/scenes/box/manifest")).send().await.unwrap().status(), 200);
    assert_eq!(c.get(format!("{base}/api/jobs")).send().await.unwrap().status(), 200);
    s.shutdown.cancel();

    let mut protected = config(&store);
    protected.protect_read = true;
    let p = start_with(protected).await;
    for path in ["/api/scenes", "/api/scenes/box", "/api/scenes/box/manifest", "/api/jobs", "/metrics"] {
        let e = json_error(c.get(format!("{}{path}", p.base)).send().await.unwrap(), 401).await;
        assert!(e.contains("reading"), "{path}: {e}");
        assert_eq!(auth(c.get(format!("{}{path}", p.base))).send().await.unwrap().status(), 200, "{path}");
    }
    let health = c.get(format!("{}/healthz", p.base)).send().await.unwrap();
    assert_eq!(health.status(), 200, "health stays public for probes");
    p.shutdown.cancel();

    let mut ro = config(&store);
    ro.read_only = true;
    let r = start_with(ro).await;
    let e = json_error(auth(c.delete(format!("{}/api/scenes/box", r.base))).send().await.unwrap(), 403).await;
    assert!(e.contains("read-only"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rename_and_delete_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(128), ..Default::default() })
        .unwrap();
    std::fs::copy(&mesh, dir.path().join("other.obj")).unwrap();
    build_scene(
        &dir.path().join("other.obj"),
        &store,
        &BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() },
    )
    .unwrap();
    let s = start_with(config(&store)).await;
    let base = &s.base;
    let c = http();
    let before = assert_scene_complete(&store, "box");

    let resp = auth(c.patch(format!("{base}/api/scenes/box")))
        .body(r#"{"id": "renamed", "name": "My Box"}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 200);
    let meta: serde_json::Value = resp.json().await.unwrap();
    assert_eq!(meta["id"], "renamed");
    assert_eq!(meta["name"], "My Box");
    json_error(c.get(format!("{base}/api/scenes/box/manifest")).send().await.unwrap(), 404).await;
    let m: Manifest = serde_json::from_slice(
        &c.get(format!("{base}/api/scenes/renamed/manifest")).send().await.unwrap().bytes().await.unwrap(),
    )
    .unwrap();
    assert_eq!(m, before.manifest);
    let e = &before.blocks[0];
    let block = c.get(format!("{base}/api/scenes/renamed/blocks/{}.{}", e.key, e.hash)).send().await.unwrap();
    assert_eq!(block.status(), 200);
    assert!(!store.join("box").exists() && store.join("renamed/manifest.json").exists());

    for (body, status, needle) in [
        (r#"{"id": "other"}"#, 409, "exists"),
        (r#"{"id": "Not Valid"}"#, 400, "invalid"),
        (r#"{}"#, 400, "\"id\""),
        (r#"{"colour": "red"}"#, 400, "colour"),
        (r#"not json"#, 400, "JSON"),
        (r#"{"name": ""}"#, 400, "name"),
    ] {
        let resp = auth(c.patch(format!("{base}/api/scenes/renamed"))).body(body).send().await.unwrap();
        let e = json_error(resp, status).await;
        assert!(e.contains(needle), "{body}: {e}");
    }
    json_error(
        auth(c.patch(format!("{base}/api/scenes/nope"))).body(r#"{"name":"x"}"#).send().await.unwrap(),
        404,
    )
    .await;

    assert_eq!(auth(c.delete(format!("{base}/api/scenes/renamed"))).send().await.unwrap().status(), 204);
    json_error(c.get(format!("{base}/api/scenes/renamed")).send().await.unwrap(), 404).await;
    json_error(auth(c.delete(format!("{base}/api/scenes/renamed"))).send().await.unwrap(), 404).await;
    json_error(auth(c.delete(format!("{base}/api/scenes/..."))).send().await.unwrap(), 400).await;
    let names: Vec<String> =
        std::fs::read_dir(&store).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    assert_eq!(names, vec!["other".to_string()], "deleted without leftovers");
    let scenes: Vec<serde_json::Value> =
        c.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert_eq!(scenes.len(), 1);
    assert_eq!(scenes[0]["id"], "other");
}

/// Fails if a block served from a pack is not byte for byte the block the
/// in-memory reference path encodes (a wrong offset, a block of another page's
/// pack, bytes shifted by one), or if a missing or truncated pack panics or
/// answers anything but a JSON 5xx naming the pack.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn served_blocks_are_the_reference_encoding_and_a_damaged_pack_is_a_clear_error() {
    use voxstream::pipeline::progress::ProgressSink;
    use voxstream::pipeline::pyramid::build_levels;
    use voxstream::pipeline::read::read_mesh;
    use voxstream::pipeline::voxelize::{choose_frame, voxelize_reporting};
    use voxstream::pipeline::write::encode_entry;

    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    // No AO field: the in-memory reference below has none (outofcore.rs checks the field's determinism).
    let opts = BuildOptions { resolution: Resolution::Explicit(256), ao_field: None, ..Default::default() };
    build_scene(&mesh, &store, &opts).unwrap();
    // The reference: the mesh voxelized in memory, every level built at once, each block encoded alone.
    let (triangles, _) = read_mesh(&mesh).unwrap();
    let frame = choose_frame(&triangles, 256).unwrap();
    let (level0, _) =
        voxelize_reporting(&triangles, &frame, opts.topology, &ProgressSink::new(&|_| {})).unwrap();
    let reference: std::collections::BTreeMap<BlockKey, Vec<u8>> =
        build_levels(level0, 256).iter().flatten().map(|b| (b.key, encode_entry(b).1)).collect();

    let m = assert_scene_complete(&store, "box");
    let base = start_read_only(&store).await;
    let c = http();
    assert_eq!(m.blocks.len(), reference.len());
    let get = |key: BlockKey, hash: String| {
        let c = c.clone();
        let url = format!("{base}/api/scenes/box/blocks/{key}.{hash}");
        async move { c.get(url).send().await.unwrap() }
    };
    for e in &m.blocks {
        let resp = get(e.key, e.hash.clone()).await;
        assert_eq!(resp.status(), 200);
        let bytes = resp.bytes().await.unwrap();
        assert!(bytes[..] == reference[&e.key][..], "block {} differs from the reference encoding", e.key);
    }
    // The negative control: blocks are distinct, so a block at another range would have failed.
    let distinct: std::collections::HashSet<&Vec<u8>> = reference.values().collect();
    assert_eq!(distinct.len(), reference.len());

    // The root block is the last range of the last pack; the first range stays readable.
    let root = m.index.pack_range(&m.root.key).unwrap();
    assert_eq!(root.end(), root.pack.bytes, "the root comes last in its pack");
    let first = m
        .blocks
        .iter()
        .find(|e| m.index.pack_range(&e.key).is_some_and(|r| r.offset == 0 && r.pack == root.pack))
        .unwrap();
    let pack = store.join("box").join(voxstream_format::hierarchy::pack_path(&root.pack.hash));
    std::fs::OpenOptions::new().write(true).open(&pack).unwrap().set_len(root.offset + 1).unwrap();
    let e = json_error(get(m.root.key, m.root.hash.clone()).await, 500).await;
    assert!(
        e.contains("truncated") && e.contains(&root.pack.hash) && e.contains(&m.root.key.to_string()),
        "{e}"
    );
    assert_eq!(get(first.key, first.hash.clone()).await.status(), 200, "a range before the cut still reads");
    let batch = c
        .post(format!("{base}/api/scenes/box/blocks/batch"))
        .json(&serde_json::json!({ "blocks": [format!("{}.{}", m.root.key, m.root.hash)] }))
        .send()
        .await
        .unwrap();
    assert!(json_error(batch, 500).await.contains("truncated"));
    std::fs::remove_file(&pack).unwrap();
    let e = json_error(get(first.key, first.hash.clone()).await, 500).await;
    assert!(e.contains(&format!("packs/{}.vxp", root.pack.hash)), "{e}");
    assert_eq!(c.get(format!("{base}/healthz")).send().await.unwrap().status(), 200, "the server lives on");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batch_returns_framed_blocks_with_a_cap() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(256), ..Default::default() })
        .unwrap();
    let mut c = config(&store);
    c.batch_max = 8;
    let s = start_with(c).await;
    let m = assert_scene_complete(&store, "box");
    let names: Vec<String> = m.blocks.iter().take(8).map(|e| format!("{}.{}", e.key, e.hash)).collect();
    let url = format!("{}/api/scenes/box/blocks/batch", s.base);
    let resp = http().post(&url).json(&serde_json::json!({ "blocks": names })).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "application/octet-stream");
    let body = resp.bytes().await.unwrap();
    let mut at = 0;
    for e in m.blocks.iter().take(8) {
        let len = u32::from_le_bytes(body[at..at + 4].try_into().unwrap()) as usize;
        let bytes = &body[at + 4..at + 4 + len];
        assert_eq!(bytes, &block_on_disk(&store, "box", &m.index, &e.key)[..]);
        at += 4 + len;
    }
    assert_eq!(at, body.len());

    let nine: Vec<String> = m.blocks.iter().cycle().take(9).map(|e| e.key.to_string()).collect();
    let e =
        json_error(http().post(&url).json(&serde_json::json!({ "blocks": nine })).send().await.unwrap(), 400)
            .await;
    assert!(e.contains("1 to 8"), "{e}");
    let bad = vec![format!("{}.{}", m.blocks[0].key, "f".repeat(64))];
    json_error(http().post(&url).json(&serde_json::json!({ "blocks": bad })).send().await.unwrap(), 404)
        .await;
    json_error(http().post(&url).body("[1,2]").send().await.unwrap(), 400).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_queue_on_a_bounded_pool_and_cancel() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut c = config(&store);
    c.build_workers = 1;
    let s = start_with(c).await;
    let base = &s.base;
    let koala = std::fs::read(koala()).unwrap();
    // A slow build occupies the only worker; the next one waits in the queue.
    let slow: serde_json::Value =
        upload(base, "filename=slow.obj&resolution=1024", koala.clone()).await.json().await.unwrap();
    let queued: serde_json::Value =
        upload(base, "filename=queued.obj", box_obj()).await.json().await.unwrap();
    let queued_id = queued["id"].as_str().unwrap();
    let j: serde_json::Value =
        http().get(format!("{base}/api/jobs/{queued_id}")).send().await.unwrap().json().await.unwrap();
    assert_eq!(j["state"], "queued");
    // A scene being built cannot be uploaded again.
    json_error(upload(base, "filename=queued.obj&replace=true", box_obj()).await, 409).await;

    let resp = auth(http().post(format!("{base}/api/jobs/{queued_id}/cancel"))).send().await.unwrap();
    assert_eq!(resp.status(), 202);
    let slow_id = slow["id"].as_str().unwrap();
    // Wait until the slow one runs, then cancel it too.
    for _ in 0..100 {
        let j: serde_json::Value =
            http().get(format!("{base}/api/jobs/{slow_id}")).send().await.unwrap().json().await.unwrap();
        if j["state"] == "running" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(auth(http().delete(format!("{base}/api/jobs/{slow_id}"))).send().await.unwrap().status(), 202);
    let events = follow_events(base, slow_id).await;
    assert_eq!(events.last().unwrap().0, "cancelled", "{events:?}");
    assert_eq!(wait_job(base, queued_id).await["state"], "cancelled");
    let scenes: Vec<serde_json::Value> =
        http().get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert!(scenes.is_empty(), "cancelled builds publish nothing: {scenes:?}");
    let e = json_error(auth(http().delete(format!("{base}/api/jobs/{slow_id}"))).send().await.unwrap(), 409)
        .await;
    assert!(e.contains("cancelled"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_are_rate_limited_per_client() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(&dir.path().join("store"));
    c.uploads_per_minute = 2;
    let s = start_with(c).await;
    for name in ["a", "b"] {
        assert_eq!(upload(&s.base, &format!("filename={name}.obj"), box_obj()).await.status(), 202);
    }
    let resp = upload(&s.base, "filename=c.obj", box_obj()).await;
    let retry: u64 = resp.headers()["retry-after"].to_str().unwrap().parse().unwrap();
    assert!((1..=30).contains(&retry), "{retry}");
    let e = json_error(resp, 429).await;
    assert!(e.contains("127.0.0.1"), "{e}");
    // Reads are not limited.
    for _ in 0..5 {
        assert_eq!(http().get(format!("{}/api/scenes", s.base)).send().await.unwrap().status(), 200);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_metrics_openapi_and_cors() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    build_scene(&mesh, &store, &BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() })
        .unwrap();
    let mut c = config(&store);
    c.cors_origins = vec!["https://viewer.example".into()];
    let s = start_with(c).await;
    let base = &s.base;
    let health: serde_json::Value =
        http().get(format!("{base}/healthz")).send().await.unwrap().json().await.unwrap();
    assert_eq!(health["status"], "ok");
    assert_eq!(health["scenes"], 1);

    let m = assert_scene_complete(&store, "box");
    let e = &m.blocks[0];
    for _ in 0..3 {
        let r =
            http().get(format!("{base}/api/scenes/box/blocks/{}.{}", e.key, e.hash)).send().await.unwrap();
        assert_eq!(r.status(), 200);
    }
    let metrics = http().get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains(&format!("voxstream_block_bytes_served_total {}", 3 * e.bytes)), "{metrics}");
    assert!(
        metrics.contains(r#"voxstream_http_requests_total{method="GET",route="/api/scenes/{id}/blocks/{block}",status="200"} 3"#),
        "{metrics}"
    );
    assert!(metrics.contains("voxstream_http_request_seconds_bucket"), "{metrics}");

    let doc: serde_json::Value =
        http().get(format!("{base}/api/openapi.json")).send().await.unwrap().json().await.unwrap();
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    let paths = doc["paths"].as_object().unwrap();
    for p in [
        "/api/scenes",
        "/api/scenes/{id}",
        "/api/scenes/{id}/manifest",
        "/api/scenes/{id}/blocks/{block}",
        "/api/scenes/{id}/blocks/batch",
        "/api/scenes/{id}/thumbnail.png",
        "/api/uploads",
        "/api/uploads/{id}",
        "/api/jobs",
        "/api/jobs/{id}",
        "/api/jobs/{id}/events",
        "/healthz",
        "/metrics",
    ] {
        assert!(paths.contains_key(p), "OpenAPI lacks {p}");
    }
    assert!(
        paths["/api/uploads/{id}"].get("patch").is_some() && paths["/api/uploads/{id}"].get("head").is_some()
    );
    assert!(doc["components"]["securitySchemes"]["bearer"].is_object());

    let pre = http()
        .request(reqwest::Method::OPTIONS, format!("{base}/api/scenes"))
        .header("origin", "https://viewer.example")
        .header("access-control-request-method", "POST")
        .send()
        .await
        .unwrap();
    assert_eq!(pre.headers()["access-control-allow-origin"], "https://viewer.example");
    let other = http()
        .get(format!("{base}/api/scenes"))
        .header("origin", "https://evil.example")
        .send()
        .await
        .unwrap();
    assert!(other.headers().get("access-control-allow-origin").is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_resumes_or_fails_interrupted_jobs_and_cleans_leftovers() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    // A first server takes two uploads but stops before building (no worker ever frees up).
    let s = start_with(config(&store)).await;
    let a: serde_json::Value =
        upload(&s.base, "filename=a.obj&resolution=1024", std::fs::read(koala()).unwrap())
            .await
            .json()
            .await
            .unwrap();
    let b: serde_json::Value = upload(&s.base, "filename=b.obj", box_obj()).await.json().await.unwrap();
    let (a, b) = (a["id"].as_str().unwrap().to_string(), b["id"].as_str().unwrap().to_string());
    s.shutdown.cancel();
    s.state.jobs.shutdown(Duration::from_secs(30)).await;
    let _ = s.task.await;
    for id in [&a, &b] {
        let rec: serde_json::Value =
            serde_json::from_slice(&std::fs::read(store.join(format!(".jobs/{id}.json"))).unwrap()).unwrap();
        assert_eq!(rec["state"], "queued", "interrupted jobs stay queued on disk: {rec}");
    }
    // Simulate a crash: b's upload vanished; a half-written scene and an abandoned upload lie around.
    std::fs::remove_dir_all(store.join(".uploads").join(&b)).unwrap();
    std::fs::create_dir_all(store.join(".tmp-a-4194399999-1/blocks")).unwrap();
    std::fs::create_dir_all(store.join(".trash-x-1")).unwrap();
    std::fs::create_dir_all(store.join(".uploads/00000000deadbeef")).unwrap();
    std::fs::write(store.join(".jobs/garbage.json"), b"{").unwrap();
    // Two unfinished tus uploads: a fresh one stays resumable, one from last month expires.
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs();
    for (id, created_at) in [("00000000000f1e54", now), ("00000000000001d0", now - 30 * 24 * 3600)] {
        let up = store.join(".uploads").join(id);
        std::fs::create_dir_all(&up).unwrap();
        std::fs::write(up.join("data"), b"v 0 0 0\n").unwrap();
        let record = serde_json::json!({
            "id": id, "length": 1000, "file_name": "x.obj", "content_type": null, "scene_id": "x",
            "resolution": 64, "topology": "conservative", "replace": false, "resumable": true,
            "created_at": created_at,
        });
        std::fs::write(up.join("upload.json"), record.to_string()).unwrap();
    }

    let mut c = config(&store);
    c.resolution = Some(64);
    let s = start_with(c).await;
    let ja = wait_job(&s.base, &a).await;
    assert_eq!(ja["state"], "done", "{ja}");
    assert!(ja["attempts"].as_u64().unwrap() >= 1);
    let jb = wait_job(&s.base, &b).await;
    assert_eq!(jb["state"], "failed");
    assert!(jb["error"].as_str().unwrap().contains("upload is gone"), "{jb}");
    assert_scene_complete(&store, "a");
    let mut names: Vec<String> =
        std::fs::read_dir(&store).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    names.sort();
    assert_eq!(names, vec![".jobs", ".uploads", "a"]);
    let uploads: Vec<String> = std::fs::read_dir(store.join(".uploads"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(uploads, vec!["00000000000f1e54".to_string()], "only the fresh unfinished upload is kept");
    assert_eq!(head_offset(&s.base, "/api/uploads/00000000000f1e54").await, 8);
    assert!(!store.join(".jobs/garbage.json").exists());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_event_streams() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = start_with(config(&store)).await;
    let slow: serde_json::Value =
        upload(&s.base, "filename=slow.obj&resolution=1024", std::fs::read(koala()).unwrap())
            .await
            .json()
            .await
            .unwrap();
    let waiting: serde_json::Value = upload(&s.base, "filename=w.obj", box_obj()).await.json().await.unwrap();
    let mut resp = http()
        .get(format!("{}/api/jobs/{}/events", s.base, waiting["id"].as_str().unwrap()))
        .send()
        .await
        .unwrap();
    let first = resp.chunk().await.unwrap().unwrap();
    assert!(String::from_utf8_lossy(&first).contains("queued"));
    s.shutdown.cancel();
    let rest = tokio::time::timeout(Duration::from_secs(5), async {
        while resp.chunk().await.unwrap().is_some() {}
    })
    .await;
    assert!(rest.is_ok(), "the SSE stream ended with the shutdown");
    tokio::time::timeout(Duration::from_secs(5), s.task).await.expect("graceful shutdown finished").unwrap();
    s.state.jobs.shutdown(Duration::from_secs(30)).await;
    let rec: serde_json::Value = serde_json::from_slice(
        &std::fs::read(store.join(format!(".jobs/{}.json", slow["id"].as_str().unwrap()))).unwrap(),
    )
    .unwrap();
    assert_eq!(rec["state"], "queued", "a build stopped by shutdown resumes on the next start");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_uploads_of_one_scene_build_one_after_the_other() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut c = config(&store);
    c.build_workers = 2;
    let s = start_with(c).await;
    let base = &s.base;
    let koala = std::fs::read(koala()).unwrap();
    // Both are created before either has a job, so both are accepted.
    let mut locations = Vec::new();
    for res in ["1024", "256"] {
        let created = tus(http().post(format!("{base}/api/uploads")))
            .header("upload-length", koala.len().to_string())
            .header("upload-metadata", format!("filename {},resolution {}", b64("same.obj"), b64(res)))
            .send()
            .await
            .unwrap();
        assert_eq!(created.status(), 201);
        locations.push(created.headers()["location"].to_str().unwrap().to_string());
    }
    let mut jobs = Vec::new();
    for loc in &locations {
        let resp = tus(http().patch(format!("{base}{loc}")))
            .header("content-type", "application/offset+octet-stream")
            .header("upload-offset", "0")
            .body(koala.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(resp.status(), 204);
        jobs.push(resp.headers()["voxstream-job"].to_str().unwrap().to_string());
    }
    let second: serde_json::Value =
        http().get(format!("{base}/api/jobs/{}", jobs[1])).send().await.unwrap().json().await.unwrap();
    assert_eq!(second["state"], "queued", "the second build of scene same waits for the first: {second}");
    let (a, b) = (wait_job(base, &jobs[0]).await, wait_job(base, &jobs[1]).await);
    assert_eq!((a["state"].as_str(), b["state"].as_str()), (Some("done"), Some("done")));
    assert!(b["started_at"].as_u64() >= a["finished_at"].as_u64());
    assert_eq!(assert_scene_complete(&store, "same").grid.resolution, 256, "the last build wins");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_format_comes_from_magic_name_header_or_content_type() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = start_with(config(&store)).await;
    let verts: Vec<[f64; 3]> = box_obj()
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let p: Vec<f64> = l.split(' ').map(|x| x.parse().unwrap()).collect();
            [p[0], p[1], p[2]]
        })
        .collect();
    let faces: Vec<[usize; 3]> = box_obj()
        .lines()
        .filter_map(|l| l.strip_prefix("f "))
        .map(|l| {
            let f: Vec<usize> = l.split(' ').map(|x| x.parse::<usize>().unwrap() - 1).collect();
            [f[0], f[1], f[2]]
        })
        .collect();
    let mut stl = String::from("solid box\n");
    for f in &faces {
        stl += "facet normal 0 0 0\nouter loop\n";
        for &i in f {
            stl += &format!("vertex {} {} {}\n", verts[i][0], verts[i][1], verts[i][2]);
        }
        stl += "endloop\nendfacet\n";
    }
    stl += "endsolid box\n";
    let mut ply = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    for v in &verts {
        ply += &format!("{} {} {}\n", v[0], v[1], v[2]);
    }
    for f in &faces {
        ply += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
    }
    let cases = [
        ("", vec![("x-filename", "Boxy.OBJ")], box_obj(), "boxy", "obj", "boxy.obj"),
        ("id=stl-box", vec![("content-type", "model/stl")], stl, "stl-box", "stl", "stl-box.stl"),
        ("id=ply-box", vec![], ply, "ply-box", "ply", "ply-box.ply"),
    ];
    for (query, headers, body, id, format, file) in cases {
        let mut req = auth(http().post(format!("{}/api/scenes?{query}", s.base))).body(body);
        for (k, v) in headers {
            req = req.header(k, v);
        }
        let resp = req.send().await.unwrap();
        assert_eq!(resp.status(), 202, "{id}");
        let job: serde_json::Value = resp.json().await.unwrap();
        assert_eq!(job["input_file"], file);
        let job = wait_job(&s.base, job["id"].as_str().unwrap()).await;
        assert_eq!(job["state"], "done", "{job}");
        let meta: serde_json::Value =
            http().get(format!("{}/api/scenes/{id}", s.base)).send().await.unwrap().json().await.unwrap();
        assert_eq!(meta["source_format"], format);
        assert_eq!(meta["triangles"], 12);
    }
}

/// `voxstream serve` without `--web` serves the viewer compiled into the binary: the same bytes
/// as viewer-wasm/dist, with the right content types and revalidation. Negative control: a binary
/// built before the viewer (server/build.rs embeds an empty folder) answers 404 here and fails.
#[tokio::test]
async fn embedded_viewer_is_served_without_web() {
    let dist = Path::new(env!("CARGO_MANIFEST_DIR")).join("../viewer-wasm/dist");
    assert!(
        dist.join("index.html").is_file() && voxstream::http::web::has_embedded_viewer(),
        "this test binary embeds no viewer: run bash scripts/build-web.sh, then cargo test again \
         (server/build.rs embeds viewer-wasm/dist when it has an index.html)"
    );
    let store = tempfile::tempdir().unwrap();
    let base = start_read_only(store.path()).await;
    let http = http();
    for (path, file, mime) in [
        ("/", "index.html", "text/html"),
        ("/index.html", "index.html", "text/html"),
        ("/pkg/voxstream_viewer_bg.wasm", "pkg/voxstream_viewer_bg.wasm", "application/wasm"),
        ("/pkg/voxstream_viewer.js", "pkg/voxstream_viewer.js", "javascript"),
        ("/viewer.css", "viewer.css", "text/css"),
        ("/upload.html", "upload.html", "text/html"),
    ] {
        let resp = http.get(format!("{base}{path}")).send().await.unwrap();
        assert_eq!(resp.status(), 200, "{path}");
        let ct = resp.headers()["content-type"].to_str().unwrap().to_string();
        assert!(ct.contains(mime), "{path}: content-type {ct:?}, expected {mime}");
        assert_eq!(resp.headers()["cache-control"], "no-cache", "{path}");
        let etag = resp.headers()["etag"].clone();
        let body = resp.bytes().await.unwrap();
        assert_eq!(
            body.as_ref(),
            std::fs::read(dist.join(file)).unwrap().as_slice(),
            "{path} differs from dist/{file}"
        );
        let again = http.get(format!("{base}{path}")).header("if-none-match", etag).send().await.unwrap();
        assert_eq!(again.status(), 304, "{path}");
    }
    let head = http.head(format!("{base}/pkg/voxstream_viewer_bg.wasm")).send().await.unwrap();
    assert_eq!(head.status(), 200);
    let e = json_error(http.get(format!("{base}/pkg/missing.wasm")).send().await.unwrap(), 404).await;
    assert!(e.contains("no viewer file"), "{e}");
    let e = json_error(http.post(format!("{base}/index.html")).send().await.unwrap(), 405).await;
    assert!(e.contains("read-only"), "{e}");
}

/// Fails if a read that loses a race with a delete or rename answers 500 (the scene's files went
/// with it: that is a 404, "fetch again"), or if a read of a scene that is still served but
/// damaged stops being a 500.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reads_racing_a_delete_or_rename_are_404_never_500() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let opts = BuildOptions { resolution: Resolution::Explicit(256), ..Default::default() };
    build_scene(&koala(), &store, &opts).unwrap();
    let on_disk = assert_scene_complete(&store, "koala");
    let s = start_with(config(&store)).await;
    let base = s.base.clone();
    let c = http();

    // The entry a request took stops being served when the scene is renamed or deleted under it.
    let taken = s.state.catalog.get("koala").unwrap();
    assert!(s.state.catalog.still_serves(&taken));
    let resp =
        auth(c.patch(format!("{base}/api/scenes/koala"))).body(r#"{"id": "gum"}"#).send().await.unwrap();
    assert_eq!(resp.status(), 200);
    assert!(!s.state.catalog.still_serves(&taken), "renamed away: the old entry is not served");
    let renamed = s.state.catalog.get("gum").unwrap();
    assert!(s.state.catalog.still_serves(&renamed));
    let resp =
        auth(c.patch(format!("{base}/api/scenes/gum"))).body(r#"{"id": "koala"}"#).send().await.unwrap();
    assert_eq!(resp.status(), 200);

    // Many reads of blocks and the thumbnail while the scene is deleted: each is a 200 or a JSON 404.
    let urls: Vec<String> = on_disk
        .blocks
        .iter()
        .map(|e| format!("{base}/api/scenes/koala/blocks/{}.{}", e.key, e.hash))
        .chain([format!("{base}/api/scenes/koala/thumbnail.png")])
        .collect();
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering::SeqCst};
    let deleted = std::sync::Arc::new(AtomicBool::new(false));
    let served = std::sync::Arc::new(AtomicUsize::new(0));
    let mut readers = Vec::new();
    for start in 0..4 {
        let (urls, deleted, served, c) = (urls.clone(), deleted.clone(), served.clone(), c.clone());
        readers.push(tokio::spawn(async move {
            let (mut gone, mut after) = (0, 0);
            for url in urls.iter().cycle().skip(start * 7) {
                let resp = c.get(url).send().await.unwrap();
                match resp.status().as_u16() {
                    200 => _ = served.fetch_add(1, SeqCst),
                    _ => {
                        json_error(resp, 404).await;
                        gone += 1;
                    }
                }
                if deleted.load(SeqCst) {
                    after += 1;
                    if after > 20 {
                        break;
                    }
                }
            }
            gone
        }));
    }
    // Delete while the readers are mid-stream: after some reads were served, however slow the machine.
    let waited = std::time::Instant::now();
    while served.load(SeqCst) < 40 && waited.elapsed() < Duration::from_secs(30) {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(auth(c.delete(format!("{base}/api/scenes/koala"))).send().await.unwrap().status(), 204);
    deleted.store(true, SeqCst);
    let mut gone = 0;
    for r in readers {
        gone += r.await.unwrap();
    }
    let ok = served.load(SeqCst);
    assert!(ok > 0 && gone > 0, "reads before and after the delete: {ok} served, {gone} gone");

    // Negative control: a scene still served whose pack is missing is a damaged store, a 500.
    let opts = BuildOptions { resolution: Resolution::Explicit(128), ..Default::default() };
    build_scene(&koala(), &store, &opts).unwrap();
    let loaded = s.state.catalog.refresh("koala").unwrap();
    assert!(s.state.catalog.still_serves(&loaded));
    let e = &assert_scene_entries(&store, "koala")[0];
    let url = format!("{base}/api/scenes/koala/blocks/{}.{}", e.key, e.hash);
    assert_eq!(c.get(&url).send().await.unwrap().status(), 200, "its pages are read");
    for pack in std::fs::read_dir(store.join("koala/packs")).unwrap() {
        std::fs::remove_file(pack.unwrap().path()).unwrap();
    }
    let resp = c.get(&url).send().await.unwrap();
    let message = json_error(resp, 500).await;
    assert!(message.contains("pack"), "{message}");
    assert!(s.state.catalog.still_serves(&loaded));
    // A rebuild published under the same id: the entry taken before it is not the one served.
    let opts = BuildOptions { resolution: Resolution::Explicit(64), ..Default::default() };
    build_scene(&koala(), &store, &opts).unwrap();
    assert!(!s.state.catalog.still_serves(&loaded), "rebuilt under it");
}

/// The block entries of a scene in a local store, read from its pages.
fn assert_scene_entries(store: &Path, id: &str) -> Vec<voxstream_format::BlockEntry> {
    voxstream::store::open_scene(store, id).unwrap().blocks()
}
