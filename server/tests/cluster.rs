//! The local cluster of `scripts/cluster.sh` (the topology docker/compose.yaml deploys): three
//! real Garage nodes at replication factor 3, two stateless `voxstream serve --store s3://…`
//! replicas, and nginx in front. Scenes are built into the bucket with `voxstream build --out
//! s3://…` and must come out of every replica and of nginx byte for byte as the same build on a
//! local path does; a replica SIGKILLed under load costs the client no failed GET; a storage node
//! SIGKILLed costs neither reads nor a build.

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use common::cluster::{Cluster, check_identical, local_blocks, sigkill, wait_listed};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cluster_serves_bucket_scenes_through_replica_and_storage_node_failures() {
    let cluster = Cluster::start();
    let http = reqwest::Client::builder().timeout(Duration::from_secs(20)).build().unwrap();
    let nginx = cluster.get("URL").to_string();
    let replicas = cluster.list("REPLICA_URLS");
    let replica_pids = cluster.list("REPLICA_PIDS");
    let garage_pids = cluster.list("GARAGE_PIDS");

    // Round trip: built into the bucket, served by both replicas and nginx as the local build.
    cluster.build("koala", "256");
    let (manifest, blocks) = local_blocks("koala", "256");
    assert!(blocks.len() > 10);
    for base in replicas.iter().chain([&nginx]) {
        wait_listed(&http, base, "koala").await;
        check_identical(&http, base, &manifest, &blocks).await;
    }
    // Control: another resolution is another scene, with other bytes.
    let (other, other_blocks) = local_blocks("koala", "128");
    assert_ne!(other, manifest);
    assert_ne!(other_blocks.len(), blocks.len());

    // Replica killed under load: clients through nginx see no failed GET.
    let stop = Arc::new(AtomicBool::new(false));
    let (ok, failed) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let paths: Arc<Vec<String>> = Arc::new(blocks.iter().map(|(p, _)| p.clone()).collect());
    let mut clients = Vec::new();
    for c in 0..4 {
        let (http, nginx, stop, ok, failed, paths) =
            (http.clone(), nginx.clone(), stop.clone(), ok.clone(), failed.clone(), paths.clone());
        clients.push(tokio::spawn(async move {
            let mut i = c;
            while !stop.load(Ordering::Relaxed) {
                let path = &paths[i % paths.len()];
                i += 1;
                let outcome = match http.get(format!("{nginx}{path}")).send().await {
                    Ok(r) if r.status() == 200 => r.bytes().await.map(|_| ()).map_err(|e| e.to_string()),
                    Ok(r) => Err(format!("HTTP {}", r.status())),
                    Err(e) => Err(e.to_string()),
                };
                match outcome {
                    Ok(()) => ok.fetch_add(1, Ordering::Relaxed),
                    Err(e) => {
                        eprintln!("GET {path}: {e}");
                        failed.fetch_add(1, Ordering::Relaxed)
                    }
                };
            }
        }));
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    let before_kill = ok.load(Ordering::Relaxed);
    sigkill(&replica_pids[0]);
    tokio::time::sleep(Duration::from_secs(3)).await;
    stop.store(true, Ordering::Relaxed);
    for c in clients {
        c.await.unwrap();
    }
    let (served, lost) = (ok.load(Ordering::Relaxed), failed.load(Ordering::Relaxed));
    eprintln!("load through nginx: {served} GETs ok ({before_kill} before the kill), {lost} failed");
    assert!(served > before_kill + 10, "the load stopped after the kill: {served} vs {before_kill}");
    assert_eq!(lost, 0, "GETs failed through nginx while a replica died");
    // Control: the killed replica itself is gone.
    assert!(http.get(format!("{}/healthz", replicas[0])).send().await.is_err(), "replica 1 still answers");
    // It rejoins when restarted.
    cluster.restart("replica", 1);
    let deadline = Instant::now() + Duration::from_secs(30);
    while http.get(format!("{}/healthz", replicas[0])).send().await.is_err() {
        assert!(Instant::now() < deadline, "replica 1 did not come back");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    check_identical(&http, &replicas[0], &manifest, &blocks).await;

    // Storage node killed: with replication factor 3 a build still publishes (quorum 2) and every
    // block of it reads back through both replicas (new, so not in any replica's cache).
    sigkill(&garage_pids[2]);
    cluster.build("koala-after", "128");
    let (manifest2, blocks2) = local_blocks("koala-after", "128");
    for base in replicas.iter().chain([&nginx]) {
        wait_listed(&http, base, "koala-after").await;
        check_identical(&http, base, &manifest2, &blocks2).await;
    }
}
