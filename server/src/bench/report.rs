//! The JSON the bench prints, and the pure arithmetic behind it: per-thread
//! summaries of measured runs, ratios against the peer, goal evaluation, and
//! the parsing of the command's size and thread-list arguments.

use std::collections::BTreeMap;

use serde::Serialize;

use super::measure::{median, median_u64};
use super::peer::{ClodStats, PeerRun};

/// The throughput goal: end-to-end input triangles per second per thread.
pub const GOAL_TRI_PER_S_PER_CORE: f64 = 2_000_000.0;

/// The voxel throughput goal: level-0 voxels written per second per thread.
pub const GOAL_VOXELS_PER_S_PER_CORE: f64 = 10_000_000.0;

pub fn goal_definitions() -> BTreeMap<&'static str, &'static str> {
    BTreeMap::from([
        (
            "tri_per_s_per_core_2M",
            "every input at every thread count: median end-to-end input triangles per second \
             (child `voxstream build` wall time) divided by the thread count >= 2,000,000",
        ),
        (
            "voxels_per_s_per_core_10M",
            "every input at every thread count: level-0 voxels stored divided by the median child \
             `voxstream build` wall time and by the thread count >= 10,000,000",
        ),
        (
            "core_seconds_within_2M_tri_10M_voxels",
            "every input at every thread count: median child `voxstream build` wall time times the \
             thread count <= input triangles / 2,000,000 + level-0 voxels / 10,000,000 seconds: both \
             rates at once, each in the share of the work it governs (a build of few triangles and \
             many voxels cannot meet the triangle rate alone, nor the reverse)",
        ),
        (
            "peak_rss_within_budget",
            "every `voxstream build` run's peak RSS <= budget_bytes (null without --memory-budget)",
        ),
        (
            "faster_than_meshopt",
            "every input where both ran, at every thread count both ran with: voxstream's median \
             tri/s >= meshopt's (parse + clod_build, child wall time)",
        ),
        ("all_runs_succeeded", "no build or peer run failed (skipped peer runs do not count)"),
    ])
}

/// One successful measured child run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunSample {
    pub wall_seconds: f64,
    pub cpu_seconds: f64,
    pub peak_rss_bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ThreadSummary {
    pub runs: usize,
    /// Why runs failed (they are left out of the medians).
    pub failures: Vec<String>,
    pub wall_seconds: Vec<f64>,
    pub wall_seconds_median: Option<f64>,
    pub tri_per_s_median: Option<f64>,
    pub tri_per_s_per_thread: Option<f64>,
    /// Level-0 voxels stored over the median wall time.
    pub voxels_per_s_median: Option<f64>,
    pub voxels_per_s_per_thread: Option<f64>,
    /// Median wall time × threads over the core-seconds both throughput goals
    /// allow together (triangles / 2 M + level-0 voxels / 10 M): ≤ 1 meets them.
    pub core_seconds_over_goal: Option<f64>,
    /// user + system CPU seconds over wall seconds: how many cores were busy.
    pub cpu_utilization_median: Option<f64>,
    pub peak_rss_bytes: Vec<u64>,
    pub peak_rss_bytes_max: Option<u64>,
    pub peak_rss_bytes_median: Option<u64>,
    /// peak_rss_bytes_max / budget_bytes.
    pub peak_rss_over_budget: Option<f64>,
    pub within_budget: Option<bool>,
}

