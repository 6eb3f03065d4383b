//! Builds on the cluster of `scripts/cluster.sh`: two `serve --store s3://… --coordinator
//! postgres://…` replicas share a real PostgreSQL (leases, tus state) and three Garage nodes (the
//! scenes and the upload's bytes). Against the real processes:
//!
//! - an upload started on one replica, cut, and resumed on the other completes byte-identical;
//! - every upload is built exactly once however many replicas poll for work;
//! - a builder SIGKILLed while it publishes leaves no replica listing a half-published scene, and
//!   the other replica takes the job over after the lease and publishes it.

mod common;

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use base64::Engine;
use futures_util::StreamExt;
use object_store::ObjectStore;
use serde_json::Value;

use common::cluster::{
    Cluster, check_identical, koala, local_blocks_uploaded, object_names, sigkill, wait_listed,
};
use common::postgres::password_in;
use common::tus;

/// The replicas' lease: a dead builder's job moves after this.
const LEASE_SECS: &str = "3";

fn metadata(pairs: &[(&str, &str)]) -> String {
    let b64 = |v: &str| base64::engine::general_purpose::STANDARD.encode(v);
    pairs.iter().map(|(k, v)| format!("{k} {}", b64(v))).collect::<Vec<_>>().join(",")
}

/// `POST /api/uploads` on `base`; returns the upload's path.
async fn tus_create(http: &reqwest::Client, base: &str, length: usize, id: &str, resolution: &str) -> String {
    let r = http
        .post(format!("{base}/api/uploads"))
        .header("Tus-Resumable", "1.0.0")
        .header("Upload-Length", length.to_string())
        .header(
            "Upload-Metadata",
            metadata(&[("filename", "koala.obj"), ("id", id), ("resolution", resolution)]),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{base}: tus create: {}", r.text().await.unwrap());
    r.headers()["location"].to_str().unwrap().to_string()
}

async fn tus_patch(http: &reqwest::Client, url: &str, offset: u64, body: reqwest::Body) -> reqwest::Response {
    http.patch(url)
        .header("Tus-Resumable", "1.0.0")
        .header("Upload-Offset", offset.to_string())
        .header("Content-Type", "application/offset+octet-stream")
        .body(body)
        .send()
        .await
        .unwrap()
}

async fn tus_offset(http: &reqwest::Client, url: &str) -> u64 {
    let r = http.head(url).header("Tus-Resumable", "1.0.0").send().await.unwrap();
    assert_eq!(r.status(), 200, "HEAD {url}");
    r.headers()["upload-offset"].to_str().unwrap().parse().unwrap()
}

async fn job(http: &reqwest::Client, base: &str, id: &str) -> Value {
    let r = http.get(format!("{base}/api/jobs/{id}")).send().await.unwrap();
    assert_eq!(r.status(), 200, "{base}: job {id}");
    r.json().await.unwrap()
}

/// Polls the job on `base` until it ends; fails with its last state after `within`.
async fn wait_job(http: &reqwest::Client, base: &str, id: &str, within: Duration) -> Value {
    let deadline = Instant::now() + within;
    loop {
        let j = job(http, base, id).await;
        if ["done", "failed", "cancelled"].contains(&j["state"].as_str().unwrap()) {
            return j;
        }
        assert!(Instant::now() < deadline, "job {id} did not end within {within:?}: {j}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// `voxstream_builds_started_total` of one replica.
async fn builds_started(http: &reqwest::Client, base: &str) -> u64 {
    let text = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix("voxstream_builds_started_total "))
        .unwrap_or_else(|| panic!("{base}/metrics has no voxstream_builds_started_total"))
        .trim()
        .parse()
        .unwrap()
}

/// `voxstream serve` on the cluster's bucket with `coordinator` and the password file `pg_env`:
/// must exit non-zero within 5 s; returns its stderr.
fn serve_fails(cluster: &Cluster, coordinator: &str, pg_env: &Path) -> String {
    let started = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_voxstream"))
        .args([
            "serve",
            "--store",
            "s3://voxstream/scenes",
            "--addr",
            "127.0.0.1:0",
            "--coordinator",
            coordinator,
        ])
        .env("VOXSTREAM_S3_ENV_FILE", cluster.get("S3_ENV"))
        .env("VOXSTREAM_PG_ENV_FILE", pg_env)
        .env_remove("PGPASSWORD")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "serve started with --coordinator {coordinator}: {stderr}");
    assert!(started.elapsed() < Duration::from_secs(5), "took {:?}: {stderr}", started.elapsed());
    stderr
}

/// The pid in a job's `builder` (`host/pid/n`).
fn builder_pid(job: &Value) -> String {
    job["builder"].as_str().expect("a running job names its builder").split('/').nth(1).unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_build_each_upload_once_resume_uploads_anywhere_and_take_over_dead_builders() {
    let cluster = Cluster::start_with(&[("CLUSTER_LEASE_SECS", LEASE_SECS)]);
    let http = reqwest::Client::builder().timeout(Duration::from_secs(60)).build().unwrap();
    let replicas = cluster.list("REPLICA_URLS");
    let replica_pids = cluster.list("REPLICA_PIDS");
    let nginx = cluster.get("URL").to_string();
    let mesh = std::fs::read(koala()).unwrap();
    let started = Instant::now();

    // --- Bad coordinator settings fail at start, naming the endpoint and the cause -------------
    let coordinator = cluster.get("COORDINATOR").to_string();
    let password = password_in(&std::fs::read_to_string(cluster.get("PG_ENV")).unwrap());
    let wrong = cluster.dir.path().join("wrong-pg.env");
    std::fs::write(&wrong, "PGPASSWORD=not-the-password\n").unwrap();
    let refused = serve_fails(&cluster, &coordinator, &wrong);
    assert!(
        refused.contains(&coordinator) && refused.contains("password authentication failed"),
        "{refused}"
    );
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let nowhere = format!("postgres://voxstream@127.0.0.1:{closed}/voxstream");
    let unreachable = serve_fails(&cluster, &nowhere, Path::new(cluster.get("PG_ENV")));
    assert!(unreachable.contains(&nowhere) && unreachable.contains("cannot connect"), "{unreachable}");
    let with_password = coordinator.replace("voxstream@", &format!("voxstream:{password}@"));
    let inline = serve_fails(&cluster, &with_password, Path::new(cluster.get("PG_ENV")));
    assert!(inline.contains("PGPASSWORD"), "{inline}");
    for text in [&refused, &unreachable, &inline] {
        assert!(!text.contains(&password), "the password is in a message: {text}");
    }

    // --- Upload moved between replicas --------------------------------------------------------
    // Created on replica 1, half sent there, then a PATCH cut off mid-body (the client's stream
    // fails), then resumed on replica 2 from the offset replica 2 reports.
    let path = tus_create(&http, &replicas[0], mesh.len(), "moved", "256").await;
    let on = |i: usize| format!("{}{path}", replicas[i]);
    let half = mesh.len() / 2;
    let r = tus_patch(&http, &on(0), 0, mesh[..half].to_vec().into()).await;
    assert_eq!(r.status(), 204, "first half on replica 1");
    let sent: Vec<u8> = mesh[half..half + 300_000].to_vec();
    // The bytes go out, then the link drops (a moment later, so they reach the server first).
    let cut = futures_util::stream::once(async move { Ok::<_, std::io::Error>(sent) }).chain(
        futures_util::stream::once(async {
            tokio::time::sleep(Duration::from_millis(500)).await;
            Err(std::io::Error::new(std::io::ErrorKind::ConnectionReset, "the client's link dropped"))
        }),
    );
    let cut_request = http
        .patch(on(0))
        .header("Tus-Resumable", "1.0.0")
        .header("Upload-Offset", half.to_string())
        .header("Content-Type", "application/offset+octet-stream")
        .body(reqwest::Body::wrap_stream(cut))
        .send()
        .await;
    assert!(cut_request.is_err() || cut_request.unwrap().status() != 204, "the cut PATCH cannot succeed");
    // The cut PATCH's kept bytes are committed once its handler sees the cut: wait for that.
    let mut resume_at = tus_offset(&http, &on(1)).await as usize;
    let deadline = Instant::now() + Duration::from_secs(10);
    while resume_at == half && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(100)).await;
        resume_at = tus_offset(&http, &on(1)).await as usize;
    }
    eprintln!("moved upload: {half} bytes sent whole, cut PATCH kept {} more", resume_at - half);
    assert!(
        resume_at > half && resume_at <= half + 300_000,
        "replica 2 reports offset {resume_at}: the cut PATCH's bytes"
    );
    // Control: replica 2 knows the true offset (a stale one is refused with it).
    let stale = tus_patch(&http, &on(1), 0, mesh[..10].to_vec().into()).await;
    assert_eq!(stale.status(), 409, "a PATCH at a stale offset");
    assert_eq!(stale.headers()["upload-offset"].to_str().unwrap(), resume_at.to_string());
    let r = tus_patch(&http, &on(1), resume_at as u64, mesh[resume_at..].to_vec().into()).await;
    assert_eq!(r.status(), 204, "rest on replica 2");
    let moved_job = r.headers()["voxstream-job"].to_str().unwrap().to_string();

    // The official clients, cut after their first 1 MiB chunk on replica 1 (the process exits) and
    // resumed by a new process on replica 2 from the upload URL alone.
    let koala_path = koala();
    let koala_arg = koala_path.to_str().unwrap();
    let chunk = (1u64 << 20).to_string();
    let mut jobs = vec![moved_job.clone()];
    for (client, scene) in [("tuspy", "py-moved"), ("tus-js-client", "js-moved")] {
        let create_args =
            ["create", &format!("{}/api/uploads", replicas[0]), koala_arg, "no-token", scene, &chunk];
        let url = tus::run(
            if client == "tuspy" { tus::tuspy(&create_args) } else { tus::tus_js(&create_args) },
            client,
        );
        let on_replica_2 = url.replacen(&replicas[0], &replicas[1], 1);
        assert_ne!(url, on_replica_2, "{client}: upload URL {url}");
        let resumed = tus::run(
            if client == "tuspy" {
                tus::tuspy(&[
                    "resume",
                    &format!("{}/api/uploads", replicas[1]),
                    &on_replica_2,
                    koala_arg,
                    "no-token",
                    &chunk,
                ])
            } else {
                tus::tus_js(&["resume", &on_replica_2, koala_arg, "no-token", &chunk])
            },
            client,
        );
        assert_eq!(
            resumed,
            format!("{chunk} {}", mesh.len()),
            "{client} resumed on replica 2 from the first chunk"
        );
        let r = http.head(&on_replica_2).header("Tus-Resumable", "1.0.0").send().await.unwrap();
        jobs.push(r.headers()["voxstream-job"].to_str().unwrap().to_string());
    }

    // Two more uploads, plain POSTs, one to each replica: several jobs for two polling builders.
    for (i, name) in ["once-a", "once-b"].iter().enumerate() {
        let r = http
            .post(format!("{}/api/scenes?filename=koala.obj&id={name}&resolution=64", replicas[i]))
            .body(mesh.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 202, "POST {name}");
        jobs.push(r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string());
    }
    let mut ended = Vec::new();
    for id in &jobs {
        // Read through the other replica and nginx: the job is the coordinator's, not a replica's.
        ended.push(wait_job(&http, &replicas[1], id, Duration::from_secs(180)).await);
    }
    for j in &ended {
        assert_eq!(j["state"], "done", "{j}");
        assert_eq!(j["attempts"], 1, "built once: {j}");
    }
    // Uploads moved between replicas (by hand, tuspy, tus-js-client): the input assembled from
    // parts written on two replicas is the file uploaded.
    for moved in &ended[..3] {
        assert_eq!(moved["input_bytes"], mesh.len() as u64, "{moved}");
        assert_eq!(moved["input_blake3"].as_str().unwrap(), blake3::hash(&mesh).to_hex().as_str(), "{moved}");
    }
    // Exactly once: the replicas together started one build per job.
    let total = builds_started(&http, &replicas[0]).await + builds_started(&http, &replicas[1]).await;
    assert_eq!(total, jobs.len() as u64, "builds started by both replicas for {} jobs", jobs.len());
    let (manifest, blocks) = local_blocks_uploaded("moved", "256");
    for base in replicas.iter().chain([&nginx]) {
        wait_listed(&http, base, "moved").await;
        check_identical(&http, base, &manifest, &blocks).await;
    }
    // The upload's parts are gone with its job.
    let store = cluster.bucket();
    let leftovers = object_names(store.as_ref(), &format!("scenes/.uploads/{moved_job}")).await;
    assert!(leftovers.is_empty(), "upload parts left behind: {leftovers:?}");
    eprintln!("moved upload and exactly-once: {:.1} s", started.elapsed().as_secs_f64());

    // --- Builder killed mid-publish -------------------------------------------------------------
    let takeover_started = Instant::now();
    // At 2048 the koala is 2,417 blocks: its first pack of 512 items closes a fifth of the way
    // in, so the kill lands mid-publish (at 1024, 558 blocks, it closed near the end and the
    // manifest sometimes came first).
    let path = tus_create(&http, &replicas[0], mesh.len(), "takeover", "2048").await;
    let r = tus_patch(&http, &format!("{}{path}", replicas[0]), 0, mesh.clone().into()).await;
    assert_eq!(r.status(), 204);
    let job_id = r.headers()["voxstream-job"].to_str().unwrap().to_string();
    // Wait until the builder has uploaded packs but not the manifest: mid-publish.
    let packs = "scenes/takeover/packs";
    let manifest_path = object_store::path::Path::from("scenes/takeover/manifest.json");
    let deadline = Instant::now() + Duration::from_secs(120);
    let (builder, packs_seen) = loop {
        let j = job(&http, &nginx, &job_id).await;
        if j["state"] == "running" {
            let n = object_names(store.as_ref(), packs).await.len();
            if n > 0 {
                break (j, n);
            }
        }
        assert!(j["state"] == "queued" || j["state"] == "running", "the build ended before the kill: {j}");
        assert!(Instant::now() < deadline, "the build never reached publishing: {j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let pid = builder_pid(&builder);
    let killed = replica_pids.iter().position(|p| *p == pid).expect("the builder is one of the replicas");
    sigkill(&pid);
    let killed_at = Instant::now();
    let survivor = &replicas[1 - killed];
    // Control: the bucket held part of the scene when its builder died, and no manifest.
    assert!(store.head(&manifest_path).await.is_err(), "the manifest was already written: not mid-publish");
    eprintln!("killed replica {} (pid {pid}) with {packs_seen} packs uploaded", killed + 1);

    // No replica lists the scene until it is whole; the survivor takes the job over and finishes.
    let (local_manifest, local_blocks_2048) = local_blocks_uploaded("takeover", "2048");
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let mut listed = None;
        for base in [survivor, &nginx] {
            let r = http.get(format!("{base}/api/scenes/takeover")).send().await.unwrap();
            match r.status().as_u16() {
                200 => listed = Some(base.clone()),
                404 => {}
                s => panic!("{base}: GET /api/scenes/takeover answered {s}"),
            }
        }
        if let Some(base) = listed {
            eprintln!(
                "takeover: listed by {base} {:.1} s after the kill; checking its {} blocks",
                killed_at.elapsed().as_secs_f64(),
                local_blocks_2048.len()
            );
            // Listed means whole: every block, as the local build.
            check_identical(&http, &base, &local_manifest, &local_blocks_2048).await;
            break;
        }
        let j = job(&http, survivor, &job_id).await;
        assert!(j["state"] != "failed" && j["state"] != "cancelled", "the job ended without the scene: {j}");
        assert!(Instant::now() < deadline, "the scene never appeared: {j}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!("takeover: every block checked {:.1} s after the kill", killed_at.elapsed().as_secs_f64());
    let j = wait_job(&http, survivor, &job_id, Duration::from_secs(30)).await;
    assert_eq!(j["state"], "done", "{j}");
    // The count that read 1 above reads 2 here: a second build is seen when there is one.
    assert_eq!(j["attempts"], 2, "taken over once: {j}");
    assert_ne!(builder_pid(&j), pid, "finished by the survivor: {j}");
    // The killed replica comes back and serves it too.
    cluster.restart("replica", killed + 1);
    wait_listed(&http, &replicas[killed], "takeover").await;
    eprintln!("builder killed mid-publish and taken over: {:.1} s", takeover_started.elapsed().as_secs_f64());
}
