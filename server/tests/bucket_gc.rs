//! Garbage collection of a bucket against a real Garage and a real PostgreSQL
//! (`scripts/cluster.sh postgres start`), driven through the library as a replica drives it:
//!
//! - a replaced scene's old packs are removed once both they and the new manifest are older than
//!   the grace period, and the new scene still reads every block (each checked against its hash);
//! - a failed build's orphan packs (packs uploaded, no manifest) are removed, and so are the parts
//!   of an upload that has no record any more;
//! - controls: within the grace period (of the objects, or of the replacing manifest), with a
//!   build of the scene queued or running, while another replica holds the collector's lock, or
//!   while another replica edits the scene (holds its lock), nothing of the scene is removed; a
//!   live upload's parts stay.

mod common;

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use object_store::ObjectStore;
use object_store::path::Path as ObjectPath;
use voxstream::bucket_store::BucketStore;
use voxstream::coordinator::{Coordinator, SceneLockError};
use voxstream::gc::{GcMetrics, collect};
use voxstream::objstore::Bucket;
use voxstream_format::Manifest;
use voxstream_format::hierarchy::pack_path;

use common::cluster::object_names;
use common::garage::{Garage, koala, voxstream_with};
use common::postgres::{Postgres, queued_job};

/// `voxstream build koala --out s3://gcbucket/scenes --name <id> --resolution <r>` (a real build).
fn build(garage: &Garage, id: &str, resolution: u32) {
    let out = voxstream_with(Some(garage), &[])
        .args(["build", koala().to_str().unwrap(), "--out", "s3://gcbucket/scenes", "--name", id])
        .args(["--resolution", &resolution.to_string()])
        .output()
        .unwrap();
    assert!(out.status.success(), "build {id}: {}", String::from_utf8_lossy(&out.stderr));
}

async fn objects(store: &dyn ObjectStore, prefix: &str) -> BTreeSet<String> {
    object_names(store, prefix).await.into_iter().collect()
}

/// The test's view of scenes in `gcbucket/scenes`, with a cache of its own.
fn bucket_store(garage: &Garage, client: &Arc<dyn ObjectStore>) -> BucketStore {
    let bucket = Bucket {
        store: client.clone(),
        bucket: "gcbucket".into(),
        prefix: "scenes".into(),
        endpoint: garage.endpoint.clone(),
    };
    BucketStore::new(bucket, 64 << 20)
}

