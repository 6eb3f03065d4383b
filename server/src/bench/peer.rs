//! The peer anchor: meshoptimizer's Nanite-style cluster-LOD build
//! (`meshopt::clod_build`, meshoptimizer's `clusterlod.h`) on the same mesh
//! our reader parsed, so both sides pay the same parse cost.
//!
//! `clodBuild` is single-threaded. With more than one thread we cut the
//! triangles into equal-count slabs by centroid along the longest axis and
//! build one independent DAG per slab on its own thread — what one would do to
//! use more cores with it; the slabs never simplify across their seams, so the
//! coarsest level has one root per slab instead of one.

use std::time::Instant;

use meshopt::{ClodMesh, VertexDataAdapter, clod_build, clod_default_config, typed_to_bytes};
use serde::{Deserialize, Serialize};

/// Triangles per cluster: Nanite's 128.
pub const CLUSTER_TRIANGLES: usize = 128;

/// Counts from one or more cluster-LOD DAGs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClodStats {
    pub groups: u64,
    pub clusters: u64,
    /// Deepest DAG level + 1 (the maximum over partitions).
    pub levels: u32,
    /// Triangles over all clusters of all levels.
    pub cluster_triangles: u64,
    /// Σ cluster vertex counts: each cluster stores its vertex references.
    pub cluster_vertex_refs: u64,
    /// Triangles in clusters taken from the original geometry (`refined == -1`).
    pub level0_triangles: u64,
}

impl ClodStats {
    fn add(&mut self, other: &ClodStats) {
        self.groups += other.groups;
        self.clusters += other.clusters;
        self.levels = self.levels.max(other.levels);
        self.cluster_triangles += other.cluster_triangles;
        self.cluster_vertex_refs += other.cluster_vertex_refs;
        self.level0_triangles += other.level0_triangles;
    }

    /// Bytes of the DAG stored meshlet-style: f32×3 per vertex, a u32 vertex
    /// reference per cluster vertex, 3 u8 local indices per triangle, and a
    /// 20-byte bounds record (centre, radius, error) per cluster and per group.
    pub fn stored_bytes_estimate(&self, vertices: u64) -> u64 {
        12 * vertices
            + 4 * self.cluster_vertex_refs
            + 3 * self.cluster_triangles
            + 20 * (self.clusters + self.groups)
    }
}

/// One DAG over `indices` (a flat triangle list into `positions`).
pub fn clod_dag(positions: &[[f32; 3]], indices: &[u32]) -> ClodStats {
    let mut stats = ClodStats::default();
    if indices.is_empty() {
        return stats;
    }
    let adapter = VertexDataAdapter::new(typed_to_bytes(positions), std::mem::size_of::<[f32; 3]>(), 0)
        .expect("a [f32; 3] slice is a whole number of 12-byte vertices");
    let mesh = ClodMesh::new(indices, &adapter);
    clod_build(clod_default_config(CLUSTER_TRIANGLES), &mesh, |group, clusters| {
        let id = stats.groups as i32;
        stats.groups += 1;
        stats.levels = stats.levels.max(group.depth as u32 + 1);
        for c in clusters {
            stats.clusters += 1;
            let tris = (c.indices.len() / 3) as u64;
            stats.cluster_triangles += tris;
            stats.cluster_vertex_refs += c.vertex_count as u64;
            if c.refined == -1 {
                stats.level0_triangles += tris;
            }
        }
        id
    });
    stats
}

/// Positions as f32 relative to the bounds' minimum (so georeferenced
/// coordinates keep their precision), and the triangle list flattened.
pub fn to_f32_relative(positions: &[[f64; 3]]) -> Vec<[f32; 3]> {
    let mut min = [f64::INFINITY; 3];
    for p in positions {
        for a in 0..3 {
            if p[a].is_finite() {
                min[a] = min[a].min(p[a]);
            }
        }
    }
    let min = min.map(|m| if m.is_finite() { m } else { 0.0 });
    positions.iter().map(|p| [0, 1, 2].map(|a| (p[a] - min[a]) as f32)).collect()
}

