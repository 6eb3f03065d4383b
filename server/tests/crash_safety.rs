//! Crash safety of the real `voxstream serve` binary: uploads are built while
//! the server is SIGKILLed at random moments, again and again. After every
//! restart each listed scene must be complete (manifest valid, every block
//! decodes and matches its hash), no half-written scene may be visible, and
//! at the end every job has ended: built from its kept upload, or failed with
//! a reason.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use voxstream_format::{Manifest, decode_block};

const TOKEN: &str = "crash-test-token";
const KILLS: usize = 22;
const STALE_MANIFEST: &str = "the served manifest differs from the one on disk";

struct Server {
    child: Child,
    base: String,
}

fn start(store: &Path) -> Server {
    let log = store.with_extension("log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_voxstream"))
        .args(["serve", "--addr", "127.0.0.1:0", "--token", TOKEN, "--resolution", "64"])
        .args(["--build-workers", "2", "--uploads-per-minute", "0", "--store"])
        .arg(store)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let Some(base) = line.trim().strip_prefix("listening on ") else {
        let status = child.wait().unwrap();
        panic!("the server did not start ({status}): {}", std::fs::read_to_string(&log).unwrap_or_default());
    };
    Server { child, base: base.to_string() }
}

fn sphere_obj(path: &Path, n: usize) {
    let mut obj = String::new();
    for i in 0..=n {
        let t = std::f64::consts::PI * i as f64 / n as f64;
        for j in 0..2 * n {
            let p = std::f64::consts::PI * j as f64 / n as f64;
            let r = 1.0 + 0.1 * (5.0 * t).sin() * (3.0 * p).cos();
            obj += &format!("v {} {} {}\n", r * t.sin() * p.cos(), r * t.sin() * p.sin(), r * t.cos());
        }
    }
    let idx = |i: usize, j: usize| i * 2 * n + (j % (2 * n)) + 1;
    for i in 0..n {
        for j in 0..2 * n {
            obj += &format!(
                "f {} {} {}\nf {} {} {}\n",
                idx(i, j),
                idx(i + 1, j),
                idx(i + 1, j + 1),
                idx(i, j),
                idx(i + 1, j + 1),
                idx(i, j + 1)
            );
        }
    }
    std::fs::write(path, obj).unwrap();
}

/// Every listed scene is complete on disk and served as it is on disk.
///
/// The restarted server keeps building while this looks, so a scene may be
/// replaced in the middle of its check: a failure only counts when the scene's
/// manifest did not change around it (else the check is repeated).
async fn check_store(base: &str, store: &Path, http: &reqwest::Client) -> usize {
    let scenes: Vec<serde_json::Value> =
        http.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
    for s in &scenes {
        let id = s["id"].as_str().unwrap();
        let manifest_path = store.join(id).join("manifest.json");
        let mut attempt = 0;
        loop {
            let before = std::fs::read(&manifest_path);
            let result = check_scene(base, store, id, http).await;
            let after = std::fs::read(&manifest_path);
            match result {
                Ok(()) => break,
                Err(e) if attempt < 20 && (before.is_err() || before.ok() != after.ok()) => {
                    eprintln!("scene {id} was replaced during its check ({e}); checking again");
                    attempt += 1;
                }
                // The build renames the scene in and the catalog re-reads it right after (before
                // the replaced scene is removed): between the two, this check can read the new
                // manifest from disk and the previous one from the server. It must catch up.
                Err(e) if attempt < 40 && e.ends_with(STALE_MANIFEST) => {
                    eprintln!("scene {id}: the server has not caught up with a publish yet; checking again");
                    attempt += 1;
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                Err(e) => panic!("{e}"),
            }
        }
    }
    // Directories that are not scenes are the server's own or a build in progress of this process.
    let listed = |name: &str, scenes: &[serde_json::Value]| scenes.iter().any(|s| s["id"] == name);
    for entry in std::fs::read_dir(store).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        let ours = name.starts_with(".tmp-")
            || name.starts_with(".build-")
            || name.starts_with(".old-")
            || name == ".jobs"
            || name == ".uploads";
        if ours || listed(&name, &scenes) {
            continue;
        }
        // Published after the listing above? Then the server lists it now.
        let now: Vec<serde_json::Value> =
            http.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
        assert!(listed(&name, &now), "unexpected entry {name:?} in the store");
    }
    scenes.len()
}

