//! The official tus clients against `voxstream serve` as a process, as a new user would use them:
//! tuspy (Python, PyPI `tuspy`, from the tools venv of `scripts/schemathesis.sh`) and tus-js-client 4
//! (Node, npm `tus-js-client`, from `tests/browser/node_modules`). Each uploads `data/koala.obj` in
//! 1 MiB chunks, is cut after the first chunk (the client process exits), and a new process resumes
//! from the upload URL alone; the upload must continue at the stored offset (not from 0) and end in a
//! built scene identical to a local build of the same file.
//!
//! Needs `bash scripts/setup.sh` (it installs both clients); a missing one fails the test with the
//! command to run.

mod common;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::serve::spawn_listening;
use common::tus::{root, run, tus_js, tuspy};

use serde_json::Value;

const TOKEN: &str = "tus-clients-token";
const CHUNK: u64 = 1 << 20;

struct Server {
    child: Child,
    base: String,
    _dir: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn serve() -> Server {
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_voxstream"));
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--token", TOKEN, "--store"])
        .arg(dir.path().join("store"))
        .stderr(Stdio::null());
    let (child, base) = spawn_listening(cmd);
    Server { child, base, _dir: dir }
}

async fn head(http: &reqwest::Client, url: &str) -> reqwest::Response {
    http.head(url).bearer_auth(TOKEN).header("Tus-Resumable", "1.0.0").send().await.unwrap()
}

fn header_u64(resp: &reqwest::Response, name: &str) -> u64 {
    resp.headers()
        .get(name)
        .unwrap_or_else(|| panic!("no {name}: {resp:?}"))
        .to_str()
        .unwrap()
        .parse()
        .unwrap()
}

/// `create` (cut after one chunk), then `resume` in a new process; checks the server's side.
/// `create(base)` and `resume(base, upload_url)` give the client's two commands.
async fn cut_and_resume_with(
    client: &str,
    scene: &str,
    create: impl FnOnce(&str) -> Command,
    resume: impl FnOnce(&str, &str) -> Command,
) {
    let mesh = root().join("data/koala.obj");
    let size = std::fs::metadata(&mesh).unwrap().len();
    assert!(size > 2 * CHUNK, "the test mesh must take several chunks");
    let server = serve();
    let http = reqwest::Client::new();

    let url = run(create(&server.base), &format!("{client} create"));
    assert!(url.starts_with(&format!("{}/api/uploads/", server.base)), "{client}: upload URL {url:?}");
    let cut = head(&http, &url).await;
    assert_eq!(cut.status(), 200, "{client}: HEAD after the cut: {cut:?}");
    assert_eq!(header_u64(&cut, "upload-offset"), CHUNK, "{client}: the first chunk is stored, no more");
    assert_eq!(header_u64(&cut, "upload-length"), size);
    assert!(cut.headers().get("voxstream-job").is_none(), "{client}: no job before the upload is complete");

    let resumed = run(resume(&server.base, &url), &format!("{client} resume"));
    let (from, to) = resumed.split_once(' ').unwrap_or_else(|| panic!("{client} resume printed {resumed:?}"));
    assert_eq!(from.parse::<u64>().unwrap(), CHUNK, "{client} resumed from the stored offset, not from 0");
    assert_eq!(to.parse::<u64>().unwrap(), size);

    let done = head(&http, &url).await;
    assert_eq!(header_u64(&done, "upload-offset"), size);
    let job_id =
        done.headers().get("voxstream-job").expect("the complete upload names its job").to_str().unwrap();
    let deadline = Instant::now() + Duration::from_secs(180);
    let job: Value = loop {
        let job: Value = http
            .get(format!("{}/api/jobs/{job_id}", server.base))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        match job["state"].as_str() {
            Some("done") => break job,
            Some("failed" | "cancelled") => panic!("{client}: the build did not finish: {job}"),
            _ if Instant::now() > deadline => panic!("{client}: the build took over 180 s: {job}"),
            _ => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    assert_eq!(job["input_bytes"], size, "{client}: {job}");
    assert_eq!(job["scene_id"], scene);

    // The same scene as a local build of the same bytes.
    let local = tempfile::tempdir().unwrap();
    let status = Command::new(env!("CARGO_BIN_EXE_voxstream"))
        .arg("build")
        .arg(&mesh)
        .arg("--out")
        .arg(local.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let manifest: Value =
        serde_json::from_slice(&std::fs::read(local.path().join("koala/manifest.json")).unwrap()).unwrap();
    let meta: Value =
        http.get(format!("{}/api/scenes/{scene}", server.base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(meta["triangles"], manifest["source"]["triangles"], "{client}: {meta}");
    assert_eq!(meta["voxels"], manifest["levels"][0]["voxels"], "{client}: {meta}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tuspy_is_cut_and_resumes_from_the_upload_url() {
    let mesh = root().join("data/koala.obj");
    let (mesh, chunk) = (mesh.to_str().unwrap(), CHUNK.to_string());
    cut_and_resume_with(
        "tuspy",
        "py-koala",
        |base| tuspy(&["create", &format!("{base}/api/uploads"), mesh, TOKEN, "py-koala", &chunk]),
        |base, url| tuspy(&["resume", &format!("{base}/api/uploads"), url, mesh, TOKEN, &chunk]),
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tus_js_client_is_cut_and_resumes_from_the_upload_url() {
    let mesh = root().join("data/koala.obj");
    let (mesh, chunk) = (mesh.to_str().unwrap(), CHUNK.to_string());
    cut_and_resume_with(
        "tus-js-client",
        "js-koala",
        |base| tus_js(&["create", &format!("{base}/api/uploads"), mesh, TOKEN, "js-koala", &chunk]),
        |_, url| tus_js(&["resume", url, mesh, TOKEN, &chunk]),
    )
    .await;
}
