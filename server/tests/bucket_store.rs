//! Scenes in a bucket, against a real Garage (tests/common/garage.rs): `voxstream build --out
//! s3://…` and `voxstream serve --store s3://…` as child processes.

mod common;

use std::collections::BTreeMap;
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use common::garage::{Garage, koala, voxstream_with};
use common::serve::spawn_listening;
use futures_util::StreamExt;
use object_store::ObjectStore;
use object_store::path::Path as ObjectPath;
use voxstream_format::{HierarchyPage, Manifest, SceneIndex};

/// Runs `voxstream build <mesh> --out <out> --resolution <res> --name <id>`; panics with its stderr
/// when it fails.
fn build(garage: Option<&Garage>, out: &str, resolution: u32, id: &str) -> String {
    let out = voxstream_with(garage, &[])
        .arg("build")
        .arg(koala())
        .args(["--out", out, "--resolution", &resolution.to_string(), "--name", id])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "build to {out:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    stdout
}

/// A `voxstream serve` child on a free loopback port; killed when dropped.
struct Server {
    child: Child,
    base: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn serve(garage: Option<&Garage>, store: &str) -> Server {
    let mut cmd = voxstream_with(garage, &[]);
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--relist-secs", "1", "--store", store])
        .stderr(Stdio::null());
    let (child, base) = spawn_listening(cmd);
    Server { child, base }
}

/// Everything a client can read of one scene over HTTP: the manifest, every page and every block
/// (bytes, ETag, Cache-Control), by URL path.
async fn read_scene(
    http: &reqwest::Client,
    base: &str,
    id: &str,
) -> BTreeMap<String, (Vec<u8>, String, String)> {
    let mut seen = BTreeMap::new();
    let get = |path: String| async move {
        let r = http.get(format!("{base}{path}")).send().await.unwrap();
        assert_eq!(r.status(), 200, "GET {path}");
        let header =
            |n: &str| r.headers().get(n).map(|v| v.to_str().unwrap().to_string()).unwrap_or_default();
        let (etag, cache) = (header("etag"), header("cache-control"));
        (r.bytes().await.unwrap().to_vec(), etag, cache)
    };
    let manifest_path = format!("/api/scenes/{id}/manifest");
    let manifest = get(manifest_path.clone()).await;
    let parsed = Manifest::from_json(&manifest.0).unwrap();
    seen.insert(manifest_path, manifest);
    let mut index = SceneIndex::new(&parsed);
    loop {
        let wanted: Vec<_> = index.missing_pages().cloned().collect();
        if wanted.is_empty() {
            break;
        }
        for r in wanted {
            let path = format!("/api/scenes/{id}/pages/{}.{}", r.root, r.hash);
            let page = get(path.clone()).await;
            index.insert_page(HierarchyPage::decode(&page.0, &r).unwrap()).unwrap();
            seen.insert(path, page);
        }
    }
    for b in index.blocks() {
        let path = format!("/api/scenes/{id}/blocks/{}.{}", b.key, b.hash);
        seen.insert(path.clone(), get(path).await);
    }
    seen
}

/// `voxstream_<name>_total{kind="<kind>"}` from the metrics text; 0 when absent.
async fn counter(http: &reqwest::Client, base: &str, name: &str, kind: &str) -> u64 {
    let text = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    let prefix = format!("voxstream_{name}_total{{kind=\"{kind}\"}} ");
    text.lines().find_map(|l| l.strip_prefix(&prefix)).map_or(0, |v| v.trim().parse().unwrap())
}

/// A scan built into Garage is served by a bucket replica block for block, page for page, identical
/// to the same build on a local path (bytes, ETags, cache headers, 304s); the bucket's other scene
/// (another resolution: the negative control) differs. A second pass of GETs is served from the
/// replica's cache (hits in /metrics; the first pass counted only misses). Writes are refused with
/// a 403 naming how to build into a bucket.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bucket_scene_is_served_identical_to_local_and_cached() {
    let garage = Garage::start();
    garage.create_bucket("scans");
    let dir = tempfile::tempdir().unwrap();
    let local = dir.path().join("store");
    build(None, local.to_str().unwrap(), 512, "koala");
    let printed = build(Some(&garage), "s3://scans/site", 512, "koala");
    assert!(printed.contains("s3://scans/site/koala"), "{printed}");
    build(Some(&garage), "s3://scans/site", 64, "koala-coarse");
    let bucket = garage.client("scans");
    // Content-addressed pages in the bucket, the manifest last.
    let names: Vec<String> = bucket
        .list(Some(&ObjectPath::from("site/koala")))
        .map(|m| m.unwrap().location.to_string())
        .collect::<Vec<_>>()
        .await;
    assert!(names.contains(&"site/koala/manifest.json".to_string()), "{names:?}");
    assert!(names.iter().any(|n| n.starts_with("site/koala/packs/") && n.ends_with(".vxp")), "{names:?}");
    assert!(
        names.iter().filter(|n| n.starts_with("site/koala/pages/")).all(|n| n.split('.').count() == 3),
        "pages are <key>.<hash>.vxh: {names:?}"
    );