async fn check_scene(base: &str, store: &Path, id: &str, http: &reqwest::Client) -> Result<(), String> {
    let dir = store.join(id);
    let bytes = std::fs::read(dir.join("manifest.json")).map_err(|e| format!("scene {id}: {e}"))?;
    let manifest = Manifest::from_json(&bytes).map_err(|e| format!("scene {id}: {e}"))?;
    // Every page present and intact: a half-published scene would miss some.
    let index =
        voxstream::store::read_scene_index(&dir, &manifest).map_err(|e| format!("scene {id}: {e}"))?;
    let mut blocks: Vec<_> = index.blocks().collect();
    blocks.sort_by_key(|b| b.key);
    if blocks.len() as u64 != manifest.block_count() {
        return Err(format!(
            "scene {id}: pages list {} blocks, levels {}",
            blocks.len(),
            manifest.block_count()
        ));
    }
    for e in &blocks {
        // Its range of its pack (every block is packed).
        let range = index.pack_range(&e.key).ok_or_else(|| format!("scene {id} block {}: no pack", e.key))?;
        let pack = std::fs::read(dir.join(voxstream_format::hierarchy::pack_path(&range.pack.hash)))
            .map_err(|err| format!("scene {id} block {}: {err}", e.key))?;
        if pack.len() as u64 != range.pack.bytes {
            return Err(format!(
                "scene {id} pack {}: {} bytes, its page says {}",
                range.pack.hash,
                pack.len(),
                range.pack.bytes
            ));
        }
        let bytes = pack[range.offset as usize..range.end() as usize].to_vec();
        if blake3::hash(&bytes).to_hex().as_str() != e.hash {
            return Err(format!("scene {id} block {}: hash mismatch", e.key));
        }
        let block = decode_block(&bytes).map_err(|err| format!("scene {id} block {}: {err}", e.key))?;
        if block.key != e.key || block.voxels.len() as u32 != e.voxels {
            return Err(format!("scene {id} block {}: decodes to another block", e.key));
        }
    }
    let served = http.get(format!("{base}/api/scenes/{id}/manifest")).send().await.unwrap();
    let served =
        Manifest::from_json(&served.bytes().await.unwrap()).map_err(|e| format!("scene {id}: {e}"))?;
    if served != manifest {
        return Err(format!("scene {id}: {STALE_MANIFEST}"));
    }
    if let Some(e) = blocks.first() {
        let r = http.get(format!("{base}/api/scenes/{id}/blocks/{}.{}", e.key, e.hash)).send().await.unwrap();
        if r.status() != 200 {
            return Err(format!("scene {id} block {}: HTTP {}", e.key, r.status()));
        }
    }
    Ok(())
}

