//! Load bench: many concurrent clients fetch content-addressed blocks from a
//! running `voxstream serve` on loopback; prints one JSON object.
//!
//! ```sh
//! cargo bench -p voxstream --bench loadtest                      # own server on koala (resolution 512)
//! cargo bench -p voxstream --bench loadtest -- --clients 200 --seconds 30
//! cargo bench -p voxstream --bench loadtest -- --url http://127.0.0.1:8080 --scene koala --pid 1234
//! ```
//!
//! Without `--url` it builds `data/koala.obj` into a temporary store and
//! starts the (release) server binary itself. Latency is per request, from
//! send to the last body byte; errors are transport failures and non-200
//! answers. `server_peak_rss_kib` is the server's VmHWM from /proc.

use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use voxstream_format::Manifest;

struct Args {
    url: Option<String>,
    scene: Option<String>,
    pid: Option<u32>,
    clients: usize,
    seconds: f64,
    resolution: u32,
}

fn parse_args() -> Args {
    let mut a = Args { url: None, scene: None, pid: None, clients: 200, seconds: 30.0, resolution: 512 };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut it = argv.iter();
    while let Some(flag) = it.next() {
        let mut value = || it.next().unwrap_or_else(|| panic!("{flag} needs a value")).clone();
        match flag.as_str() {
            "--url" => a.url = Some(value()),
            "--scene" => a.scene = Some(value()),
            "--pid" => a.pid = Some(value().parse().expect("--pid takes a number")),
            "--clients" => a.clients = value().parse().expect("--clients takes a number"),
            "--seconds" => a.seconds = value().parse().expect("--seconds takes a number"),
            "--resolution" => a.resolution = value().parse().expect("--resolution takes a number"),
            _ => {} // cargo bench passes --bench
        }
    }
    a
}

fn peak_rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn percentile(sorted: &[u32], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i] as f64 / 1000.0
}

fn main() {
    let args = parse_args();
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let mut own_server = None;
    let (base, pid) = match &args.url {
        Some(url) => (url.trim_end_matches('/').to_string(), args.pid),
        None => {
            let store = tmp.path().join("store");
            let mesh = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/koala.obj");
            let opts = voxstream::pipeline::BuildOptions {
                resolution: voxstream::pipeline::Resolution::Explicit(args.resolution),
                ..Default::default()
            };
            voxstream::pipeline::build_scene(&mesh, &store, &opts).expect("building koala");
            let mut child = Command::new(env!("CARGO_BIN_EXE_voxstream"))
                .args(["serve", "--addr", "127.0.0.1:0", "--read-only", "--store"])
                .arg(&store)
                .env("RUST_LOG", "warn")
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit())
                .spawn()
                .expect("starting the server");
            let mut line = String::new();
            std::io::BufRead::read_line(
                &mut std::io::BufReader::new(child.stdout.take().unwrap()),
                &mut line,
            )
            .unwrap();
            let base = line.trim().strip_prefix("listening on ").expect("server start line").to_string();
            let pid = child.id();
            own_server = Some(child);
            (base, Some(pid))
        }
    };
    let report = rt.block_on(run(&base, &args));
    let mut report = report;
    if let Some(pid) = pid {
        report["server_pid"] = pid.into();
        report["server_peak_rss_kib"] = peak_rss_kib(pid).into();
    }
    println!("{}", serde_json::to_string_pretty(&report).unwrap());
    if let Some(mut child) = own_server {
        let _ = child.kill();
        let _ = child.wait();
    }
}

async fn run(base: &str, args: &Args) -> serde_json::Value {
    let http = reqwest::Client::builder().pool_max_idle_per_host(args.clients).build().unwrap();
    let scene = match &args.scene {
        Some(s) => s.clone(),
        None => {
            let scenes: Vec<serde_json::Value> =
                http.get(format!("{base}/api/scenes")).send().await.unwrap().json().await.unwrap();
            scenes.first().expect("the server has no scene")["id"].as_str().unwrap().to_string()
        }
    };
    let manifest_bytes = http.get(format!("{base}/api/scenes/{scene}/manifest")).send().await.unwrap();
    let manifest = Manifest::from_json(&manifest_bytes.bytes().await.unwrap()).expect("manifest");
    let mut index = voxstream_format::SceneIndex::new(&manifest);
    loop {
        let next = index.missing_pages().next().cloned();
        let Some(r) = next else { break };
        let url = format!("{base}/api/scenes/{scene}/pages/{}.{}", r.root, r.hash);
        let bytes = http.get(url).send().await.unwrap().bytes().await.unwrap();
        index.insert_page(voxstream_format::HierarchyPage::decode(&bytes, &r).expect("page")).unwrap();
    }
    let urls: Arc<Vec<String>> = Arc::new(
        index.blocks().map(|e| format!("{base}/api/scenes/{scene}/blocks/{}.{}", e.key, e.hash)).collect(),
    );
    let errors = Arc::new(AtomicU64::new(0));
    let bytes = Arc::new(AtomicU64::new(0));
    let deadline = Instant::now() + Duration::from_secs_f64(args.seconds);
    let started = Instant::now();
    let mut tasks = Vec::new();
    for c in 0..args.clients {
        let (http, urls, errors, bytes) = (http.clone(), urls.clone(), errors.clone(), bytes.clone());
        tasks.push(tokio::spawn(async move {
            let mut latencies_us = Vec::new();
            let mut i = c * 7919;
            while Instant::now() < deadline {
                i = i.wrapping_mul(1103515245).wrapping_add(12345);
                let url = &urls[(i >> 4) % urls.len()];
                let t = Instant::now();
                let ok = match http.get(url).send().await {
                    Ok(r) if r.status() == 200 => match r.bytes().await {
                        Ok(b) => {
                            bytes.fetch_add(b.len() as u64, Ordering::Relaxed);
                            true
                        }
                        Err(_) => false,
                    },
                    _ => false,
                };
                latencies_us.push(t.elapsed().as_micros().min(u32::MAX as u128) as u32);
                if !ok {
                    errors.fetch_add(1, Ordering::Relaxed);
                }
            }
            latencies_us
        }));
    }
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    let elapsed = started.elapsed().as_secs_f64();
    all.sort_unstable();
    serde_json::json!({
        "scene": scene,
        "blocks_in_scene": urls.len(),
        "clients": args.clients,
        "seconds": elapsed,
        "requests": all.len(),
        "requests_per_second": all.len() as f64 / elapsed,
        "megabytes_per_second": bytes.load(Ordering::Relaxed) as f64 / elapsed / 1e6,
        "p50_ms": percentile(&all, 0.50),
        "p90_ms": percentile(&all, 0.90),
        "p99_ms": percentile(&all, 0.99),
        "max_ms": all.last().map_or(0.0, |&v| v as f64 / 1000.0),
        "errors": errors.load(Ordering::Relaxed),
    })
}