/// Splits triangles into `parts` slabs of (nearly) equal count by centroid
/// along the longest axis of the vertex bounds, each slab with its own compact
/// vertex buffer. Non-finite centroids go to the last slab.
pub fn partition_by_slabs(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    parts: usize,
) -> Vec<(Vec<[f32; 3]>, Vec<u32>)> {
    let parts = parts.clamp(1, triangles.len().max(1));
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let key = |t: &[u32; 3]| {
        let s: f32 = t.iter().map(|&i| positions[i as usize][axis]).sum();
        if s.is_finite() { s } else { f32::INFINITY }
    };
    // Slab boundaries: quantiles of the centroid keys, found by selection.
    let mut keys: Vec<f32> = triangles.iter().map(key).collect();
    let mut cuts = Vec::with_capacity(parts - 1);
    for p in 1..parts {
        let rank = p * keys.len() / parts;
        let (_, v, _) = keys.select_nth_unstable_by(rank, f32::total_cmp);
        cuts.push(*v);
    }
    drop(keys);
    let mut slabs: Vec<Vec<u32>> = vec![Vec::with_capacity(triangles.len() / parts + 1); parts];
    let mut verts: Vec<Vec<[f32; 3]>> = vec![Vec::new(); parts];
    // One slab at a time keeps a single global→local map alive.
    let mut map = vec![u32::MAX; positions.len()];
    for (part, slab) in slabs.iter_mut().enumerate() {
        let in_part = |k: f32| {
            let above = part == 0 || k >= cuts[part - 1];
            let below = part + 1 == parts || k < cuts[part];
            above && below
        };
        let mut touched = Vec::new();
        for t in triangles {
            if !in_part(key(t)) {
                continue;
            }
            for &i in t {
                let m = &mut map[i as usize];
                if *m == u32::MAX {
                    *m = verts[part].len() as u32;
                    verts[part].push(positions[i as usize]);
                    touched.push(i);
                }
                slab.push(*m);
            }
        }
        for i in touched {
            map[i as usize] = u32::MAX;
        }
    }
    verts.into_iter().zip(slabs).collect()
}

/// Timings and counts of one peer run (what `voxstream bench-meshopt` prints).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PeerRun {
    pub input_triangles: u64,
    pub vertices: u64,
    pub threads: usize,
    /// Independent DAGs built (1 unless partitioned for threads).
    pub partitions: usize,
    pub cluster_triangles_max: usize,
    /// Our reader, identical to the build's parse.
    pub parse_seconds: f64,
    /// f64 → f32 positions and, when partitioned, the slab split.
    pub prepare_seconds: f64,
    /// `clod_build` alone (the slowest partition when partitioned: wall time).
    pub clod_seconds: f64,
    pub total_seconds: f64,
    pub dag: ClodStats,
    pub stored_bytes_estimate: u64,
    /// `VmHWM` of the child as it reports itself (cross-check of the rusage figure).
    pub self_peak_rss_bytes: Option<u64>,
}