async fn jobs(base: &str, http: &reqwest::Client) -> Vec<serde_json::Value> {
    // Once more on a request error: a pooled connection the server closed after a 409 (it answers
    // before reading the body) fails the next request sent on it.
    let get = || http.get(format!("{base}/api/jobs")).send();
    let r = match get().await {
        Ok(r) => r,
        Err(e) if e.is_request() => get().await.unwrap(),
        Err(e) => panic!("GET /api/jobs: {e}"),
    };
    r.json().await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_servers_never_show_partial_scenes_and_resume_their_jobs() {
    let seed: u64 =
        std::env::var("CRASH_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or_else(rand::random);
    eprintln!("crash test seed {seed} (rerun with CRASH_SEED={seed})");
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let sphere = dir.path().join("sphere.obj");
    sphere_obj(&sphere, 120);
    let synth = dir.path().join("synth.ply");
    voxstream::synth::write_sphere_ply(&synth, 40_000).unwrap();
    let meshes: Vec<(PathBuf, &str)> = vec![
        (Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj"), "koala.obj"),
        (sphere, "sphere.obj"),
        (synth, "synth.ply"),
    ];
    let bodies: Vec<Vec<u8>> = meshes.iter().map(|(p, _)| std::fs::read(p).unwrap()).collect();
    let ids = ["koala", "sphere", "synth", "alt"];
    let http = reqwest::Client::new();
    let started = Instant::now();
    let mut killed_while_running = 0;
    let mut uploads = 0;

    for round in 0..KILLS {
        let mut server = start(&store);
        let base = server.base.clone();
        check_store(&base, &store, &http).await;
        for _ in 0..rng.random_range(1..=2) {
            let m = rng.random_range(0..meshes.len());
            let id = ids[rng.random_range(0..ids.len())];
            let resolution = [128, 256, 512][rng.random_range(0..3)];
            let resp = http
                .post(format!(
                    "{base}/api/scenes?filename={}&id={id}&replace=true&resolution={resolution}",
                    meshes[m].1
                ))
                .bearer_auth(TOKEN)
                .body(bodies[m].clone())
                .send()
                .await;
            // 409: a resumed job is already building that id. The server says so before reading the
            // body and closes the connection, which the client may see as a broken pipe instead.
            match resp {
                Ok(resp) => {
                    assert!([202, 409].contains(&resp.status().as_u16()), "round {round}: {}", resp.status());
                    uploads += (resp.status() == 202) as usize;
                }
                Err(e) => assert!(e.is_request(), "round {round}: {e}"),
            }
        }
        // Most kills land shortly after a build starts (however fast builds get), the rest at any
        // moment (uploads still arriving, jobs queued, builds publishing).
        if rng.random_range(0..4) < 3 {
            let until = Instant::now() + Duration::from_secs(3);
            while Instant::now() < until && !jobs(&base, &http).await.iter().any(|j| j["state"] == "running")
            {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            tokio::time::sleep(Duration::from_millis(rng.random_range(0..60))).await;
        } else {
            tokio::time::sleep(Duration::from_millis(rng.random_range(0..500))).await;
        }
        if jobs(&base, &http).await.iter().any(|j| j["state"] == "running") {
            killed_while_running += 1;
        }
        server.child.kill().unwrap(); // SIGKILL
        server.child.wait().unwrap();
    }

    // The last start: every job ends, every listed scene is complete.
    let mut server = start(&store);
    let base = server.base.clone();
    let deadline = Instant::now() + Duration::from_secs(60);
    let all = loop {
        let all = jobs(&base, &http).await;
        if all.iter().all(|j| ["done", "failed", "cancelled"].contains(&j["state"].as_str().unwrap())) {
            break all;
        }
        assert!(Instant::now() < deadline, "jobs did not end: {all:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let scenes = check_store(&base, &store, &http).await;
    let done = all.iter().filter(|j| j["state"] == "done").count();
    let resumed = all.iter().filter(|j| j["state"] == "done" && j["attempts"].as_u64().unwrap() > 1).count();
    for j in all.iter().filter(|j| j["state"] == "failed") {
        let e = j["error"].as_str().unwrap();
        assert!(e.contains("interrupted") || e.contains("upload is gone"), "{j}");
    }
    assert_eq!(all.len(), uploads, "every accepted upload has its job");
    assert!(scenes >= 1 && done >= 1, "{scenes} scenes, {done} jobs done");
    assert!(resumed >= 1, "no job was resumed after a kill: {all:?}");
    assert!(killed_while_running >= KILLS / 4, "only {killed_while_running} kills hit a running build");
    assert_eq!(std::fs::read_dir(store.join(".uploads")).unwrap().count(), 0, "ended jobs leave no uploads");
    let no_tmp = std::fs::read_dir(&store)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .all(|name| !name.starts_with(".tmp-") && !name.starts_with(".build-"));
    assert!(no_tmp, "no build temp dir is left once all jobs ended");
    eprintln!(
        "{KILLS} kills ({killed_while_running} during a build), {uploads} uploads, {done} jobs done ({resumed} after a \
         resume), {scenes} scenes, {:.1} s",
        started.elapsed().as_secs_f64()
    );
    server.child.kill().unwrap();
    server.child.wait().unwrap();
}