    let local_server = serve(None, local.to_str().unwrap());
    let replica = serve(Some(&garage), "s3://scans/site");
    let http = reqwest::Client::new();
    let list: serde_json::Value =
        http.get(format!("{}/api/scenes", replica.base)).send().await.unwrap().json().await.unwrap();
    let ids: Vec<&str> = list.as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap()).collect();
    assert_eq!(ids, ["koala", "koala-coarse"]);

    let from_local = read_scene(&http, &local_server.base, "koala").await;
    let blocks = from_local.keys().filter(|k| k.contains("/blocks/")).count() as u64;
    assert!(blocks > 10, "{blocks} blocks");
    assert_eq!(counter(&http, &replica.base, "store_cache_hits", "block").await, 0);
    let from_bucket = read_scene(&http, &replica.base, "koala").await;
    assert_eq!(from_local.len(), from_bucket.len());
    for (path, local) in &from_local {
        assert!(
            from_bucket.get(path) == Some(local),
            "{path} differs between the local and the bucket store"
        );
    }
    // Negative control: another scene of the same bucket is not the same.
    let coarse = read_scene(&http, &replica.base, "koala-coarse").await;
    let manifest = |m: &BTreeMap<String, (Vec<u8>, String, String)>, id: &str| {
        m[&format!("/api/scenes/{id}/manifest")].0.clone()
    };
    assert_ne!(manifest(&coarse, "koala-coarse"), manifest(&from_bucket, "koala"));
    let block_etags = |m: &BTreeMap<String, (Vec<u8>, String, String)>| {
        m.iter().filter(|(k, _)| k.contains("/blocks/")).map(|(_, v)| v.1.clone()).collect::<Vec<_>>()
    };
    assert_ne!(block_etags(&coarse), block_etags(&from_bucket));

    // 304s are the same too.
    let (path, (_, etag, _)) = from_local.iter().find(|(k, _)| k.contains("/blocks/")).unwrap();
    for base in [&local_server.base, &replica.base] {
        let r = http.get(format!("{base}{path}")).header("if-none-match", etag).send().await.unwrap();
        assert_eq!(r.status(), 304, "{base}{path}");
        assert_eq!(r.headers()["etag"].to_str().unwrap(), etag);
    }

    // The first pass read every block from the bucket; the second is served from the cache.
    let misses = counter(&http, &replica.base, "store_cache_misses", "block").await;
    assert!(misses >= blocks, "{misses} misses for {blocks} blocks");
    let hits_before = counter(&http, &replica.base, "store_cache_hits", "block").await;
    let again = read_scene(&http, &replica.base, "koala").await;
    assert_eq!(again, from_bucket);
    let hits = counter(&http, &replica.base, "store_cache_hits", "block").await - hits_before;
    assert_eq!(hits, blocks, "second pass: {hits} block hits for {blocks} blocks");
    assert_eq!(counter(&http, &replica.base, "store_cache_misses", "block").await, misses, "no new misses");
    let metrics = http.get(format!("{}/metrics", replica.base)).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains(&format!("voxstream_store_cache_capacity_bytes {}", 256u64 << 20)), "{metrics}");

    // Writes are refused, saying how scenes get into a bucket.
    for r in [
        http.post(format!("{}/api/scenes?filename=k.obj", replica.base))
            .body("v 0 0 0")
            .send()
            .await
            .unwrap(),
        http.delete(format!("{}/api/scenes/koala", replica.base)).send().await.unwrap(),
    ] {
        assert_eq!(r.status(), 403);
        let body: serde_json::Value = r.json().await.unwrap();
        assert!(body["error"].as_str().unwrap().contains("voxstream build --out s3://"), "{body}");
    }
    // A scene published after the replica started is found (listing, or lookup on a miss).
    build(Some(&garage), "s3://scans/site", 64, "late");
    let r = http.get(format!("{}/api/scenes/late", replica.base)).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let r = http.get(format!("{}/api/scenes/never-built", replica.base)).send().await.unwrap();
    assert_eq!(r.status(), 404);
}

