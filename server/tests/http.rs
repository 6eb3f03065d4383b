//! The server on an ephemeral port: catalog, manifest and blocks come back and
//! decode to what the store holds; unknown ids get 404 with a JSON error.

use std::path::Path;

use voxstream::build::{BuildOptions, build_scene};
use voxstream::http::{AppState, BLOCK_CACHE_CONTROL, router};
use voxstream_format::{Manifest, SceneSummary, decode_block};

/// A closed box with a notch, written as OBJ: enough to give several blocks and levels.
fn write_test_mesh(path: &Path) {
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
    std::fs::write(path, obj).unwrap();
}

async fn start(store: &Path) -> String {
    let state = AppState::load(store, None).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, router(state)).await.unwrap() });
    format!("http://{addr}")
}

async fn json_error(resp: reqwest::Response, status: u16) -> String {
    assert_eq!(resp.status().as_u16(), status, "{}", resp.url());
    assert_eq!(resp.headers()["content-type"], "application/json");
    let body: serde_json::Value = resp.json().await.unwrap();
    body["error"].as_str().expect("JSON body has an error string").to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_what_the_store_holds() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("Box Scan.obj");
    write_test_mesh(&mesh);
    let store = dir.path().join("store");
    let report = build_scene(&mesh, &store, &BuildOptions { resolution: 256, ..Default::default() }).unwrap();
    assert_eq!(report.id, "box-scan");
    assert_eq!(report.levels, 3);
    let base = start(&store).await;
    let http = reqwest::Client::new();

    let scenes: Vec<SceneSummary> =
        http.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert_eq!(scenes.len(), 1);
    assert_eq!(scenes[0].id, "box-scan");
    assert_eq!(scenes[0].triangles, 12);
    assert_eq!(scenes[0].blocks, report.blocks);

    let on_disk = Manifest::from_json(&std::fs::read(store.join("box-scan/manifest.json")).unwrap()).unwrap();
    let served = http.get(format!("{base}/api/scenes/box-scan/manifest")).send().await.unwrap();
    assert_eq!(served.status(), 200);
    let served = Manifest::from_json(&served.bytes().await.unwrap()).unwrap();
    assert_eq!(served, on_disk);
    assert!(served.blocks.len() > 8, "expected several blocks, got {}", served.blocks.len());

    for entry in &served.blocks {
        let url = format!("{base}/api/scenes/box-scan/blocks/{}", entry.key);
        let resp = http.get(&url).send().await.unwrap();
        assert_eq!(resp.status(), 200, "{url}");
        let etag = resp.headers()["etag"].to_str().unwrap().to_string();
        assert_eq!(etag, format!("\"{}\"", entry.hash));
        assert_eq!(resp.headers()["cache-control"], BLOCK_CACHE_CONTROL);
        assert_eq!(resp.headers()["content-type"], "application/octet-stream");
        assert!(resp.headers().get("content-encoding").is_none());
        let bytes = resp.bytes().await.unwrap();
        let file = std::fs::read(store.join(format!("box-scan/blocks/{}.vxb", entry.key))).unwrap();
        assert_eq!(&bytes[..], &file[..]);
        let block = decode_block(&bytes).unwrap();
        assert_eq!(block.key, entry.key);
        assert_eq!(block.voxels.len() as u32, entry.voxels);
        assert_eq!(block.face_count(), entry.faces);
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), entry.hash);

        let again = http.get(&url).header("if-none-match", &etag).send().await.unwrap();
        assert_eq!(again.status(), 304);
        assert!(again.bytes().await.unwrap().is_empty());
    }

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
    json_error(http.get(format!("{base}/api/scenes/..%2f..%2fetc/manifest")).send().await.unwrap(), 404)
        .await;
    json_error(http.get(format!("{base}/api/nothing-here")).send().await.unwrap(), 404).await;
    json_error(http.get(format!("{base}/index.html")).send().await.unwrap(), 404).await;
}

#[tokio::test]
async fn rebuild_replaces_a_scene_atomically_and_bad_input_leaves_no_trace() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("box.obj");
    write_test_mesh(&mesh);
    let store = dir.path().join("store");
    build_scene(&mesh, &store, &BuildOptions { resolution: 64, ..Default::default() }).unwrap();
    let first = std::fs::read(store.join("box/manifest.json")).unwrap();
    build_scene(&mesh, &store, &BuildOptions { resolution: 128, ..Default::default() }).unwrap();
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
