//! Renames, deletes and garbage collection of bucket scenes on the cluster of `scripts/cluster.sh`
//! (two `serve --store s3://… --coordinator postgres://…` replicas, three Garage nodes, a real
//! PostgreSQL), against the real processes:
//!
//! - a delete on replica 1 removes the scene's manifest and every object from the bucket, and
//!   replica 2 stops listing it within its relist period; another scene is untouched;
//! - a rename on replica 1 serves the same blocks (same hashes, same bytes) under the new id on
//!   both replicas, the old id is a 404 on both, and the old objects are gone; renaming onto an
//!   existing id, or while a build of either id is queued or running, is a 409; a display name
//!   change is seen by both replicas;
//! - after a replacing build, the replica that built it collects the previous version's packs once
//!   the grace period (1 s here) has passed, counts them in /metrics, and the new scene reads every
//!   block.

mod common;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use base64::Engine;
use object_store::ObjectStore;
use serde_json::{Value, json};
use voxstream::bucket_store::BucketStore;
use voxstream::objstore::Bucket;
use voxstream_format::Manifest;
use voxstream_format::hierarchy::pack_path;

use common::cluster::{Cluster, koala, object_names, wait_listed};

/// Object names under `scenes/<id>/`, relative to it.
async fn objects(store: &dyn ObjectStore, id: &str) -> BTreeSet<String> {
    let names = object_names(store, &format!("scenes/{id}")).await;
    names.into_iter().map(|n| n[format!("scenes/{id}/").len()..].to_string()).collect()
}

/// `<key>.<hash>` of every block of scene `id`, from the bucket (every page read).
async fn block_names(store: &BucketStore, id: &str) -> Vec<String> {
    let manifest = Manifest::from_json(&store.manifest(id).await.unwrap().unwrap()).unwrap();
    let index = store.load_index(id, &manifest).await.unwrap();
    let mut names: Vec<String> = index.blocks().map(|e| format!("{}.{}", e.key, e.hash)).collect();
    names.sort();
    names
}

async fn packs_named(store: &BucketStore, id: &str) -> BTreeSet<String> {
    let manifest = Manifest::from_json(&store.manifest(id).await.unwrap().unwrap()).unwrap();
    let index = store.load_index(id, &manifest).await.unwrap();
    index.packs().map(|p| pack_path(&p.hash)).collect()
}

/// Every block `names` of scene `id` from `base`, in order; each must be a 200.
async fn fetch_blocks(http: &reqwest::Client, base: &str, id: &str, names: &[String]) -> Vec<Vec<u8>> {
    let mut out = Vec::with_capacity(names.len());
    for name in names {
        let r = http.get(format!("{base}/api/scenes/{id}/blocks/{name}")).send().await.unwrap();
        assert_eq!(r.status(), 200, "{base}: block {name} of {id}");
        let bytes = r.bytes().await.unwrap().to_vec();
        let hash = name.split_once('.').unwrap().1;
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), hash, "{base}: block {name} of {id}");
        out.push(bytes);
    }
    out
}

async fn status_of(http: &reqwest::Client, url: &str) -> u16 {
    http.get(url).send().await.unwrap().status().as_u16()
}