pub fn summarize_runs(
    triangles: u64,
    voxels: Option<u64>,
    threads: usize,
    samples: &[RunSample],
    failures: Vec<String>,
    budget_bytes: Option<u64>,
) -> ThreadSummary {
    let walls: Vec<f64> = samples.iter().map(|s| s.wall_seconds).collect();
    let rates: Vec<f64> = walls.iter().map(|&w| triangles as f64 / w).collect();
    let utilization: Vec<f64> = samples.iter().map(|s| s.cpu_seconds / s.wall_seconds).collect();
    let rss: Vec<u64> = samples.iter().map(|s| s.peak_rss_bytes).collect();
    let tri_per_s_median = median(&rates);
    let peak_rss_bytes_max = rss.iter().copied().max();
    let wall_seconds_median = median(&walls);
    let voxels_per_s_median = voxels.zip(wall_seconds_median).map(|(v, w)| v as f64 / w);
    ThreadSummary {
        runs: samples.len() + failures.len(),
        failures,
        wall_seconds_median,
        wall_seconds: walls,
        tri_per_s_median,
        tri_per_s_per_thread: tri_per_s_median.map(|r| r / threads.max(1) as f64),
        voxels_per_s_median,
        voxels_per_s_per_thread: voxels_per_s_median.map(|r| r / threads.max(1) as f64),
        core_seconds_over_goal: voxels.zip(wall_seconds_median).map(|(v, w)| {
            let allowed = triangles as f64 / GOAL_TRI_PER_S_PER_CORE + v as f64 / GOAL_VOXELS_PER_S_PER_CORE;
            w * threads.max(1) as f64 / allowed
        }),
        cpu_utilization_median: median(&utilization),
        peak_rss_bytes_median: median_u64(&rss),
        peak_rss_bytes: rss,
        peak_rss_over_budget: budget_bytes.zip(peak_rss_bytes_max).map(|(b, m)| m as f64 / b.max(1) as f64),
        within_budget: budget_bytes.zip(peak_rss_bytes_max).map(|(b, m)| m <= b),
        peak_rss_bytes_max,
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct VoxstreamReport {
    pub threads: BTreeMap<String, ThreadSummary>,
    /// The resolution asked for (`auto` or a power of two).
    pub requested_resolution: String,
    /// The resolution the build used (with `auto`, what it chose).
    pub resolution: u32,
    /// Why the build used that resolution (the manifest's `resolution_choice.reason`).
    pub resolution_reason: Option<String>,
    /// Σ sizes of every file under the published scene directory (blocks, pages, manifest).
    pub scene_bytes: Option<u64>,
    /// scene_bytes ÷ input triangles.
    pub bytes_per_triangle: Option<f64>,
    /// scene_bytes ÷ level-0 voxels.
    pub bytes_per_level0_voxel: Option<f64>,
    pub voxels_level0: Option<u64>,
    pub blocks: Option<u64>,
    /// Blocks on each level, finest first.
    pub blocks_per_level: Vec<u32>,
    /// The published scene's files by kind.
    pub files: Option<SceneFiles>,
    /// manifest.json + every hierarchy page: what a viewer may read besides blocks.
    pub manifest_plus_page_bytes: Option<u64>,
}

/// Bytes and counts of a published scene's files, by kind (measured on disk).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct SceneFiles {
    pub manifest_bytes: u64,
    pub pages: u64,
    pub page_bytes: u64,
    /// Files holding block bytes (packs, 256 blocks each) and their bytes.
    pub block_files: u64,
    pub block_bytes: u64,
    /// Anything else under the scene directory (nothing, today).
    pub other_bytes: u64,
}

impl SceneFiles {
    pub fn total(&self) -> u64 {
        self.manifest_bytes + self.page_bytes + self.block_bytes + self.other_bytes
    }
}

/// Fills in the size figures of `report` from the built scene's manifest and files.
pub fn record_scene(report: &mut VoxstreamReport, manifest: &voxstream_format::Manifest, files: SceneFiles) {
    let bytes = files.total();
    let voxels = manifest.levels.first().map(|l| l.voxels);
    report.resolution = manifest.grid.resolution;
    report.resolution_reason = Some(manifest.resolution_choice.reason.clone());
    report.scene_bytes = Some(bytes);
    report.bytes_per_triangle = Some(bytes as f64 / manifest.source.triangles.max(1) as f64);
    report.bytes_per_level0_voxel = voxels.map(|v| bytes as f64 / v.max(1) as f64);
    report.voxels_level0 = voxels;
    report.blocks = Some(manifest.block_count());
    report.blocks_per_level = manifest.levels.iter().map(|l| l.blocks).collect();
    report.files = Some(files);
    report.manifest_plus_page_bytes = Some(files.manifest_bytes + files.page_bytes);
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PeerThreadSummary {
    pub runs: usize,
    pub failures: Vec<String>,
    /// Independent DAGs (1 = meshoptimizer's real single-DAG build).
    pub partitions: Option<usize>,
    /// Child process wall time: parse + prepare + clod_build + exit.
    pub wall_seconds_median: Option<f64>,
    pub parse_seconds_median: Option<f64>,
    pub prepare_seconds_median: Option<f64>,
    pub clod_seconds_median: Option<f64>,
    /// Input triangles over the child's wall time.
    pub tri_per_s_median: Option<f64>,
    pub tri_per_s_per_thread: Option<f64>,
    /// Input triangles over clod_build's time alone.
    pub clod_only_tri_per_s_median: Option<f64>,
    pub peak_rss_bytes_max: Option<u64>,
    pub peak_rss_bytes_median: Option<u64>,
    /// The child's own VmHWM, a cross-check of the rusage figure.
    pub self_reported_peak_rss_bytes_max: Option<u64>,
}

pub fn summarize_peer(
    threads: usize,
    runs: &[(RunSample, PeerRun)],
    failures: Vec<String>,
) -> PeerThreadSummary {
    let pick = |f: &dyn Fn(&(RunSample, PeerRun)) -> f64| median(&runs.iter().map(f).collect::<Vec<_>>());
    let tri_per_s_median = pick(&|(s, p)| p.input_triangles as f64 / s.wall_seconds);
    let rss: Vec<u64> = runs.iter().map(|(s, _)| s.peak_rss_bytes).collect();
    PeerThreadSummary {
        runs: runs.len() + failures.len(),
        failures,
        partitions: runs.first().map(|(_, p)| p.partitions),
        wall_seconds_median: pick(&|(s, _)| s.wall_seconds),
        parse_seconds_median: pick(&|(_, p)| p.parse_seconds),
        prepare_seconds_median: pick(&|(_, p)| p.prepare_seconds),
        clod_seconds_median: pick(&|(_, p)| p.clod_seconds),
        tri_per_s_median,
        tri_per_s_per_thread: tri_per_s_median.map(|r| r / threads.max(1) as f64),
        clod_only_tri_per_s_median: pick(&|(_, p)| p.input_triangles as f64 / p.clod_seconds),
        peak_rss_bytes_max: rss.iter().copied().max(),
        peak_rss_bytes_median: median_u64(&rss),
        self_reported_peak_rss_bytes_max: runs.iter().filter_map(|(_, p)| p.self_peak_rss_bytes).max(),
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PeerReport {
    /// Why the peer did not run on this input, when it did not.
    pub skipped: Option<String>,
    /// The case whose run this is: the peer is measured once per mesh, on the
    /// first case that names it, and repeated for its other resolutions.
    pub measured_in_case: Option<String>,
    pub threads: BTreeMap<String, PeerThreadSummary>,
    /// The single-DAG build's shape (from the 1-thread run, else the first that ran).
    pub dag: Option<ClodStats>,
    pub stored_bytes_estimate: Option<u64>,
    pub bytes_per_triangle_estimate: Option<f64>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Ratios {
    /// voxstream tri/s ÷ meshopt tri/s (both child wall time), per thread count.
    pub tri_per_s: BTreeMap<String, f64>,
    /// voxstream peak RSS (max) ÷ meshopt peak RSS (max), per thread count.
    pub peak_rss: BTreeMap<String, f64>,
    /// voxstream scene bytes ÷ meshopt's estimated stored DAG bytes.
    pub bytes_per_triangle: Option<f64>,
}

pub fn ratios(vox: &VoxstreamReport, peer: &PeerReport) -> Ratios {
    let mut r = Ratios::default();
    for (n, v) in &vox.threads {
        let Some(p) = peer.threads.get(n) else { continue };
        if let (Some(a), Some(b)) = (v.tri_per_s_median, p.tri_per_s_median) {
            r.tri_per_s.insert(n.clone(), a / b);
        }
        if let (Some(a), Some(b)) = (v.peak_rss_bytes_max, p.peak_rss_bytes_max) {
            r.peak_rss.insert(n.clone(), a as f64 / b.max(1) as f64);
        }
    }
    r.bytes_per_triangle = vox.bytes_per_triangle.zip(peer.bytes_per_triangle_estimate).map(|(a, b)| a / b);
    r
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Goals {
    #[serde(rename = "tri_per_s_per_core_2M")]
    pub tri_per_s_per_core_2m: Option<bool>,
    #[serde(rename = "voxels_per_s_per_core_10M")]
    pub voxels_per_s_per_core_10m: Option<bool>,
    #[serde(rename = "core_seconds_within_2M_tri_10M_voxels")]
    pub core_seconds_within_goal: Option<bool>,
    pub peak_rss_within_budget: Option<bool>,
    pub faster_than_meshopt: Option<bool>,
    pub all_runs_succeeded: bool,
}

/// `None` when nothing was evaluated, else whether every evaluated case passed.
fn all_of(values: impl IntoIterator<Item = Option<bool>>) -> Option<bool> {
    values.into_iter().flatten().fold(None, |acc, v| Some(acc.unwrap_or(true) && v))
}

pub fn evaluate_goals(vox: &VoxstreamReport, peer: &PeerReport) -> Goals {
    let rates = vox.threads.values().map(|t| t.tri_per_s_per_thread.map(|r| r >= GOAL_TRI_PER_S_PER_CORE));
    let voxel_rates =
        vox.threads.values().map(|t| t.voxels_per_s_per_thread.map(|r| r >= GOAL_VOXELS_PER_S_PER_CORE));
    let mut faster = Vec::new();
    for (n, v) in &vox.threads {
        if let Some(p) = peer.threads.get(n) {
            faster.push(v.tri_per_s_median.zip(p.tri_per_s_median).map(|(a, b)| a >= b));
        }
    }
    let failed = vox.threads.values().any(|t| !t.failures.is_empty() || t.tri_per_s_median.is_none())
        || peer.threads.values().any(|t| !t.failures.is_empty());
    Goals {
        // A thread count with no successful run fails the goal rather than vanishing from it.
        tri_per_s_per_core_2m: all_of(rates.map(|r| Some(r.unwrap_or(false)))),
        voxels_per_s_per_core_10m: all_of(voxel_rates.map(|r| Some(r.unwrap_or(false)))),
        core_seconds_within_goal: all_of(
            vox.threads.values().map(|t| Some(t.core_seconds_over_goal.is_some_and(|r| r <= 1.0))),
        ),
        peak_rss_within_budget: all_of(vox.threads.values().map(|t| t.within_budget)),
        faster_than_meshopt: all_of(faster),
        all_runs_succeeded: !failed && !vox.threads.is_empty(),
    }
}

pub fn combine_goals(per_input: &[Goals]) -> Goals {
    Goals {
        tri_per_s_per_core_2m: all_of(per_input.iter().map(|g| g.tri_per_s_per_core_2m)),
        voxels_per_s_per_core_10m: all_of(per_input.iter().map(|g| g.voxels_per_s_per_core_10m)),
        core_seconds_within_goal: all_of(per_input.iter().map(|g| g.core_seconds_within_goal)),
        peak_rss_within_budget: all_of(per_input.iter().map(|g| g.peak_rss_within_budget)),
        faster_than_meshopt: all_of(per_input.iter().map(|g| g.faster_than_meshopt)),
        all_runs_succeeded: !per_input.is_empty() && per_input.iter().all(|g| g.all_runs_succeeded),
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InputReport {
    /// `<name>@<requested resolution>`, unique within a report.
    pub case: String,
    pub name: String,
    pub path: String,
    /// Input triangles as the build counted them (skipped ones included).
    pub triangles: Option<u64>,
    pub file_bytes: u64,
    pub voxstream: VoxstreamReport,
    pub meshopt: PeerReport,
    pub ratio_voxstream_over_meshopt: Ratios,
    pub goals: Goals,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Machine {
    pub cores: usize,
    pub cpu_model: Option<String>,
    pub memory_bytes: Option<u64>,
    pub memory_available_bytes_at_start: Option<u64>,
    pub load_average_1m_at_start: Option<f64>,
    pub os: &'static str,
    pub arch: &'static str,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Config {
    pub voxstream_version: &'static str,
    pub runs: usize,
    pub threads: Vec<usize>,
    /// Later runs of a case are skipped once one of its runs took longer than this.
    pub single_run_over_seconds: Option<f64>,
    /// Each case as `path@resolution`, in the order measured.
    pub cases: Vec<String>,
    pub synth_triangles: u64,
    pub memory_budget: Option<String>,
    pub meshopt_cluster_triangles: usize,
    pub timed: BTreeMap<&'static str, &'static str>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    pub machine: Machine,
    pub config: Config,
    pub budget_bytes: Option<u64>,
    pub inputs: Vec<InputReport>,
    pub goals: Goals,
    pub goal_definitions: BTreeMap<&'static str, &'static str>,
}

/// `"1,2,4"` → `[1, 2, 4]`: positive, no duplicates.
pub fn parse_thread_list(s: &str) -> Result<Vec<usize>, String> {
    let mut out: Vec<usize> = Vec::new();
    for part in s.split(',').map(str::trim) {
        let n: usize = part.parse().map_err(|_| format!("{part:?} is not a thread count"))?;
        if n == 0 {
            return Err("thread counts start at 1".into());
        }
        if out.contains(&n) {
            return Err(format!("thread count {n} is listed twice"));
        }
        out.push(n);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(wall: f64, rss_mib: u64) -> RunSample {
        RunSample { wall_seconds: wall, cpu_seconds: wall * 1.5, peak_rss_bytes: rss_mib << 20 }
    }

    fn peer_run(triangles: u64, clod: f64) -> PeerRun {
        PeerRun {
            input_triangles: triangles,
            vertices: triangles / 2,
            threads: 1,
            partitions: 1,
            cluster_triangles_max: 128,
            parse_seconds: 0.5,
            prepare_seconds: 0.1,
            clod_seconds: clod,
            total_seconds: 0.6 + clod,
            dag: ClodStats::default(),
            stored_bytes_estimate: 0,
            self_peak_rss_bytes: Some(1 << 20),
        }
    }

    #[test]
    fn thread_summary_takes_medians_and_checks_the_budget() {
        let runs = [sample(2.0, 300), sample(1.0, 100), sample(4.0, 200)];
        let s = summarize_runs(
            8_000_000,
            Some(30_000_000),
            2,
            &runs,
            vec!["exit code 1: boom".into()],
            Some(250 << 20),
        );
        assert_eq!(s.runs, 4);
        assert_eq!(s.wall_seconds_median, Some(2.0));
        assert_eq!(s.tri_per_s_median, Some(4_000_000.0));
        assert_eq!(s.tri_per_s_per_thread, Some(2_000_000.0));
        assert_eq!(s.cpu_utilization_median, Some(1.5));
        assert_eq!(s.voxels_per_s_median, Some(15_000_000.0));
        assert_eq!(s.voxels_per_s_per_thread, Some(7_500_000.0));
        assert_eq!(s.core_seconds_over_goal, Some(4.0 / 7.0));
        assert_eq!(s.peak_rss_bytes_max, Some(300 << 20));
        assert_eq!(s.peak_rss_bytes_median, Some(200 << 20));
        assert_eq!(s.peak_rss_over_budget, Some(1.2));
        assert_eq!(s.within_budget, Some(false));
        let none = summarize_runs(10, None, 1, &[], vec![], None);
        assert_eq!((none.tri_per_s_median, none.within_budget, none.peak_rss_bytes_max), (None, None, None));
        assert_eq!(none.core_seconds_over_goal, None);
    }

    fn vox_with(rates: &[(usize, f64)], within: Option<bool>) -> VoxstreamReport {
        let mut v = VoxstreamReport::default();
        for &(n, wall) in rates {
            let budget = within.map(|ok| if ok { 1 << 30 } else { 1 });
            v.threads.insert(
                n.to_string(),
                summarize_runs(4_000_000, Some(24_000_000), n, &[sample(wall, 64)], vec![], budget),
            );
        }
        v
    }

    #[test]
    fn goals_follow_the_measurements() {
        // 4 M triangles: 1 thread in 1.5 s (2.67 M/s), 2 threads in 0.8 s (2.5 M/s per thread).
        let fast = vox_with(&[(1, 1.5), (2, 0.8)], Some(true));
        let peer_slow = PeerReport {
            threads: BTreeMap::from([(
                "1".to_string(),
                summarize_peer(1, &[(sample(4.0, 128), peer_run(4_000_000, 3.0))], vec![]),
            )]),
            ..Default::default()
        };
        let g = evaluate_goals(&fast, &peer_slow);
        assert_eq!(
            g,
            Goals {
                tri_per_s_per_core_2m: Some(true),
                voxels_per_s_per_core_10m: Some(true),
                core_seconds_within_goal: Some(true),
                peak_rss_within_budget: Some(true),
                faster_than_meshopt: Some(true),
                all_runs_succeeded: true
            }
        );
        let r = ratios(&fast, &peer_slow);
        assert_eq!(r.tri_per_s.get("1").copied(), Some(4.0 / 1.5));
        assert_eq!(r.peak_rss.get("1").copied(), Some(0.5));
        assert!(!r.tri_per_s.contains_key("2"));

        // 2 threads in 1.2 s is only 1.67 M/s and 10 M voxels/s per thread; over budget; no peer.
        let slow = vox_with(&[(1, 1.5), (2, 1.2)], Some(false));
        let g2 = evaluate_goals(&slow, &PeerReport::default());
        assert_eq!(g2.tri_per_s_per_core_2m, Some(false));
        assert_eq!(g2.voxels_per_s_per_core_10m, Some(true));
        // 4 M triangles and 24 M voxels allow 2 + 2.4 core-seconds: 2.4 meets that, the triangle rate alone does not.
        assert_eq!(slow.threads["2"].core_seconds_over_goal, Some(2.4 / 4.4));
        assert_eq!(g2.core_seconds_within_goal, Some(true));
        let over = vox_with(&[(1, 1.5), (2, 2.3)], Some(true));
        assert_eq!(evaluate_goals(&over, &PeerReport::default()).core_seconds_within_goal, Some(false));
        let slower = vox_with(&[(1, 1.5), (2, 1.3)], Some(true));
        assert_eq!(evaluate_goals(&slower, &PeerReport::default()).voxels_per_s_per_core_10m, Some(false));
        assert_eq!(g2.peak_rss_within_budget, Some(false));
        assert_eq!(g2.faster_than_meshopt, None);

        let failed = summarize_runs(4_000_000, None, 1, &[], vec!["killed".into()], None);
        let broken =
            VoxstreamReport { threads: BTreeMap::from([("1".into(), failed)]), ..Default::default() };
        let g3 = evaluate_goals(&broken, &PeerReport::default());
        assert_eq!(g3.tri_per_s_per_core_2m, Some(false));
        assert_eq!(g3.voxels_per_s_per_core_10m, Some(false));
        assert_eq!(g3.core_seconds_within_goal, Some(false));
        assert!(!g3.all_runs_succeeded);

        let all = combine_goals(&[g, g2]);
        assert_eq!(all.tri_per_s_per_core_2m, Some(false));
        assert_eq!(all.faster_than_meshopt, Some(true)); // evaluated on the first input only
        assert!(all.all_runs_succeeded);
        assert!(!combine_goals(&[g, g3]).all_runs_succeeded);
        assert_eq!(combine_goals(&[]).tri_per_s_per_core_2m, None);
    }

    #[test]
    fn peer_summary_separates_clod_time() {
        let runs =
            [(sample(5.0, 512), peer_run(10_000_000, 2.0)), (sample(3.0, 256), peer_run(10_000_000, 4.0))];
        let s = summarize_peer(1, &runs, vec![]);
        assert_eq!(s.wall_seconds_median, Some(4.0));
        assert_eq!(s.clod_seconds_median, Some(3.0));
        assert_eq!(s.tri_per_s_median, Some((2e6 + 10e6 / 3.0) / 2.0));
        assert_eq!(s.clod_only_tri_per_s_median, Some((5e6 + 2.5e6) / 2.0));
        assert_eq!(s.peak_rss_bytes_max, Some(512 << 20));
        assert_eq!(s.partitions, Some(1));
    }

    #[test]
    fn report_json_has_the_documented_shape() {
        let vox = vox_with(&[(1, 2.0), (2, 1.0)], None);
        let report = Report {
            machine: Machine {
                cores: 2,
                cpu_model: None,
                memory_bytes: None,
                memory_available_bytes_at_start: None,
                load_average_1m_at_start: None,
                os: "linux",
                arch: "x86_64",
            },
            config: Config {
                voxstream_version: "0",
                runs: 1,
                threads: vec![1, 2],
                single_run_over_seconds: None,
                cases: vec!["x.ply@512".into()],
                synth_triangles: 0,
                memory_budget: None,
                meshopt_cluster_triangles: 128,
                timed: BTreeMap::new(),
            },
            budget_bytes: None,
            inputs: vec![InputReport {
                case: "x@512".into(),
                name: "x".into(),
                path: "x.ply".into(),
                triangles: Some(4_000_000),
                file_bytes: 1,
                goals: evaluate_goals(&vox, &PeerReport::default()),
                voxstream: vox,
                meshopt: PeerReport { skipped: Some("too big".into()), ..Default::default() },
                ratio_voxstream_over_meshopt: Ratios::default(),
            }],
            goals: Goals::default(),
            goal_definitions: goal_definitions(),
        };
        let v = serde_json::to_value(&report).unwrap();
        assert_eq!(v["machine"]["cores"], 2);
        assert_eq!(v["inputs"][0]["voxstream"]["threads"]["2"]["tri_per_s_median"], 4_000_000.0);
        assert_eq!(v["inputs"][0]["voxstream"]["threads"]["1"]["tri_per_s_per_thread"], 2_000_000.0);
        assert_eq!(v["inputs"][0]["meshopt"]["skipped"], "too big");
        assert_eq!(v["inputs"][0]["goals"]["tri_per_s_per_core_2M"], true);
        assert!(v["goals"].get("tri_per_s_per_core_2M").is_some());
        assert!(v["budget_bytes"].is_null());
        assert!(v["goal_definitions"]["tri_per_s_per_core_2M"].as_str().unwrap().contains("2,000,000"));
    }

    #[test]
    fn thread_lists_and_sizes_parse_strictly() {
        assert_eq!(parse_thread_list("1,2").unwrap(), [1, 2]);
        assert_eq!(parse_thread_list(" 4 ").unwrap(), [4]);
        assert!(parse_thread_list("0").is_err());
        assert!(parse_thread_list("1,1").is_err());
        assert!(parse_thread_list("1,x").is_err());
        assert!(parse_thread_list("").is_err());
        assert_eq!(crate::pipeline::parse_byte_size("4G").unwrap(), 4 << 30);
        assert_eq!(crate::pipeline::parse_byte_size("512MiB").unwrap(), 512 << 20);
        assert_eq!(crate::pipeline::parse_byte_size("1.5g").unwrap(), 3 << 29);
        assert_eq!(crate::pipeline::parse_byte_size("1000000").unwrap(), 1_000_000);
        assert_eq!(crate::pipeline::parse_byte_size("64 kb").unwrap(), 64 << 10);
        assert!(crate::pipeline::parse_byte_size("4X").is_err());
        assert!(crate::pipeline::parse_byte_size("G").is_err());
        assert!(crate::pipeline::parse_byte_size("0").is_err());
        assert!(crate::pipeline::parse_byte_size("99999999T").is_err());
    }
}
