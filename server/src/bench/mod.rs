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
    Config, InputReport, Machine, PeerReport, Report, RunSample, SceneFiles, VoxstreamReport, combine_goals,
    evaluate_goals, goal_definitions, parse_thread_list, ratios, record_scene, summarize_peer,
    summarize_runs,
};

use crate::pipeline::Resolution;

/// Cases measured when no `--input` is given (issue 8's "Measure" list, those
/// whose mesh exists), relative to the repository root: the dragon at auto and
/// Cedar Creek at 4096, 8192 and 16384. The synthetic scan is added by
/// `--synth-triangles`.
pub const DEFAULT_INPUTS: [&str; 4] = [
    "../shared/data/dragon_vrip.ply@auto",
    "../shared/data/matterport_cedar_creek.ply@4096",
    "../shared/data/matterport_cedar_creek.ply@8192",
    "../shared/data/matterport_cedar_creek.ply@16384",
];

/// The peer is skipped when its estimated peak (bytes per input triangle, measured
/// on the dragon and the synthetic sphere at 105-125, doubled for margin) exceeds
/// 80 % of the memory available.
const PEER_BYTES_PER_TRIANGLE_ESTIMATE: u64 = 250;

/// A resolution as the bench takes it: `auto` or a power of two up to 65536.
pub fn parse_bench_resolution(text: &str) -> Result<Resolution, String> {
    let r: Resolution = text.trim().parse()?;
    if let Resolution::Explicit(n) = r {
        crate::pipeline::voxelize::check_resolution(n).map_err(|e| e.to_string())?;
    }
    Ok(r)
}

/// One `--input`: a mesh, and the resolution its builds use (`None`: `--resolution`'s).
#[derive(Debug, Clone, PartialEq)]
pub struct InputSpec {
    pub path: PathBuf,
    pub resolution: Option<Resolution>,
}