/// A replica whose bucket is unreachable, whose key is refused or whose bucket does not exist says
/// so at start, naming the endpoint and the cause, and exits non-zero within seconds without
/// printing the secret. Negative control: the right settings start and list the scene.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_bucket_configuration_fails_fast_and_clearly() {
    let garage = Garage::start();
    garage.create_bucket("scans");
    // A port that was free a moment ago: nothing listens there.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dead = format!("http://127.0.0.1:{port}");
    // (store, settings over the right ones, what the error must name)
    type Case<'a> = (&'a str, Vec<(&'a str, String)>, &'a [&'a str]);
    let cases: [Case; 3] = [
        ("s3://scans/site", vec![("AWS_ENDPOINT_URL", dead.clone())], &[dead.as_str(), "connect"]),
        (
            "s3://scans/site",
            vec![("AWS_SECRET_ACCESS_KEY", "0".repeat(64))],
            &[garage.endpoint.as_str(), "credentials refused"],
        ),
        ("s3://no-such-bucket/site", vec![], &[garage.endpoint.as_str(), "no-such-bucket", "does not exist"]),
    ];
    for (store, env, expected) in cases {
        for args in [
            vec!["serve", "--addr", "127.0.0.1:0", "--store", store],
            vec!["build", koala().to_str().unwrap(), "--resolution", "64", "--out", store],
        ] {
            let started = Instant::now();
            let out = voxstream_with(Some(&garage), &env).args(&args).output().unwrap();
            let took = started.elapsed();
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(!out.status.success(), "{args:?} with {env:?} succeeded");
            assert!(String::from_utf8_lossy(&out.stdout).is_empty(), "{args:?} printed: never serve empty");
            for e in expected {
                assert!(err.contains(e), "{args:?}: expected {e:?} in {err}");
            }
            assert!(took < Duration::from_secs(10), "{args:?} took {took:?}");
            assert!(!err.contains(&garage.secret), "the secret was printed: {err}");
        }
    }
    build(Some(&garage), "s3://scans/site", 64, "koala");
    let server = serve(Some(&garage), "s3://scans/site");
    let list = reqwest::get(format!("{}/api/scenes", server.base)).await.unwrap().text().await.unwrap();
    assert!(list.contains("\"id\":\"koala\""), "{list}");
}

/// A build killed while it uploads never makes a half-published scene visible: the scene's old
/// manifest (a complete earlier build) stays, every object it names is still there, and a replica
/// serves the old scene whole. A first publish killed the same way leaves no manifest, so no
/// replica lists it. Negative control: the same build left to finish replaces the manifest.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_bucket_build_never_publishes_half_a_scene() {
    let garage = Garage::start();
    garage.create_bucket("scans");
    let bucket = garage.client("scans");
    build(Some(&garage), "s3://scans/site", 64, "koala");
    let manifest_at = ObjectPath::from("site/koala/manifest.json");
    let old_manifest = bucket.get(&manifest_at).await.unwrap().bytes().await.unwrap();

    for id in ["koala", "fresh"] {
        let packs_before = count(&bucket, &format!("site/{id}/packs")).await;
        let mut child = voxstream_with(Some(&garage), &[])
            .arg("build")
            .arg(koala())
            .args(["--out", "s3://scans/site", "--resolution", "2048", "--name", id])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        // Kill it once its first new pack is in the bucket: mid-upload.
        let started = Instant::now();
        loop {
            if count(&bucket, &format!("site/{id}/packs")).await > packs_before {
                break;
            }
            assert!(
                child.try_wait().unwrap().is_none(),
                "the build ended before it was killed: make it bigger"
            );
            assert!(started.elapsed() < Duration::from_secs(300), "no pack uploaded within 300 s");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(count(&bucket, &format!("site/{id}/packs")).await > packs_before, "uploads had begun");
        let manifest = bucket.get(&ObjectPath::from(format!("site/{id}/manifest.json"))).await;
        match id {
            "koala" => {
                assert_eq!(manifest.unwrap().bytes().await.unwrap(), old_manifest, "the old manifest stays")
            }
            _ => {
                assert!(matches!(manifest, Err(object_store::Error::NotFound { .. })), "no manifest for {id}")
            }
        }
    }
    let replica = serve(Some(&garage), "s3://scans/site");
    let http = reqwest::Client::new();
    let list: serde_json::Value =
        http.get(format!("{}/api/scenes", replica.base)).send().await.unwrap().json().await.unwrap();
    let ids: Vec<&str> = list.as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap()).collect();
    assert_eq!(ids, ["koala"], "the half-published scene is not listed");
    assert_eq!(http.get(format!("{}/api/scenes/fresh", replica.base)).send().await.unwrap().status(), 404);
    let old = read_scene(&http, &replica.base, "koala").await;
    assert_eq!(
        old[&"/api/scenes/koala/manifest".to_string()].0,
        old_manifest.to_vec(),
        "the old scene, whole"
    );

    // Negative control: left to finish, the rebuild replaces the manifest.
    build(Some(&garage), "s3://scans/site", 128, "koala");
    let new_manifest = bucket.get(&manifest_at).await.unwrap().bytes().await.unwrap();
    assert_ne!(new_manifest, old_manifest);
}

async fn count(bucket: &std::sync::Arc<dyn ObjectStore>, prefix: &str) -> usize {
    bucket.list(Some(&ObjectPath::from(prefix))).collect::<Vec<_>>().await.len()
}