/// Polls until `GET url` answers `status`; fails after `within`.
async fn wait_status(http: &reqwest::Client, url: &str, status: u16, within: Duration) -> Duration {
    let started = Instant::now();
    loop {
        if status_of(http, url).await == status {
            return started.elapsed();
        }
        assert!(started.elapsed() < within, "{url} did not answer {status} within {within:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A JSON error answer: its status and message.
async fn error(r: reqwest::Response) -> (u16, String) {
    let status = r.status().as_u16();
    let body: Value = r.json().await.expect("errors are JSON");
    (status, body["error"].as_str().expect("an error message").to_string())
}

async fn patch(http: &reqwest::Client, base: &str, id: &str, body: Value) -> reqwest::Response {
    http.patch(format!("{base}/api/scenes/{id}")).json(&body).send().await.unwrap()
}

/// Uploads the koala as scene `id` (tus, one PATCH) on `base`; returns the job id.
async fn upload(http: &reqwest::Client, base: &str, id: &str, resolution: &str, replace: bool) -> String {
    let mesh = std::fs::read(koala()).unwrap();
    let b64 = |v: &str| base64::engine::general_purpose::STANDARD.encode(v);
    let mut meta = vec![("filename", "koala.obj"), ("id", id), ("resolution", resolution)];
    if replace {
        meta.push(("replace", "true"));
    }
    let meta = meta.iter().map(|(k, v)| format!("{k} {}", b64(v))).collect::<Vec<_>>().join(",");
    let r = http
        .post(format!("{base}/api/uploads"))
        .header("Tus-Resumable", "1.0.0")
        .header("Upload-Length", mesh.len().to_string())
        .header("Upload-Metadata", meta)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "tus create: {}", r.text().await.unwrap());
    let path = r.headers()["location"].to_str().unwrap().to_string();
    let r = http
        .patch(format!("{base}{path}"))
        .header("Tus-Resumable", "1.0.0")
        .header("Upload-Offset", "0")
        .header("Content-Type", "application/offset+octet-stream")
        .body(mesh)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204, "tus patch");
    r.headers()["voxstream-job"].to_str().unwrap().to_string()
}

async fn job_state(http: &reqwest::Client, base: &str, job: &str) -> String {
    let j: Value = http.get(format!("{base}/api/jobs/{job}")).send().await.unwrap().json().await.unwrap();
    j["state"].as_str().unwrap().to_string()
}

async fn wait_job(http: &reqwest::Client, base: &str, job: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        let state = job_state(http, base, job).await;
        if ["done", "failed", "cancelled"].contains(&state.as_str()) {
            return state;
        }
        assert!(Instant::now() < deadline, "job {job} did not end");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

async fn gc_deleted(http: &reqwest::Client, base: &str) -> u64 {
    let text = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix("voxstream_gc_objects_deleted_total "))
        .unwrap_or_else(|| panic!("{base}/metrics has no voxstream_gc_objects_deleted_total"))
        .trim()
        .parse()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bucket_scenes_are_deleted_renamed_and_collected_across_replicas() {
    let started = Instant::now();
    // The periodic collector runs every 3 s: it must not disturb anything below, and it alone
    // removes the orphan put here (the after-publish pass only looks at the scene it built).
    let cluster = Cluster::start_with(&[("CLUSTER_GC_GRACE_SECS", "1"), ("CLUSTER_GC_INTERVAL_SECS", "3")]);
    let http = reqwest::Client::builder().timeout(Duration::from_secs(60)).build().unwrap();
    let replicas = cluster.list("REPLICA_URLS");
    let (r1, r2) = (replicas[0].as_str(), replicas[1].as_str());
    let s3 = cluster.bucket();
    let store = BucketStore::new(
        Bucket {
            store: s3.clone(),
            bucket: "voxstream".into(),
            prefix: "scenes".into(),
            endpoint: "test".into(),
        },
        64 << 20,
    );
    // The replicas list the bucket every 2 s (scripts/cluster.sh); a miss is remembered for 2 s.
    let relist = Duration::from_secs(2);
    let follow = relist * 3;

    for (id, resolution) in [("alpha", "64"), ("beta", "256"), ("gamma", "128")] {
        cluster.build(id, resolution);
    }
    for base in [r1, r2] {
        for id in ["alpha", "beta", "gamma"] {
            wait_listed(&http, base, id).await;
        }
    }
    let gamma_objects = objects(s3.as_ref(), "gamma").await;
    assert!(
        !gamma_objects.contains("building.json"),
        "a finished build deletes its marker: {gamma_objects:?}"
    );
    // What a killed CLI build leaves: packs under an id that never got a manifest.
    let orphan = format!("scenes/orphan/{}", pack_path(&"0f".repeat(32)));
    s3.put(&orphan.as_str().into(), vec![7u8; 100].into()).await.unwrap();
    let orphan_put = Instant::now();
    assert_eq!(objects(s3.as_ref(), "orphan").await.len(), 1, "the orphan is where the collector looks");
    eprintln!("{:.1} s: cluster up, three scenes built", started.elapsed().as_secs_f64());

    // --- delete ----------------------------------------------------------------------------
    assert!(objects(s3.as_ref(), "alpha").await.contains("manifest.json"));
    let r = http.delete(format!("{r1}/api/scenes/alpha")).send().await.unwrap();
    assert_eq!(r.status(), 204, "delete on replica 1: {}", r.text().await.unwrap());
    let left = objects(s3.as_ref(), "alpha").await;
    assert!(left.is_empty(), "the deleted scene's objects remain: {left:?}");
    assert_eq!(status_of(&http, &format!("{r1}/api/scenes/alpha")).await, 404, "replica 1 follows at once");
    let took = wait_status(&http, &format!("{r2}/api/scenes/alpha"), 404, follow).await;
    eprintln!("replica 2 stopped serving the deleted scene after {took:?}");
    let listed: Value = http.get(format!("{r2}/api/scenes")).send().await.unwrap().json().await.unwrap();
    assert!(!listed.to_string().contains("\"alpha\""), "{listed}");
    // Deleting it again: 404 JSON naming it.
    let (status, message) = error(http.delete(format!("{r2}/api/scenes/alpha")).send().await.unwrap()).await;
    assert_eq!(status, 404);
    assert!(message.contains("alpha"), "{message}");
    // Control: the other scenes are untouched.
    assert_eq!(objects(s3.as_ref(), "gamma").await, gamma_objects);
    for base in [r1, r2] {
        assert_eq!(status_of(&http, &format!("{base}/api/scenes/beta")).await, 200);
    }

    // --- rename ----------------------------------------------------------------------------
    let beta_objects = objects(s3.as_ref(), "beta").await;
    let beta_manifest = store.manifest("beta").await.unwrap().unwrap();
    let names = block_names(&store, "beta").await;
    assert!(names.len() > 10, "{} blocks", names.len());
    let before = fetch_blocks(&http, r1, "beta", &names).await;
    let r = patch(&http, r1, "beta", json!({ "id": "delta" })).await;
    assert_eq!(r.status(), 200, "rename on replica 1");
    let meta: Value = r.json().await.unwrap();
    assert_eq!(meta["id"], "delta");
    // The bucket: the same objects under the new id, the same manifest bytes, nothing under the old.
    assert_eq!(objects(s3.as_ref(), "delta").await, beta_objects);
    assert_eq!(store.manifest("delta").await.unwrap().unwrap(), beta_manifest);
    assert!(objects(s3.as_ref(), "beta").await.is_empty(), "the old id's objects remain");
    assert_eq!(block_names(&store, "delta").await, names);
    // Both replicas serve the new id block for block (same hashes, same bytes).
    for base in [r1, r2] {
        assert_eq!(fetch_blocks(&http, base, "delta", &names).await, before, "{base}: delta");
    }
    assert_eq!(status_of(&http, &format!("{r1}/api/scenes/beta")).await, 404);
    wait_status(&http, &format!("{r2}/api/scenes/beta"), 404, follow).await;
    let old_block = format!("{r2}/api/scenes/beta/blocks/{}", names[0]);
    assert_eq!(status_of(&http, &old_block).await, 404);

    // Onto an existing id: 409, both scenes as they were.
    let (status, message) = error(patch(&http, r2, "delta", json!({ "id": "gamma" })).await).await;
    assert_eq!(status, 409, "{message}");
    assert!(message.contains("gamma"), "{message}");
    assert_eq!(objects(s3.as_ref(), "gamma").await, gamma_objects);
    assert_eq!(objects(s3.as_ref(), "delta").await, beta_objects);
    // Bad input: 4xx JSON naming the problem, nothing changed.
    for (body, want) in [
        (json!({ "id": "Not An Id!" }), "id"),
        (json!({}), "\"id\""),
        (json!({ "colour": "red" }), "colour"),
        (json!({ "name": "" }), "name"),
    ] {
        let (status, message) = error(patch(&http, r1, "delta", body.clone()).await).await;
        assert_eq!(status, 400, "{body}: {message}");
        assert!(message.contains(want), "{body}: {message}");
    }
    let (status, _) = error(patch(&http, r1, "no-such-scene", json!({ "id": "x" })).await).await;
    assert_eq!(status, 404);
    assert_eq!(objects(s3.as_ref(), "delta").await, beta_objects);

    // A display name: scene.json in the bucket; both replicas show it.
    let r = patch(&http, r1, "delta", json!({ "name": "Koala, renamed" })).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.json::<Value>().await.unwrap()["name"], "Koala, renamed");
    assert!(objects(s3.as_ref(), "delta").await.contains("scene.json"));
    let deadline = Instant::now() + follow;
    loop {
        let m: Value = http.get(format!("{r2}/api/scenes/delta")).send().await.unwrap().json().await.unwrap();
        if m["name"] == "Koala, renamed" {
            break;
        }
        assert!(Instant::now() < deadline, "replica 2 never showed the new name: {m}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!("{:.1} s: deletes and renames checked", started.elapsed().as_secs_f64());

    // --- builds fence edits ------------------------------------------------------------------
    // A replacing build of gamma (at a higher resolution: several seconds) and a first build of
    // zeta: while they are queued or running, neither id can be renamed, deleted or renamed onto.
    let old_gamma_packs = packs_named(&store, "gamma").await;
    let gc_before = gc_deleted(&http, r1).await + gc_deleted(&http, r2).await;
    let gamma_job = upload(&http, r1, "gamma", "256", true).await;
    let zeta_job = upload(&http, r2, "zeta", "256", false).await;
    let (rename_gamma, delete_gamma, onto_zeta) = (
        patch(&http, r2, "gamma", json!({ "id": "eta" })).await,
        http.delete(format!("{r1}/api/scenes/gamma")).send().await.unwrap(),
        patch(&http, r1, "delta", json!({ "id": "zeta" })).await,
    );
    let states = (job_state(&http, r1, &gamma_job).await, job_state(&http, r1, &zeta_job).await);
    assert!(
        ["queued", "running"].contains(&states.0.as_str())
            && ["queued", "running"].contains(&states.1.as_str()),
        "the builds ended before the edits were tried: {states:?}; the test proves nothing"
    );
    for (what, r) in
        [("rename gamma", rename_gamma), ("delete gamma", delete_gamma), ("rename onto zeta", onto_zeta)]
    {
        let (status, message) = error(r).await;
        assert_eq!(status, 409, "{what}: {message}");
        assert!(message.contains("build"), "{what}: {message}");
    }
    assert_eq!(wait_job(&http, r1, &gamma_job).await, "done");
    assert_eq!(wait_job(&http, r1, &zeta_job).await, "done");
    assert!(objects(s3.as_ref(), "delta").await.contains("manifest.json"), "delta was not renamed");
    assert!(objects(s3.as_ref(), "eta").await.is_empty());

    // --- garbage collection after the replacing build ----------------------------------------
    let new_gamma_packs = packs_named(&store, "gamma").await;
    let replaced: BTreeSet<String> = old_gamma_packs.difference(&new_gamma_packs).cloned().collect();
    assert!(!replaced.is_empty(), "the rebuild names other packs");
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let now = objects(s3.as_ref(), "gamma").await;
        if replaced.iter().all(|p| !now.contains(p)) {
            let packs: BTreeSet<String> = now.into_iter().filter(|o| o.starts_with("packs/")).collect();
            assert_eq!(packs, new_gamma_packs, "exactly the new manifest's packs remain");
            break;
        }
        assert!(Instant::now() < deadline, "the replaced packs were never collected: {replaced:?}");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let gc_after = gc_deleted(&http, r1).await + gc_deleted(&http, r2).await;
    assert!(gc_after >= gc_before + replaced.len() as u64, "metrics: {gc_before} -> {gc_after}");
    let names = block_names(&store, "gamma").await;
    for base in [r1, r2] {
        wait_status(&http, &format!("{base}/api/scenes/gamma/blocks/{}", names[0]), 200, follow).await;
        fetch_blocks(&http, base, "gamma", &names).await;
    }
    // Control: the other scenes lost nothing.
    assert_eq!(objects(s3.as_ref(), "delta").await.len(), beta_objects.len() + 1, "delta: + scene.json");
    fetch_blocks(&http, r2, "delta", &block_names(&store, "delta").await).await;

    // --- the periodic collector ------------------------------------------------------------
    let deadline = Instant::now() + Duration::from_secs(30);
    while !objects(s3.as_ref(), "orphan").await.is_empty() {
        assert!(Instant::now() < deadline, "the periodic collector never removed {orphan}");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    eprintln!("the orphan pack was gone {:.1} s after it was put", orphan_put.elapsed().as_secs_f64());
    eprintln!("{:.1} s: all checked", started.elapsed().as_secs_f64());
}
