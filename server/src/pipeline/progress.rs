//! Build progress: which stage, how far the whole build is, and end-to-end
//! throughput, reported through a callback. The CLI draws it with indicatif;
//! the server will stream the same reports to users.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    Read,
    Voxelize,
    Lod,
    Write,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Read => "read",
            Stage::Voxelize => "voxelize",
            Stage::Lod => "lod",
            Stage::Write => "write",
        }
    }

    /// The slice of the whole build this stage covers, from measured koala and
    /// dragon builds (reading and voxelizing dominate).
    fn span(self) -> (f64, f64) {
        match self {
            Stage::Read => (0.0, 0.35),
            Stage::Voxelize => (0.35, 0.75),
            Stage::Lod => (0.75, 0.85),
            Stage::Write => (0.85, 1.0),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Progress {
    pub stage: Stage,
    /// Of the whole build, 0..=1; never decreases within one build.
    pub fraction: f64,
    /// Input triangles per second, end to end, so far (0 until they are counted).
    pub triangles_per_second: f64,
}

/// Turns per-stage fractions into [`Progress`] reports.
pub struct ProgressSink<'a> {
    report: &'a (dyn Fn(Progress) + Sync),
    start: Instant,
    triangles: AtomicU64,
}

impl<'a> ProgressSink<'a> {
    pub fn new(report: &'a (dyn Fn(Progress) + Sync)) -> Self {
        Self { report, start: Instant::now(), triangles: AtomicU64::new(0) }
    }

    pub fn set_triangles(&self, n: u64) {
        self.triangles.store(n, Ordering::Relaxed);
    }

    /// Reports that `stage` is `stage_fraction` (0..=1) done.
    pub fn stage(&self, stage: Stage, stage_fraction: f64) {
        let (lo, hi) = stage.span();
        let fraction = lo + (hi - lo) * stage_fraction.clamp(0.0, 1.0);
        let secs = self.start.elapsed().as_secs_f64().max(1e-6);
        let triangles = self.triangles.load(Ordering::Relaxed) as f64;
        (self.report)(Progress { stage, fraction, triangles_per_second: triangles * fraction / secs });
    }
}

/// Counts finished items of one stage from many threads and reports each.
pub struct StageCounter<'s, 'a> {
    sink: &'s ProgressSink<'a>,
    stage: Stage,
    total: u64,
    done: AtomicU64,
}

impl<'s, 'a> StageCounter<'s, 'a> {
    pub fn new(sink: &'s ProgressSink<'a>, stage: Stage, total: usize) -> Self {
        sink.stage(stage, 0.0);
        Self { sink, stage, total: total.max(1) as u64, done: AtomicU64::new(0) }
    }

    pub fn tick(&self) {
        let done = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        self.sink.stage(self.stage, done as f64 / self.total as f64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn fractions_cover_the_build_in_order() {
        let seen = Mutex::new(Vec::new());
        let report = |p: Progress| seen.lock().unwrap().push(p);
        let sink = ProgressSink::new(&report);
        sink.stage(Stage::Read, 0.0);
        sink.set_triangles(1000);
        let c = StageCounter::new(&sink, Stage::Voxelize, 4);
        for _ in 0..4 {
            c.tick();
        }
        sink.stage(Stage::Write, 1.0);
        let seen = seen.into_inner().unwrap();
        assert!(seen.windows(2).all(|w| w[0].fraction <= w[1].fraction));
        assert_eq!(seen.first().unwrap().fraction, 0.0);
        assert_eq!(seen.last().unwrap().fraction, 1.0);
        assert_eq!(seen[0].triangles_per_second, 0.0);
        assert!(seen.last().unwrap().triangles_per_second > 0.0);
        assert_eq!(seen.iter().filter(|p| p.stage == Stage::Voxelize).count(), 5);
    }
}
