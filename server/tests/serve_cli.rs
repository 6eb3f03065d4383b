//! `voxstream serve` as a process: it refuses to open writing to the network
//! without a token, and SIGTERM shuts it down gracefully (open SSE streams
//! end, a running build is left queued and finishes after the next start).

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::serve::spawn_listening;

const TOKEN: &str = "serve-cli-token";

#[test]
fn refuses_open_writing_beyond_loopback() {
    let dir = tempfile::tempdir().unwrap();
    for (args, needle) in [
        (vec!["--addr", "0.0.0.0:0"], "refusing to serve on 0.0.0.0:0"),
        (vec!["--addr", "[::]:0", "--token", ""], "refusing"),
        (vec!["--protect-read"], "--protect-read needs --token"),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_voxstream"))
            .arg("serve")
            .args(&args)
            .arg("--store")
            .arg(dir.path())
            .env_remove("VOXSTREAM_TOKEN")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} started");
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_ends_event_streams_and_keeps_the_build_for_the_next_start() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let start = || {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_voxstream"));
        cmd.args(["serve", "--addr", "127.0.0.1:0", "--token", TOKEN, "--store"])
            .arg(&store)
            .stderr(Stdio::null());
        spawn_listening(cmd)
    };
    let (mut child, base) = start();
    let http = reqwest::Client::new();
    let koala = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../data/koala.obj")).unwrap();
    let job: serde_json::Value = http
        .post(format!("{base}/api/scenes?filename=koala.obj&resolution=1024"))
        .bearer_auth(TOKEN)
        .body(koala)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    let mut events = http.get(format!("{base}/api/jobs/{id}/events")).send().await.unwrap();
    assert!(events.chunk().await.unwrap().is_some());

    let sent = Instant::now();
    let term = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(term.success());
    let ended = tokio::time::timeout(Duration::from_secs(15), async {
        while let Ok(Some(_)) = events.chunk().await {}
    })
    .await;
    assert!(ended.is_ok(), "the event stream ended at shutdown");
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(sent.elapsed() < Duration::from_secs(20), "the server did not exit after SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "graceful exit: {status}");
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(store.join(format!(".jobs/{id}.json"))).unwrap()).unwrap();
    assert_eq!(record["state"], "queued", "an interrupted build resumes: {record}");

    let (mut child, base) = start();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let j: serde_json::Value =
            http.get(format!("{base}/api/jobs/{id}")).send().await.unwrap().json().await.unwrap();
        if j["state"] == "done" {
            break;
        }
        assert!(j["state"] == "queued" || j["state"] == "running", "{j}");
        assert!(Instant::now() < deadline, "the resumed build did not finish");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(http.get(format!("{base}/api/scenes/koala")).send().await.unwrap().status(), 200);
    child.kill().unwrap();
    child.wait().unwrap();
}
