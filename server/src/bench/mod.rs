//! `voxstream bench`: end-to-end build throughput, peak memory and stored
//! size per input triangle, next to a peer anchor (meshoptimizer's
//! cluster-LOD build) on the same meshes, printed as one JSON document.
//!
//! Every measured run is a child process (`voxstream build`, or the hidden
//! `voxstream bench-meshopt`) so its peak RSS is its own (`wait4` rusage)
//! and the thread count is set the way a user would (`RAYON_NUM_THREADS`).
//! The parent only spawns, waits and summarizes; progress goes to stderr,
//! the JSON to stdout.

pub mod measure;
pub mod peer;
pub mod report;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, bail};

use measure::{ChildRun, dir_size, proc_kib_field, run_child};
use peer::{CLUSTER_TRIANGLES, PeerRun};
use report::{
    Config, InputReport, Machine, PeerReport, Report, RunSample, VoxstreamReport, combine_goals,
    evaluate_goals, goal_definitions, parse_thread_list, ratios, summarize_peer, summarize_runs,
};

/// Inputs used when no `--input` is given, relative to the repository root.
pub const DEFAULT_INPUTS: [&str; 2] =
    ["../shared/data/dragon_vrip.ply", "../shared/data/matterport_cedar_creek.ply"];

/// The peer is skipped when its estimated peak (bytes per input triangle, measured
/// on the dragon and the synthetic sphere at 105-125, doubled for margin) exceeds
/// 80 % of the memory available.
const PEER_BYTES_PER_TRIANGLE_ESTIMATE: u64 = 250;

#[derive(clap::Args, Debug, Clone)]
pub struct BenchArgs {
    /// A mesh to measure (repeatable). Default: ../shared/data/dragon_vrip.ply and
    /// ../shared/data/matterport_cedar_creek.ply, those that exist.
    #[arg(long = "input")]
    pub inputs: Vec<PathBuf>,
    /// Also measure a synthetic scan (`voxstream synth`) of at least this many
    /// triangles, generated once into the work directory; 0 for none.
    #[arg(long, default_value_t = 50_000_000)]
    pub synth_triangles: u64,
    /// Measured runs per input and thread count; medians are reported.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    pub runs: u32,
    /// Comma-separated thread counts (RAYON_NUM_THREADS of each build).
    #[arg(long, default_value = "1,2")]
    pub threads: String,
    /// Level-0 voxels per edge (`auto` or a power of two), passed to every build.
    #[arg(long, default_value = "auto")]
    pub resolution: crate::pipeline::Resolution,
    /// Passed through to `voxstream build --memory-budget`; peak RSS is judged against it.
    #[arg(long)]
    pub memory_budget: Option<String>,
    /// Skip the meshoptimizer peer anchor.
    #[arg(long)]
    pub no_meshopt: bool,
    /// Where the synthetic scan and the scratch stores go (default: the system temp dir).
    #[arg(long)]
    pub work_dir: Option<PathBuf>,
}

/// `voxstream bench-meshopt` (hidden): one peer run, printed as JSON.
#[derive(clap::Args, Debug, Clone)]
pub struct BenchMeshoptArgs {
    pub input: PathBuf,
    /// 1: meshoptimizer's single-DAG build; n > 1: n independent DAGs over
    /// centroid slabs, one per thread.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
}

pub fn bench_meshopt_main(args: &BenchMeshoptArgs) -> anyhow::Result<()> {
    let run = peer::run_peer(&args.input, args.threads)
        .with_context(|| format!("meshopt peer on {}", args.input.display()))?;
    println!("{}", serde_json::to_string(&run)?);
    Ok(())
}

fn machine() -> Machine {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
    Machine {
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        cpu_model: cpuinfo
            .lines()
            .find_map(|l| l.strip_prefix("model name")?.split_once(':').map(|(_, m)| m.trim().to_string())),
        memory_bytes: proc_kib_field(&meminfo, "MemTotal"),
        memory_available_bytes_at_start: proc_kib_field(&meminfo, "MemAvailable"),
        load_average_1m_at_start: std::fs::read_to_string("/proc/loadavg")
            .ok()
            .and_then(|s| s.split_whitespace().next()?.parse().ok()),
        os: std::env::consts::OS,
        arch: std::env::consts::ARCH,
    }
}

fn timed_descriptions() -> BTreeMap<&'static str, &'static str> {
    BTreeMap::from([
        (
            "voxstream",
            "child `voxstream build <input> --out <scratch> --resolution R [--memory-budget B]` with \
             RAYON_NUM_THREADS=n, spawn to reap: read + parse, voxelize, LOD, encode, write, fsync, publish. \
             Peak RSS: wait4 ru_maxrss of that child. Size: every file under the published scene directory.",
        ),
        (
            "meshopt",
            "child `voxstream bench-meshopt <input> --threads n`, spawn to reap: our reader's parse, f64 to \
             f32 positions (n > 1: plus a split into n equal centroid slabs along the longest axis), then \
             meshopt::clod_build (meshoptimizer 1.3 clusterlod.h, clod_default_config(128)) with a counting \
             callback; n > 1 builds n independent DAGs on n threads (clodBuild itself is single-threaded). \
             Nothing is written to disk; stored bytes are an estimate (12 B/vertex, 4 B/cluster vertex, \
             3 B/triangle, 20 B bounds per cluster and group).",
        ),
    ])
}