/// The packs scene `id`'s current manifest names (every page of its hierarchy read).
async fn referenced_packs(bucket: &BucketStore, id: &str) -> BTreeSet<String> {
    let manifest = Manifest::from_json(&bucket.manifest(id).await.unwrap().unwrap()).unwrap();
    let index = bucket.load_index(id, &manifest).await.unwrap();
    assert!(index.is_complete());
    index.packs().map(|p| format!("scenes/{id}/{}", pack_path(&p.hash))).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn collector_removes_replaced_and_orphan_packs_after_the_grace_period_only() {
    let started = Instant::now();
    let garage = Garage::start();
    garage.create_bucket("gcbucket");
    let pg = Postgres::start();
    // SAFETY: this binary's only test, set before any thread reads the environment.
    unsafe { std::env::set_var("VOXSTREAM_PG_ENV_FILE", pg.password_file()) };
    let deadline = Duration::from_secs(5);
    let a = Coordinator::connect(&pg.url, Duration::from_secs(30), deadline).await.unwrap();
    let b = Coordinator::connect(&pg.url, Duration::from_secs(30), deadline).await.unwrap();
    let sql = pg.client().await;
    let client = garage.client("gcbucket");
    let store = bucket_store(&garage, &client);
    let metrics = GcMetrics::default();

    // koala v1; a failed build's packs (built, then its manifest removed: a build killed before
    // publishing leaves exactly that); a dead upload's part and a live upload's part.
    build(&garage, "koala", 64);
    let v1 = referenced_packs(&store, "koala").await;
    build(&garage, "orphan", 32);
    client.delete(&ObjectPath::from("scenes/orphan/manifest.json")).await.unwrap();
    let orphan = objects(client.as_ref(), "scenes/orphan").await;
    assert!(orphan.iter().any(|o| o.contains("/packs/")), "{orphan:?}");
    // A long build outside the cluster: an old pack, kept by its live marker (put again below).
    let cli_pack = format!("scenes/cli/{}", pack_path(&"0e".repeat(32)));
    let cli_marker = "scenes/cli/building.json";
    client.put(&ObjectPath::from(cli_pack.as_str()), vec![9u8; 500].into()).await.unwrap();
    client.put(&ObjectPath::from(cli_marker), b"{}".to_vec().into()).await.unwrap();
    let dead_part = "scenes/.uploads/00000000000000d1/00000000000000000000-0000000000000001";
    let live_part = "scenes/.uploads/00000000000000e2/00000000000000000000-0000000000000002";
    for part in [dead_part, live_part] {
        client.put(&ObjectPath::from(part), vec![7u8; 1000].into()).await.unwrap();
    }
    sql.execute(
        "INSERT INTO voxstream_uploads (id, record, created_at) VALUES ('00000000000000e2', '{}', 1)",
        &[],
    )
    .await
    .unwrap();
    // The old objects age past the grace period before the scene is replaced.
    let grace = Duration::from_secs(5);
    tokio::time::sleep(grace + Duration::from_millis(500)).await;
    build(&garage, "koala", 128);
    let v2 = referenced_packs(&store, "koala").await;
    let replaced: BTreeSet<String> = v1.difference(&v2).cloned().collect();
    assert!(!replaced.is_empty(), "the rebuild at another resolution names other packs");
    let before = objects(client.as_ref(), "scenes").await;
    for p in v1.iter().chain(&v2) {
        assert!(before.contains(p), "{p} is in the bucket");
    }

    // Control 1: a grace period longer than every object's age removes nothing.
    let r = collect(&store, &a, Duration::from_secs(3600), None, &metrics).await.unwrap().unwrap();
    assert_eq!((r.objects, r.bytes), (0, 0), "{r:?}");
    assert_eq!(objects(client.as_ref(), "scenes").await, before);

    // Control 2: another replica holds the collector's lock: this pass does not run.
    let inner = b.with_gc_lock(collect(&store, &a, Duration::ZERO, None, &metrics)).await.unwrap();
    assert!(matches!(inner, Some(Ok(None))), "a second collector ran: {inner:?}");
    assert_eq!(objects(client.as_ref(), "scenes").await, before);

    // Scene locks: while one replica edits koala (a rename or delete), another's edit or
    // collection of it is refused at once, and nothing ran.
    let inner =
        a.with_scenes_locked(&["koala"], true, b.with_scenes_locked(&["koala"], false, async {})).await;
    assert!(matches!(inner, Ok(Err(SceneLockError::Busy(ref id))) if id == "koala"), "{inner:?}");
    let r = a
        .with_scenes_locked(&["koala"], true, collect(&store, &b, Duration::ZERO, Some("koala"), &metrics))
        .await;
    assert!(matches!(r, Ok(Ok(Some(ref r))) if r.objects == 0 && r.skipped == ["koala"]), "{r:?}");
    assert_eq!(objects(client.as_ref(), "scenes").await, before);

    // Control 3: the old packs are older than the grace period, but the manifest that replaced
    // them is not (a replica may still serve the previous one): kept. A build of `orphan` is
    // queued: nothing of it is removed. The dead upload's part goes; the live upload's stays.
    sql.execute(
        "INSERT INTO voxstream_jobs (id, scene_id, state, created_at, job) VALUES ($1, $2, 'queued', 1, $3)",
        &[
            &"00000000000000f1",
            &"orphan",
            &serde_json::to_string(&queued_job("00000000000000f1", "orphan")).unwrap(),
        ],
    )
    .await
    .unwrap();
    let r = collect(&store, &a, grace, None, &metrics).await.unwrap().unwrap();
    assert!(r.skipped.contains(&"orphan".to_string()), "{r:?}");
    assert!(r.skipped.contains(&"cli".to_string()), "the live marker keeps the build's id: {r:?}");
    assert_eq!((r.objects, r.bytes), (1, 1000), "only the dead upload's part: {r:?}");
    let after = objects(client.as_ref(), "scenes").await;
    let expected: BTreeSet<String> = before.iter().filter(|o| *o != dead_part).cloned().collect();
    assert_eq!(after, expected);
    assert!(after.contains(live_part));

    // Control 4: once the manifest is old enough, a build of koala running still protects it.
    tokio::time::sleep(grace + Duration::from_millis(500)).await;
    sql.execute(
        "INSERT INTO voxstream_jobs (id, scene_id, state, created_at, job, owner, lease_until)
         VALUES ($1, $2, 'running', 1, $3, 'elsewhere', now() + interval '1 hour')",
        &[
            &"00000000000000f2",
            &"koala",
            &serde_json::to_string(&queued_job("00000000000000f2", "koala")).unwrap(),
        ],
    )
    .await
    .unwrap();
    let r = collect(&store, &a, grace, None, &metrics).await.unwrap().unwrap();
    assert_eq!((r.objects, r.skipped.len()), (0, 3), "{r:?}");
    assert_eq!(objects(client.as_ref(), "scenes").await, expected);

    // The builds end: the replaced packs and the orphan's objects go, nothing else.
    sql.execute("UPDATE voxstream_jobs SET state = 'failed'", &[]).await.unwrap();
    let r = collect(&store, &a, grace, None, &metrics).await.unwrap().unwrap();
    let removed: BTreeSet<String> =
        expected.difference(&objects(client.as_ref(), "scenes").await).cloned().collect();
    let wanted: BTreeSet<String> = replaced.union(&orphan).cloned().collect();
    assert_eq!(removed, wanted);
    assert_eq!(r.objects as usize, wanted.len(), "{r:?}");
    assert_eq!(r.skipped, ["cli"], "{r:?}");
    assert_eq!(metrics.objects.get(), 1 + wanted.len() as u64);
    assert_eq!(metrics.bytes.get(), 1000 + r.bytes);
    let left = objects(client.as_ref(), "scenes/koala").await;
    let packs_left: BTreeSet<String> = left.iter().filter(|o| o.contains("/packs/")).cloned().collect();
    assert_eq!(packs_left, v2, "exactly the new manifest's packs remain");
    assert!(objects(client.as_ref(), "scenes/orphan").await.is_empty());
    assert!(objects(client.as_ref(), "scenes/.uploads").await.contains(live_part));

    // The new scene reads every block, each checked against its hash, from a cold cache.
    let fresh = bucket_store(&garage, &client);
    let manifest = Manifest::from_json(&fresh.manifest("koala").await.unwrap().unwrap()).unwrap();
    let index = fresh.load_index("koala", &manifest).await.unwrap();
    let mut read = 0;
    for entry in index.blocks() {
        let bytes = fresh.block("koala", index.pack_range(&entry.key), entry).await.unwrap();
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), entry.hash);
        read += 1;
    }
    assert_eq!(read as u64, manifest.block_count());
    // Control 5: the build outside the cluster ends without a manifest (its marker gone): its
    // pack is garbage now.
    assert!(objects(client.as_ref(), "scenes/cli").await.contains(&cli_pack));
    client.delete(&ObjectPath::from(cli_marker)).await.unwrap();
    let r = collect(&store, &a, grace, None, &metrics).await.unwrap().unwrap();
    assert_eq!((r.objects, r.bytes), (1, 500), "{r:?}");
    assert!(objects(client.as_ref(), "scenes/cli").await.is_empty());
    // A second pass finds nothing more.
    let r = collect(&store, &a, grace, None, &metrics).await.unwrap().unwrap();
    assert_eq!(r.objects, 0, "{r:?}");
    eprintln!(
        "collected {} replaced packs and {} orphan objects; {read} blocks read after; {:.1} s",
        replaced.len(),
        orphan.len(),
        started.elapsed().as_secs_f64()
    );
}
