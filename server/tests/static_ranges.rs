//! A static publish (`voxstream publish`) is read by the viewer as range requests of its packs:
//! `packs/<hash>.vxp?r=<start>-<end>` with `Range: bytes=<start>-<end>`. Each host a user would
//! put it on is tried with real processes: nginx (Debian's, unprivileged), Garage's S3 website
//! endpoint after `publish --to s3://…`, and a plain static file server (tower-http's
//! `ServeDir`) answer 206 with exactly the bytes of a block, whose blake3 is the one its page
//! states; `python3 -m http.server`, which ignores Range, answers 200 with the whole pack, from
//! which the block is sliced (what the viewer does). Negative control on each: a range one byte
//! off gives bytes whose hash fails.

mod common;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::garage::{self, Garage};
use voxstream_format::hierarchy::{content_hash, pack_path};
use voxstream_format::{BlockEntry, Manifest, PackRange, load_scene_index};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A viewer folder with just what publish needs (the site's scene files are what is tested).
fn viewer_dir(root: &Path) -> PathBuf {
    let dir = root.join("viewer");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("index.html"), "<!doctype html><html><head><title>v</title></head></html>")
        .unwrap();
    dir
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().expect("running voxstream");
    assert!(
        out.status.success(),
        "{cmd:?}: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Blocks to fetch: the first and last of a pack, one in the middle, and the root (last of
/// the last pack), each with its range.
fn sample_blocks(site_scene: &Path) -> Vec<(BlockEntry, PackRange)> {
    let manifest = Manifest::from_json(&std::fs::read(site_scene.join("manifest")).unwrap()).unwrap();
    let index = load_scene_index(&manifest, |r, _| {
        std::fs::read(site_scene.join(format!("pages/{}.{}", r.root, r.hash)))
    })
    .expect("the published pages load");
    let mut by_pack: HashMap<String, Vec<(BlockEntry, PackRange)>> = HashMap::new();
    for e in index.blocks() {
        let r = index.pack_range(&e.key).expect("every block is packed");
        by_pack.entry(r.pack.hash.clone()).or_default().push((e.clone(), r));
    }
    let (_, mut blocks) = by_pack.into_iter().max_by_key(|(_, b)| b.len()).unwrap();
    blocks.sort_by_key(|(_, r)| r.offset);
    let mut picked =
        vec![blocks[0].clone(), blocks[blocks.len() / 2].clone(), blocks[blocks.len() - 1].clone()];
    let root = index.pack_range(&manifest.root.key).unwrap();
    picked.push((manifest.root.clone(), root));
    picked
}

/// GET `url` with `Range: bytes=start-end` (and `Host: host` when given): status and body.
async fn get_range(
    http: &reqwest::Client,
    url: &str,
    host: Option<&str>,
    start: u64,
    end: u64,
) -> (u16, Vec<u8>) {
    let mut req = http.get(url).header("Range", format!("bytes={start}-{end}"));
    if let Some(h) = host {
        req = req.header("Host", h);
    }
    let resp = req.send().await.unwrap_or_else(|e| panic!("GET {url}: {e}"));
    let status = resp.status().as_u16();
    (status, resp.bytes().await.unwrap().to_vec())
}

/// The viewer's rule: a 206 is the block; a 200 is the whole pack, to be sliced.
fn block_from_answer(status: u16, body: Vec<u8>, start: u64, end: u64) -> Vec<u8> {
    match status {
        206 => body,
        200 => body[start as usize..=end as usize].to_vec(),
        s => panic!("HTTP {s}"),
    }
}

/// Fetches every sample block from `base` (the site's root URL) as the viewer does; asserts the
/// status the host gives and that each block's hash checks, and that a range one byte off fails.
async fn check_host(
    name: &str,
    base: &str,
    host: Option<&str>,
    blocks: &[(BlockEntry, PackRange)],
    status: u16,
) {
    let http = reqwest::Client::new();
    for (e, r) in blocks {
        let (start, end) = (r.offset, r.end() - 1);
        let url = format!("{base}/api/scenes/koala/{}?r={start}-{end}", pack_path(&r.pack.hash));
        let (got, body) = get_range(&http, &url, host, start, end).await;
        assert_eq!(got, status, "{name}: {url}");
        if got == 206 {
            assert_eq!(body.len() as u64, r.bytes as u64, "{name}: a 206 holds exactly the range");
        } else {
            assert_eq!(body.len() as u64, r.pack.bytes, "{name}: a 200 holds the whole pack");
        }
        let block = block_from_answer(got, body, start, end);
        assert_eq!(content_hash(&block), e.hash, "{name}: block {} from {url}", e.key);
        assert_eq!(voxstream_format::decode_block(&block).unwrap().key, e.key);
        // Control: one byte later (or earlier, for the pack's last block) is not the block.
        let (s2, e2) = if r.end() < r.pack.bytes { (start + 1, end + 1) } else { (start - 1, end - 1) };
        let url = format!("{base}/api/scenes/koala/{}?r={s2}-{e2}", pack_path(&r.pack.hash));
        let (got, body) = get_range(&http, &url, host, s2, e2).await;
        let shifted = block_from_answer(got, body, s2, e2);
        assert_eq!(shifted.len(), block.len());
        assert_ne!(content_hash(&shifted), e.hash, "{name}: a shifted range passed the hash check");
    }
    eprintln!("{name}: {} blocks read with HTTP {status}, hashes checked", blocks.len());
}

struct Nginx {
    dir: PathBuf,
    conf: PathBuf,
}

impl Nginx {
    /// Debian's nginx serving `root` on `port`, unprivileged: prefix, pid, logs and temp paths
    /// under `dir` (as scripts/cluster.sh runs it).
    fn start(dir: &Path, root: &Path, port: u16) -> Nginx {
        std::fs::create_dir_all(dir.join("tmp")).unwrap();
        let d = dir.display();
        let conf = dir.join("nginx.conf");
        std::fs::write(
            &conf,
            format!(
                "worker_processes 1;\npid {d}/nginx.pid;\nerror_log {d}/error.log warn;\n\
                 events {{ worker_connections 64; }}\nhttp {{\n  access_log {d}/access.log;\n\
                 client_body_temp_path {d}/tmp/body;\n  proxy_temp_path {d}/tmp/proxy;\n\
                 fastcgi_temp_path {d}/tmp/fastcgi;\n  uwsgi_temp_path {d}/tmp/uwsgi;\n\
                 scgi_temp_path {d}/tmp/scgi;\n  server {{\n    listen 127.0.0.1:{port};\n\
                 location / {{ root {}; }}\n  }}\n}}\n",
                root.display()
            ),
        )
        .unwrap();
        let status = Command::new("nginx")
            .arg("-p")
            .arg(dir)
            .arg("-c")
            .arg(&conf)
            .arg("-e")
            .arg(dir.join("error.log"))
            .status()
            .expect("nginx (Debian's nginx-light: bash scripts/cluster.sh tools installs it)");
        assert!(status.success(), "nginx did not start");
        Nginx { dir: dir.to_path_buf(), conf }
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = Command::new("nginx")
            .arg("-p")
            .arg(&self.dir)
            .arg("-c")
            .arg(&self.conf)
            .arg("-e")
            .arg(self.dir.join("error.log"))
            .args(["-s", "quit"])
            .status();
    }
}

struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

async fn wait_listening(port: u16, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while tokio::net::TcpStream::connect(("127.0.0.1", port)).await.is_err() {
        assert!(Instant::now() < deadline, "{what} did not listen on {port}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn published_packs_are_read_by_range_on_every_host() {
    let tmp = tempfile::tempdir().unwrap();
    let store = tmp.path().join("store");
    // At 2048 the koala is several packs, so the site's pages name more than one.
    run(garage::voxstream_with(None, &[])
        .arg("build")
        .arg(garage::koala())
        .args(["--resolution", "2048", "--out"])
        .arg(&store));
    let viewer = viewer_dir(tmp.path());
    let site = tmp.path().join("site");
    let said = run(garage::voxstream_with(None, &[])
        .args(["publish", "koala", "--store"])
        .arg(&store)
        .arg("--to")
        .arg(&site)
        .arg("--web")
        .arg(&viewer));
    eprintln!("{said}");

    // The site holds packs and pages, no per-block file; index.html says it is static.
    let scene = site.join("api/scenes/koala");
    assert!(!scene.join("blocks").exists(), "per-block files were published");
    let packs = std::fs::read_dir(scene.join("packs")).unwrap().count();
    let blocks = sample_blocks(&scene);
    let stored_packs = std::fs::read_dir(store.join("koala/packs")).unwrap().count();
    assert_eq!(packs, stored_packs, "the store's packs, copied as they are");
    assert!(packs > 1, "{packs} pack: the test wants several");
    let index = std::fs::read_to_string(site.join("index.html")).unwrap();
    assert!(index.contains(r#"<meta name="voxstream-static" content="packs">"#), "{index}");
    assert!(index.contains(r#"<meta name="voxstream-scene" content="koala">"#), "{index}");

    // nginx.
    let port = free_port();
    let _nginx = Nginx::start(&tmp.path().join("nginx"), &site, port);
    wait_listening(port, "nginx").await;
    check_host("nginx", &format!("http://127.0.0.1:{port}"), None, &blocks, 206).await;

    // A plain static file server: tower-http's ServeDir, nothing of voxstream's.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let app = axum::Router::new().fallback_service(tower_http::services::ServeDir::new(&site));
    let served = tokio::spawn(async move { axum::serve(listener, app).await });
    check_host("ServeDir", &format!("http://{addr}"), None, &blocks, 206).await;
    served.abort();

    // python3 -m http.server ignores Range: 200 with the whole pack, sliced as the viewer does.
    let port = free_port();
    let _python = KillOnDrop(
        Command::new("python3")
            .args(["-m", "http.server", "--bind", "127.0.0.1", &port.to_string(), "--directory"])
            .arg(&site)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("python3"),
    );
    wait_listening(port, "python3 -m http.server").await;
    check_host("python3 -m http.server", &format!("http://127.0.0.1:{port}"), None, &blocks, 200).await;

    // Garage: publish --to s3://…, then its website endpoint.
    let garage = Garage::start();
    garage.create_bucket("site");
    garage.allow_website("site");
    let said = run(garage::voxstream_with(Some(&garage), &[])
        .args(["publish", "koala", "--store"])
        .arg(&store)
        .arg("--to")
        .arg("s3://site")
        .arg("--web")
        .arg(&viewer));
    eprintln!("{said}");
    let client = garage.client("site");
    let listed: Vec<String> = {
        use futures_util::TryStreamExt;
        client.list(None).map_ok(|m| m.location.to_string()).try_collect().await.unwrap()
    };
    assert!(listed.iter().all(|p| !p.contains("/blocks/")), "per-block objects in the bucket: {listed:?}");
    assert_eq!(listed.iter().filter(|p| p.contains("/packs/")).count(), packs, "{listed:?}");
    let host = format!("site{}", garage::WEB_ROOT_DOMAIN);
    check_host("Garage website", &garage.web_endpoint, Some(&host), &blocks, 206).await;
}
