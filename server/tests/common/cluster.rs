//! The local cluster of `scripts/cluster.sh` for tests: start it in a temp folder, read its
//! `cluster.env`, build into its bucket, kill and restart parts, and compare what replicas serve
//! with a local build. Dropping it stops every process the script started.

#![allow(dead_code)] // each test binary uses part of the common helpers

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::{StreamExt, TryStreamExt};
use object_store::ObjectStore;
use object_store::aws::AmazonS3Builder;
use voxstream_format::Manifest;

pub struct Cluster {
    pub dir: tempfile::TempDir,
    env: HashMap<String, String>,
}

pub fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/cluster.sh")
}

pub fn koala() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj")
}

fn run_script(args: &[&str], env: &[(&str, &str)]) -> String {
    let out = Command::new("bash")
        .arg(script())
        .args(args)
        .envs(env.iter().copied())
        .env("VOXSTREAM_BIN", env!("CARGO_BIN_EXE_voxstream"))
        .output()
        .expect("running scripts/cluster.sh");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "scripts/cluster.sh {args:?} failed:\n{text}");
    text
}

impl Cluster {
    pub fn start() -> Cluster {
        Self::start_with(&[])
    }

    /// Starts it with extra environment for the script (`CLUSTER_LEASE_SECS`, …).
    pub fn start_with(env: &[(&str, &str)]) -> Cluster {
        let dir = tempfile::tempdir().unwrap();
        run_script(&["start", dir.path().to_str().unwrap()], env);
        let env = std::fs::read_to_string(dir.path().join("cluster.env"))
            .unwrap()
            .lines()
            .filter_map(|l| l.split_once('='))
            .map(|(k, v)| (k.to_string(), v.trim_matches('"').to_string()))
            .collect();
        Cluster { dir, env }
    }

    /// The cluster's bucket, as a test reads it (credentials from its s3.env).
    pub fn bucket(&self) -> Arc<dyn ObjectStore> {
        let text = std::fs::read_to_string(self.get("S3_ENV")).unwrap();
        let mut builder = AmazonS3Builder::new().with_bucket_name("voxstream").with_allow_http(true);
        for (k, v) in text.lines().filter_map(|l| l.split_once('=')) {
            builder = match k {
                "AWS_ENDPOINT_URL" => builder.with_endpoint(v),
                "AWS_REGION" => builder.with_region(v),
                "AWS_ACCESS_KEY_ID" => builder.with_access_key_id(v),
                "AWS_SECRET_ACCESS_KEY" => builder.with_secret_access_key(v),
                _ => builder,
            };
        }
        Arc::new(builder.build().unwrap())
    }

    pub fn get(&self, key: &str) -> &str {
        &self.env[key]
    }

    pub fn list(&self, key: &str) -> Vec<String> {
        self.get(key).split_whitespace().map(String::from).collect()
    }

    pub fn build(&self, name: &str, resolution: &str) {
        run_script(
            &[
                "build",
                koala().to_str().unwrap(),
                self.dir.path().to_str().unwrap(),
                "--name",
                name,
                "--resolution",
                resolution,
            ],
            &[],
        );
    }

    pub fn restart(&self, what: &str, i: usize) -> u32 {
        run_script(&["restart", what, &i.to_string(), self.dir.path().to_str().unwrap()], &[])
            .lines()
            .last()
            .and_then(|l| l.trim().parse().ok())
            .expect("restart prints the new pid")
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash").arg(script()).arg("stop").arg(self.dir.path()).output();
    }
}

/// Names of the objects under `prefix`, in listing order.
pub async fn object_names(store: &dyn ObjectStore, prefix: &str) -> Vec<String> {
    let prefix = object_store::path::Path::from(prefix);
    store.list(Some(&prefix)).map_ok(|m| m.location.to_string()).try_collect().await.unwrap()
}

pub fn sigkill(pid: &str) {
    let status = Command::new("kill").args(["-KILL", pid]).status().unwrap();
    assert!(status.success(), "kill -KILL {pid}");
}

/// Every block of scene `id` built locally at `resolution`: its URL path and bytes.
pub fn local_blocks(id: &str, resolution: &str) -> (Manifest, Vec<(String, Vec<u8>)>) {
    local_blocks_of(&koala(), id, resolution)
}

/// The same for the koala uploaded as scene `id`: a server names an upload's input after its
/// scene (`<id>.obj`), and the manifest records that name.
pub fn local_blocks_uploaded(id: &str, resolution: &str) -> (Manifest, Vec<(String, Vec<u8>)>) {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join(format!("{id}.obj"));
    std::fs::copy(koala(), &input).unwrap();
    local_blocks_of(&input, id, resolution)
}

fn local_blocks_of(mesh: &Path, id: &str, resolution: &str) -> (Manifest, Vec<(String, Vec<u8>)>) {
    let store = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_voxstream"))
        .args(["build", mesh.to_str().unwrap(), "--out", store.path().to_str().unwrap()])
        .args(["--name", id, "--resolution", resolution])
        .output()
        .unwrap();
    assert!(out.status.success(), "local build: {}", String::from_utf8_lossy(&out.stderr));
    let scene = voxstream::store::open_scene(store.path(), id).unwrap();
    let blocks = scene
        .blocks()
        .into_iter()
        .map(|e| (format!("/api/scenes/{id}/blocks/{}.{}", e.key, e.hash), scene.read_block(&e).unwrap()))
        .collect();
    let manifest = scene.manifest;
    (manifest, blocks)
}

pub async fn wait_listed(http: &reqwest::Client, base: &str, id: &str) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(r) = http.get(format!("{base}/api/scenes/{id}")).send().await {
            if r.status() == 200 {
                return;
            }
        }
        assert!(Instant::now() < deadline, "{base} never listed scene {id}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Fetches every block from `base` and checks it against the local build; returns the count.
pub async fn check_identical(
    http: &reqwest::Client,
    base: &str,
    manifest: &Manifest,
    blocks: &[(String, Vec<u8>)],
) {
    let id = &manifest.name;
    let served = http.get(format!("{base}/api/scenes/{id}/manifest")).send().await.unwrap();
    assert_eq!(served.status(), 200, "{base}: manifest");
    assert_eq!(
        &Manifest::from_json(&served.bytes().await.unwrap()).unwrap(),
        manifest,
        "{base}: manifest differs"
    );
    // A few GETs at once, as a viewer makes them.
    futures_util::stream::iter(blocks)
        .for_each_concurrent(8, |(path, bytes)| async move {
            let r = http.get(format!("{base}{path}")).send().await.unwrap();
            assert_eq!(r.status(), 200, "{base}{path}");
            assert!(
                r.bytes().await.unwrap() == bytes.as_slice(),
                "{base}{path}: bytes differ from the local build"
            );
        })
        .await;
}