fn input_name(path: &Path) -> String {
    path.file_stem().map_or_else(|| path.display().to_string(), |s| s.to_string_lossy().into_owned())
}

fn sample(run: &ChildRun) -> RunSample {
    RunSample {
        wall_seconds: run.wall_seconds,
        cpu_seconds: run.user_seconds + run.system_seconds,
        peak_rss_bytes: run.peak_rss_bytes,
    }
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

struct Bench<'a> {
    exe: PathBuf,
    args: &'a BenchArgs,
    threads: Vec<usize>,
    budget_bytes: Option<u64>,
    scratch: PathBuf,
}

impl Bench<'_> {
    fn build_command(&self, input: &Path, store: &Path, threads: usize) -> Command {
        let mut cmd = Command::new(&self.exe);
        cmd.arg("build")
            .arg(input)
            .arg("--out")
            .arg(store)
            .args(["--name", "bench", "--resolution", &self.args.resolution.to_string()])
            .env("RAYON_NUM_THREADS", threads.to_string())
            .env("RUST_LOG", "warn");
        if let Some(b) = &self.args.memory_budget {
            cmd.args(["--memory-budget", b]);
        }
        cmd
    }

    fn measure_voxstream(&self, name: &str, input: &Path) -> anyhow::Result<(VoxstreamReport, Option<u64>)> {
        let mut report = VoxstreamReport::default();
        let store = self.scratch.join("store");
        let mut triangles = None;
        for &n in &self.threads {
            let (mut samples, mut failures) = (Vec::new(), Vec::new());
            for r in 0..self.args.runs {
                if store.exists() {
                    std::fs::remove_dir_all(&store)?;
                }
                let run = run_child(&mut self.build_command(input, &store, n), &self.scratch.join("log"))?;
                if !run.succeeded() {
                    eprintln!("bench: {name} voxstream threads={n} run {}: FAILED {}", r + 1, run.failure());
                    failures.push(run.failure());
                    continue;
                }
                let scene = store.join("bench");
                let manifest =
                    voxstream_format::Manifest::from_json(&std::fs::read(scene.join("manifest.json"))?)
                        .context("the build's manifest")?;
                let bytes = dir_size(&scene)?;
                triangles = Some(manifest.source.triangles);
                report.resolution = manifest.grid.resolution;
                report.scene_bytes = Some(bytes);
                report.bytes_per_triangle = Some(bytes as f64 / manifest.source.triangles.max(1) as f64);
                report.voxels_level0 = manifest.levels.first().map(|l| l.voxels);
                report.blocks = Some(manifest.block_count());
                report.blocks_per_level = manifest.levels.iter().map(|l| l.blocks).collect();
                eprintln!(
                    "bench: {name} voxstream threads={n} run {}: {:.2} s, {:.2} Mtri/s, peak {:.0} MiB",
                    r + 1,
                    run.wall_seconds,
                    manifest.source.triangles as f64 / run.wall_seconds / 1e6,
                    mib(run.peak_rss_bytes)
                );
                samples.push(sample(&run));
            }
            let summary = summarize_runs(triangles.unwrap_or(0), n, &samples, failures, self.budget_bytes);
            report.threads.insert(n.to_string(), summary);
        }
        if store.exists() {
            std::fs::remove_dir_all(&store)?;
        }
        Ok((report, triangles))
    }

    fn peer_skip_reason(&self, triangles: Option<u64>) -> Option<String> {
        if self.args.no_meshopt {
            return Some("--no-meshopt".into());
        }
        let Some(t) = triangles else {
            return Some("no voxstream build succeeded, so the triangle count is unknown".into());
        };
        let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
        let available = proc_kib_field(&meminfo, "MemAvailable")?;
        let need = t.saturating_mul(PEER_BYTES_PER_TRIANGLE_ESTIMATE);
        (need > available / 5 * 4).then(|| {
            format!(
                "estimated peak {:.1} GiB ({PEER_BYTES_PER_TRIANGLE_ESTIMATE} B/triangle) exceeds 80% of the \
                 {:.1} GiB available",
                need as f64 / (1u64 << 30) as f64,
                available as f64 / (1u64 << 30) as f64
            )
        })
    }

    fn measure_peer(&self, name: &str, input: &Path, triangles: Option<u64>) -> anyhow::Result<PeerReport> {
        let mut report = PeerReport::default();
        if let Some(reason) = self.peer_skip_reason(triangles) {
            eprintln!("bench: {name} meshopt skipped: {reason}");
            report.skipped = Some(reason);
            return Ok(report);
        }
        let mut first_dag = None;
        for &n in &self.threads {
            let (mut runs, mut failures) = (Vec::new(), Vec::new());
            for r in 0..self.args.runs {
                let mut cmd = Command::new(&self.exe);
                cmd.arg("bench-meshopt")
                    .arg(input)
                    .args(["--threads", &n.to_string()])
                    .env("RAYON_NUM_THREADS", n.to_string())
                    .env("RUST_LOG", "warn");
                let run = run_child(&mut cmd, &self.scratch.join("log"))?;
                let parsed = if run.succeeded() {
                    serde_json::from_str::<PeerRun>(run.stdout.trim())
                        .map_err(|e| format!("unreadable bench-meshopt output ({e}): {}", run.stdout.trim()))
                } else {
                    Err(run.failure())
                };
                match parsed {
                    Ok(p) => {
                        eprintln!(
                            "bench: {name} meshopt threads={n} run {}: {:.2} s (parse {:.2} s, clod {:.2} s), \
                             peak {:.0} MiB",
                            r + 1,
                            run.wall_seconds,
                            p.parse_seconds,
                            p.clod_seconds,
                            mib(run.peak_rss_bytes)
                        );
                        if n == 1 || first_dag.is_none() {
                            first_dag = Some((p.dag, p.stored_bytes_estimate, p.input_triangles));
                        }
                        runs.push((sample(&run), p));
                    }
                    Err(e) => {
                        eprintln!("bench: {name} meshopt threads={n} run {}: FAILED {e}", r + 1);
                        failures.push(e);
                    }
                }
            }
            report.threads.insert(n.to_string(), summarize_peer(n, &runs, failures));
        }
        if let Some((dag, bytes, tris)) = first_dag {
            report.dag = Some(dag);
            report.stored_bytes_estimate = Some(bytes);
            report.bytes_per_triangle_estimate = Some(bytes as f64 / tris.max(1) as f64);
        }
        Ok(report)
    }
}