impl InputSpec {
    /// `PATH` or `PATH@RES` (RES `auto` or a power of two). The part after the
    /// last `@` must be a resolution, so a path that itself holds an `@` is
    /// written with one, e.g. `scan@2x.ply@auto`.
    pub fn parse(text: &str) -> Result<Self, String> {
        let Some((path, res)) = text.rsplit_once('@') else {
            if text.is_empty() {
                return Err("an empty input path".into());
            }
            return Ok(Self { path: PathBuf::from(text), resolution: None });
        };
        if path.is_empty() {
            return Err(format!("{text:?} names no file before '@'"));
        }
        let resolution = parse_bench_resolution(res).map_err(|e| {
            format!(
                "{text:?}: after the last '@' comes the case's resolution, auto or a power of two up to \
                 65536 ({e}); write a path that holds '@' as PATH@auto"
            )
        })?;
        Ok(Self { path: PathBuf::from(path), resolution: Some(resolution) })
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct BenchArgs {
    /// A case to measure (repeatable): a mesh, optionally with its own resolution as
    /// `PATH@auto` or `PATH@4096`; the same mesh may be listed at several resolutions.
    /// Default: the dragon at auto and Cedar Creek at 4096, 8192 and 16384 (from
    /// ../shared/data, those that exist).
    #[arg(long = "input", value_parser = InputSpec::parse)]
    pub inputs: Vec<InputSpec>,
    /// Also measure a synthetic scan (`voxstream synth`) of at least this many
    /// triangles, generated once into the work directory; 0 for none.
    #[arg(long, default_value_t = 100_000_000)]
    pub synth_triangles: u64,
    /// The synthetic scan's resolution (default: `--resolution`'s).
    #[arg(long, value_parser = parse_bench_resolution)]
    pub synth_resolution: Option<Resolution>,
    /// Measured runs per case and thread count; medians are reported.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    pub runs: u32,
    /// Skip a case's later runs (at that thread count) once one of its runs took
    /// longer than this many seconds: big cases then run once, small ones `--runs` times.
    #[arg(long, value_parser = parse_seconds)]
    pub single_run_over: Option<f64>,
    /// Comma-separated thread counts (RAYON_NUM_THREADS of each build).
    #[arg(long, default_value = "1,2")]
    pub threads: String,
    /// Level-0 voxels per edge (`auto` or a power of two) of every case that does not
    /// name its own with `@`.
    #[arg(long, default_value = "auto", value_parser = parse_bench_resolution)]
    pub resolution: Resolution,
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

fn parse_seconds(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 => Ok(s),
        _ => Err(format!("{text:?} is not a positive number of seconds")),
    }
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

/// One measured case: a mesh at a resolution.
struct Case {
    /// `<name>@<resolution>`.
    label: String,
    name: String,
    path: PathBuf,
    resolution: Resolution,
}

struct Bench<'a> {
    exe: PathBuf,
    args: &'a BenchArgs,
    threads: Vec<usize>,
    budget_bytes: Option<u64>,
    scratch: PathBuf,
}

/// The published scene's files by kind: `manifest.json`, `pages/`, the block
/// bytes (`packs/`, 256 blocks a pack; `blocks/` in stores written before packs), the rest.
pub fn scene_files(scene: &Path) -> std::io::Result<SceneFiles> {
    let mut files = SceneFiles::default();
    for entry in std::fs::read_dir(scene)? {
        let entry = entry?;
        let path = entry.path();
        let kind = entry.file_type()?;
        let name = entry.file_name();
        if kind.is_dir() && (name == "pages" || name == "packs" || name == "blocks") {
            let (count, bytes) = std::fs::read_dir(&path)?.try_fold((0u64, 0u64), |(n, b), e| {
                let e = e?;
                Ok::<_, std::io::Error>(if e.file_type()?.is_file() {
                    (n + 1, b + e.metadata()?.len())
                } else {
                    (n, b + dir_size(&e.path())?)
                })
            })?;
            if name == "pages" {
                (files.pages, files.page_bytes) = (count, bytes);
            } else {
                files.block_files += count;
                files.block_bytes += bytes;
            }
        } else if kind.is_file() && name == "manifest.json" {
            files.manifest_bytes = entry.metadata()?.len();
        } else if kind.is_dir() {
            files.other_bytes += dir_size(&path)?;
        } else if kind.is_file() {
            files.other_bytes += entry.metadata()?.len();
        }
    }
    // Pages live in the packs: count them from the hierarchy, and the packs' rest as blocks.
    if files.pages == 0 && files.manifest_bytes > 0 {
        let manifest = voxstream_format::Manifest::from_json(&std::fs::read(scene.join("manifest.json"))?)
            .map_err(std::io::Error::other)?;
        let index = crate::store::read_scene_index(scene, &manifest).map_err(std::io::Error::other)?;
        files.pages = index.pages_loaded() as u64;
        files.page_bytes = index.page_bytes_loaded();
        files.block_bytes = files.block_bytes.saturating_sub(files.page_bytes);
    }
    Ok(files)
}

impl Bench<'_> {
    fn build_command(&self, input: &Path, store: &Path, threads: usize, resolution: Resolution) -> Command {
        let mut cmd = Command::new(&self.exe);
        cmd.arg("build")
            .arg(input)
            .arg("--out")
            .arg(store)
            .args(["--name", "bench", "--resolution", &resolution.to_string()])
            .env("RAYON_NUM_THREADS", threads.to_string())
            .env("RUST_LOG", "warn");
        if let Some(b) = &self.args.memory_budget {
            cmd.args(["--memory-budget", b]);
        }
        cmd
    }

    /// Whether to stop a case's runs after `run` took `wall` seconds.
    fn enough_runs(&self, wall: f64) -> bool {
        self.args.single_run_over.is_some_and(|limit| wall > limit)
    }

    fn measure_voxstream(&self, case: &Case) -> anyhow::Result<(VoxstreamReport, Option<u64>)> {
        let name = &case.label;
        let mut report =
            VoxstreamReport { requested_resolution: case.resolution.to_string(), ..Default::default() };
        let store = self.scratch.join("store");
        let mut triangles = None;
        for &n in &self.threads {
            let (mut samples, mut failures) = (Vec::new(), Vec::new());
            for r in 0..self.args.runs {
                if store.exists() {
                    std::fs::remove_dir_all(&store)?;
                }
                let run = run_child(
                    &mut self.build_command(&case.path, &store, n, case.resolution),
                    &self.scratch.join("log"),
                )?;
                if !run.succeeded() {
                    eprintln!("bench: {name} voxstream threads={n} run {}: FAILED {}", r + 1, run.failure());
                    failures.push(run.failure());
                    continue;
                }
                let scene = store.join("bench");
                let manifest =
                    voxstream_format::Manifest::from_json(&std::fs::read(scene.join("manifest.json"))?)
                        .context("the build's manifest")?;
                let files = scene_files(&scene).context("measuring the built scene")?;
                triangles = Some(manifest.source.triangles);
                record_scene(&mut report, &manifest, files);
                eprintln!(
                    "bench: {name} voxstream threads={n} run {}: {:.2} s, {:.2} Mtri/s, {:.2} Mvoxel/s, \
                     peak {:.0} MiB",
                    r + 1,
                    run.wall_seconds,
                    manifest.source.triangles as f64 / run.wall_seconds / 1e6,
                    manifest.levels[0].voxels as f64 / run.wall_seconds / 1e6,
                    mib(run.peak_rss_bytes)
                );
                samples.push(sample(&run));
                if self.enough_runs(run.wall_seconds) {
                    break;
                }
            }
            let summary = summarize_runs(
                triangles.unwrap_or(0),
                report.voxels_level0,
                n,
                &samples,
                failures,
                self.budget_bytes,
            );
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
        let mut report = PeerReport { measured_in_case: Some(name.to_string()), ..Default::default() };
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
                        let wall = run.wall_seconds;
                        runs.push((sample(&run), p));
                        if self.enough_runs(wall) {
                            break;
                        }
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
    let machine = machine();
    let exe = std::env::current_exe().context("locating the voxstream binary")?;
    let specs: Vec<InputSpec> = if args.inputs.is_empty() {
        DEFAULT_INPUTS
            .iter()
            .map(|s| InputSpec::parse(s).expect("the default cases parse"))
            .filter(|c| c.path.is_file())
            .collect()
    } else {
        args.inputs.clone()
    };
    let mut cases = Vec::new();
    for spec in specs {
        if !spec.path.is_file() {
            bail!("input {} is not a file", spec.path.display());
        }
        let resolution = spec.resolution.unwrap_or(args.resolution);
        let name = input_name(&spec.path);
        cases.push(Case { label: format!("{name}@{resolution}"), name, path: spec.path, resolution });
    }
    for (i, c) in cases.iter().enumerate() {
        if cases[..i].iter().any(|d| d.path == c.path && d.resolution == c.resolution) {
            bail!("--input {}@{} is listed twice", c.path.display(), c.resolution);
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
        let resolution = args.synth_resolution.unwrap_or(args.resolution);
        let name = input_name(&path);
        cases.push(Case { label: format!("{name}@{resolution}"), name, path, resolution });
    }
    if cases.is_empty() {
        bail!(
            "nothing to measure: no --input, none of {DEFAULT_INPUTS:?} exists, and --synth-triangles is 0"
        );
    }
    let bench =
        Bench { exe, args, threads: threads.clone(), budget_bytes, scratch: work.path().join("scratch") };
    let mut reports: Vec<InputReport> = Vec::new();
    for case in &cases {
        eprintln!("bench: case {} ({})", case.label, case.path.display());
        let file_bytes = std::fs::metadata(&case.path)?.len();
        let (voxstream, triangles) = bench.measure_voxstream(case)?;
        // The peer does not depend on the resolution: measured once per mesh.
        let earlier = reports.iter().find(|r| Path::new(&r.path) == case.path && r.meshopt.skipped.is_none());
        let meshopt = match earlier {
            Some(r) => r.meshopt.clone(),
            None => bench.measure_peer(&case.label, &case.path, triangles)?,
        };
        reports.push(InputReport {
            case: case.label.clone(),
            name: case.name.clone(),
            path: case.path.display().to_string(),
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
            single_run_over_seconds: args.single_run_over,
            cases: cases.iter().map(|c| format!("{}@{}", c.path.display(), c.resolution)).collect(),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn input_specs_take_a_resolution_after_the_last_at() {
        let spec = |s: &str| InputSpec::parse(s);
        assert_eq!(spec("a/scan.ply").unwrap(), InputSpec { path: "a/scan.ply".into(), resolution: None });
        assert_eq!(spec("scan.ply@4096").unwrap().resolution, Some(Resolution::Explicit(4096)));
        assert_eq!(spec("scan.ply@AUTO").unwrap().resolution, Some(Resolution::Auto));
        let at = spec("dir/scan@2x.ply@auto").unwrap();
        assert_eq!((at.path, at.resolution), (PathBuf::from("dir/scan@2x.ply"), Some(Resolution::Auto)));
        assert_eq!(spec("s@65536").unwrap().resolution, Some(Resolution::Explicit(65536)));
        // Negative controls: each names what is wrong.
        for (bad, says) in [
            ("scan.ply@4000", "power of two"),
            ("scan.ply@131072", "65536"),
            ("scan.ply@", "resolution"),
            ("scan.ply@fast", "auto"),
            ("scan@2x.ply", "PATH@auto"),
            ("@4096", "names no file"),
            ("", "empty"),
        ] {
            let e = spec(bad).expect_err(bad);
            assert!(e.contains(says), "{bad:?}: {e}");
        }
    }

    #[test]
    fn bench_resolutions_are_checked_when_parsed() {
        assert_eq!(parse_bench_resolution("auto"), Ok(Resolution::Auto));
        assert_eq!(parse_bench_resolution("1024"), Ok(Resolution::Explicit(1024)));
        assert!(parse_bench_resolution("100").is_err());
        assert!(parse_bench_resolution("0").is_err());
        assert!(parse_seconds("0").is_err());
        assert!(parse_seconds("nan").is_err());
        assert_eq!(parse_seconds("60"), Ok(60.0));
    }

    #[test]
    fn scene_files_are_split_by_kind() {
        let dir = tempfile::tempdir().unwrap();
        let scene = dir.path();
        std::fs::create_dir_all(scene.join("packs")).unwrap();
        std::fs::create_dir_all(scene.join("pages")).unwrap();
        std::fs::write(scene.join("manifest.json"), [0u8; 100]).unwrap();
        std::fs::write(scene.join("pages/1-0-0-0.vxh"), [0u8; 40]).unwrap();
        for (i, n) in [10usize, 20, 30].into_iter().enumerate() {
            std::fs::write(scene.join(format!("packs/{i}.vxp")), vec![0u8; n]).unwrap();
        }
        std::fs::write(scene.join("scene.json"), [0u8; 7]).unwrap();
        let f = scene_files(scene).unwrap();
        assert_eq!(
            f,
            SceneFiles {
                manifest_bytes: 100,
                pages: 1,
                page_bytes: 40,
                block_files: 3,
                block_bytes: 60,
                other_bytes: 7
            }
        );
        assert_eq!(f.total(), dir_size(scene).unwrap());
    }
}