/// Parses `input` with our reader and builds the cluster-LOD DAG(s).
pub fn run_peer(input: &std::path::Path, threads: usize) -> anyhow::Result<PeerRun> {
    let threads = threads.max(1);
    let start = Instant::now();
    let (mut mesh, _) = crate::pipeline::read::read_mesh(input)?;
    let parse_seconds = start.elapsed().as_secs_f64();
    let input_triangles = mesh.triangles.len() as u64;
    let vertices_in = mesh.positions.len() as u64;

    let partitions = threads.min(mesh.triangles.len().max(1));
    let t = Instant::now();
    let positions = to_f32_relative(&mesh.positions);
    // The peer keeps only what meshoptimizer reads (f32 positions, u32 indices), so its
    // peak RSS is not inflated by our f64 copy.
    mesh.positions = Vec::new();
    let (dag, prepare_seconds, clod_seconds, vertices_stored) = if threads == 1 {
        let prepare_seconds = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let dag = clod_dag(&positions, mesh.triangles.as_flattened());
        (dag, prepare_seconds, t.elapsed().as_secs_f64(), vertices_in)
    } else {
        let slabs = partition_by_slabs(&positions, &mesh.triangles, threads);
        drop(positions);
        mesh.triangles = Vec::new();
        let prepare_seconds = t.elapsed().as_secs_f64();
        let vertices_stored = slabs.iter().map(|(v, _)| v.len() as u64).sum();
        let t = Instant::now();
        let dags: Vec<ClodStats> = std::thread::scope(|s| {
            let handles: Vec<_> = slabs.iter().map(|(v, i)| s.spawn(move || clod_dag(v, i))).collect();
            handles.into_iter().map(|h| h.join().expect("clod thread panicked")).collect()
        });
        let mut dag = ClodStats::default();
        dags.iter().for_each(|d| dag.add(d));
        (dag, prepare_seconds, t.elapsed().as_secs_f64(), vertices_stored)
    };
    Ok(PeerRun {
        input_triangles,
        vertices: vertices_in,
        threads,
        partitions,
        cluster_triangles_max: CLUSTER_TRIANGLES,
        parse_seconds,
        prepare_seconds,
        clod_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
        stored_bytes_estimate: dag.stored_bytes_estimate(vertices_stored),
        dag,
        self_peak_rss_bytes: super::measure::own_peak_rss_bytes(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed, bumpy UV sphere: rows × 2·rows quads.
    fn sphere(rows: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        let cols = 2 * rows;
        let mut p = Vec::new();
        for r in 0..=rows {
            let th = std::f32::consts::PI * r as f32 / rows as f32;
            for c in 0..cols {
                let ph = 2.0 * std::f32::consts::PI * c as f32 / cols as f32;
                let rad = 1.0 + 0.05 * (5.0 * th).sin() * (7.0 * ph).cos();
                p.push([rad * th.sin() * ph.cos(), rad * th.cos(), rad * th.sin() * ph.sin()]);
            }
        }
        let idx = |r: u32, c: u32| r * cols + c % cols;
        let mut t = Vec::new();
        for r in 0..rows {
            for c in 0..cols {
                t.push([idx(r, c), idx(r + 1, c), idx(r, c + 1)]);
                t.push([idx(r, c + 1), idx(r + 1, c), idx(r + 1, c + 1)]);
            }
        }
        (p, t)
    }

    #[test]
    fn clod_builds_a_multi_level_dag_covering_the_input() {
        let (p, t) = sphere(64); // 16384 triangles
        let dag = clod_dag(&p, t.as_flattened());
        // Level 0 is the original geometry, every triangle once.
        assert_eq!(dag.level0_triangles, t.len() as u64);
        assert!(dag.levels >= 4, "{dag:?}");
        // Coarser levels add roughly half each time: total < 3x the input.
        assert!(dag.cluster_triangles > t.len() as u64 && dag.cluster_triangles < 3 * t.len() as u64);
        assert!(dag.clusters >= t.len() as u64 / CLUSTER_TRIANGLES as u64, "{dag:?}");
        assert!(dag.stored_bytes_estimate(p.len() as u64) > 12 * p.len() as u64);
        assert_eq!(clod_dag(&p, &[]), ClodStats::default());
    }

    #[test]
    fn slabs_split_triangles_evenly_with_compact_vertices() {
        let (p, t) = sphere(32);
        let slabs = partition_by_slabs(&p, &t, 3);
        assert_eq!(slabs.len(), 3);
        let counts: Vec<usize> = slabs.iter().map(|(_, i)| i.len() / 3).collect();
        assert_eq!(counts.iter().sum::<usize>(), t.len());
        for &c in &counts {
            assert!(c.abs_diff(t.len() / 3) <= t.len() / 50, "{counts:?}");
        }
        // Every slab triangle maps back to an input triangle with the same corners.
        let mut seen: Vec<[[u32; 3]; 3]> = Vec::new();
        for (v, i) in &slabs {
            assert!(i.iter().all(|&k| (k as usize) < v.len()));
            for tri in i.chunks(3) {
                seen.push([0, 1, 2].map(|c| v[tri[c] as usize].map(f32::to_bits)));
            }
        }
        let mut want: Vec<[[u32; 3]; 3]> =
            t.iter().map(|tri| [0, 1, 2].map(|c| p[tri[c] as usize].map(f32::to_bits))).collect();
        seen.sort_unstable();
        want.sort_unstable();
        assert_eq!(seen, want);
        // One part is the whole mesh; more parts than triangles is capped.
        assert_eq!(partition_by_slabs(&p, &t, 1)[0].1.len(), 3 * t.len());
        assert_eq!(partition_by_slabs(&p, &t[..2], 5).len(), 2);
    }

    #[test]
    fn f32_positions_are_relative_to_the_minimum() {
        let p = [[1e7 + 1.0, -5.0, 2.0], [1e7 + 3.0, -4.0, f64::NAN]];
        let q = to_f32_relative(&p);
        assert_eq!(q[0], [0.0, 0.0, 0.0]);
        assert_eq!(q[1][..2], [2.0, 1.0]);
        assert!(q[1][2].is_nan());
    }
}