/// Runs the whole benchmark and returns the report.
pub fn run_bench(args: &BenchArgs) -> anyhow::Result<Report> {
    let threads = parse_thread_list(&args.threads).map_err(|e| anyhow::anyhow!("--threads: {e}"))?;
    let budget_bytes = match &args.memory_budget {
        Some(b) => {
            Some(crate::pipeline::parse_byte_size(b).map_err(|e| anyhow::anyhow!("--memory-budget: {e}"))?)
        }
        None => None,
    };
    if let crate::pipeline::Resolution::Explicit(r) = args.resolution {
        crate::pipeline::voxelize::check_resolution(r)?;
    }
    let machine = machine();
    let exe = std::env::current_exe().context("locating the voxstream binary")?;
    let mut inputs: Vec<PathBuf> = if args.inputs.is_empty() {
        DEFAULT_INPUTS.iter().map(PathBuf::from).filter(|p| p.is_file()).collect()
    } else {
        args.inputs.clone()
    };
    for p in &inputs {
        if !p.is_file() {
            bail!("input {} is not a file", p.display());
        }
    }
    let base = args.work_dir.clone().unwrap_or_else(std::env::temp_dir);
    std::fs::create_dir_all(&base)?;
    let work = tempfile::Builder::new().prefix("voxstream-bench-").tempdir_in(&base)?;
    if args.synth_triangles > 0 {
        let path = work.path().join(format!("synth_sphere_{}.ply", args.synth_triangles));
        eprintln!(
            "bench: writing a synthetic scan of {} triangles to {}",
            args.synth_triangles,
            path.display()
        );
        let r = crate::synth::write_sphere_ply(&path, args.synth_triangles)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("bench: {} triangles, {} bytes", r.triangles, r.bytes);
        inputs.push(path);
    }
    if inputs.is_empty() {
        bail!(
            "nothing to measure: no --input, none of {DEFAULT_INPUTS:?} exists, and --synth-triangles is 0"
        );
    }
    let bench =
        Bench { exe, args, threads: threads.clone(), budget_bytes, scratch: work.path().join("scratch") };
    let mut reports = Vec::new();
    for input in &inputs {
        let name = input_name(input);
        let file_bytes = std::fs::metadata(input)?.len();
        let (voxstream, triangles) = bench.measure_voxstream(&name, input)?;
        let meshopt = bench.measure_peer(&name, input, triangles)?;
        reports.push(InputReport {
            name,
            path: input.display().to_string(),
            triangles,
            file_bytes,
            ratio_voxstream_over_meshopt: ratios(&voxstream, &meshopt),
            goals: evaluate_goals(&voxstream, &meshopt),
            voxstream,
            meshopt,
        });
    }
    Ok(Report {
        machine,
        config: Config {
            voxstream_version: env!("CARGO_PKG_VERSION"),
            runs: args.runs as usize,
            threads,
            resolution: args.resolution.to_string(),
            synth_triangles: args.synth_triangles,
            memory_budget: args.memory_budget.clone(),
            meshopt_cluster_triangles: CLUSTER_TRIANGLES,
            timed: timed_descriptions(),
        },
        budget_bytes,
        goals: combine_goals(&reports.iter().map(|r| r.goals).collect::<Vec<_>>()),
        inputs: reports,
        goal_definitions: goal_definitions(),
    })
}

/// `voxstream bench`: measures and prints the report as JSON on stdout.
pub fn bench_main(args: &BenchArgs) -> anyhow::Result<()> {
    let report = run_bench(args)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
