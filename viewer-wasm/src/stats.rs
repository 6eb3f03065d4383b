//! Numbers the page shows in its stats line and returns from `window.voxstream.stats()`.

use serde::Serialize;

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Stats {
    /// Time of the last frame from the start of its encoding until the GPU finished it.
    pub frame_ms: f64,
    /// Frames drawn so far (the number the last one had).
    pub frames_drawn: u64,
    /// GPU time of each pass of the last frame timed (browser with
    /// `?gpu-timing=1` on an adapter with timestamp queries; `null` otherwise).
    pub gpu_timed: Option<crate::pass_timer::TimedFrame>,
    pub blocks_drawn: u32,
    /// Bytes of block, page and manifest responses received so far.
    pub bytes_fetched: u64,
    /// Blocks decoded and expanded on the GPU so far (cache hits are not counted again).
    pub blocks_loaded: u32,
    pub faces_drawn: u64,
    /// Hierarchy pages loaded so far.
    pub pages_loaded: u32,
    /// Blocks skipped by the last traversal because their bounds leave the frustum.
    pub culled_frustum: u32,
    /// Blocks the last traversal did not refine because feedback saw them hidden.
    pub culled_occlusion: u32,
    /// GPU bytes held now (every buffer and texture), the most ever held, and the budget.
    pub resident_bytes: u64,
    pub peak_resident_bytes: u64,
    pub budget_bytes: u64,
    pub requests_in_flight: u32,
    /// In-flight requests aborted because the view no longer needed them.
    pub requests_aborted: u32,
    /// Blocks that failed for good (fetch or decode); drawn as their ancestor.
    pub blocks_failed: u32,
    /// Bytes written to the GPU by block uploads.
    pub bytes_uploaded: u64,
    /// Uploads refused because the budget had no room.
    pub uploads_refused: u32,
    /// The longest main-thread task of the viewer so far (a frame, a worker
    /// result taken in), in ms, with the WebGPU calls it made.
    pub longest_main_task_ms: f64,
    /// The longest such task less the time spent inside WebGPU calls (surface
    /// texture, buffer and texture writes, encoding, submit, present): the
    /// viewer's own work. On a CPU WebGPU the calls hold the rasteriser's setup.
    pub longest_own_task_ms: f64,
    /// The longest time a task spent inside WebGPU calls.
    pub longest_webgpu_ms: f64,
    /// What the task of `longest_own_task_ms` was: "frame", "block taken in" or "AO volume taken in".
    pub longest_own_task_kind: &'static str,
    /// Main-thread tasks so far, and those whose own work passed 4 ms (the bound).
    pub main_tasks: u32,
    pub own_tasks_over_4ms: u32,
    /// The longest traversal and request plan, in ms: part of a frame's own work.
    pub longest_traversal_ms: f64,
    /// The longest time each step of a frame took (WebGPU calls included), in ms.
    pub longest_phases_ms: std::collections::BTreeMap<&'static str, f64>,
    /// WebGPU time of the task now running, folded in by `note_main_thread_task`.
    #[serde(skip)]
    pub webgpu_ms_in_task: f64,
    /// AO occupancy volumes uploaded so far, and how many of them a worker built.
    pub ao_volumes: u32,
    pub ao_volumes_from_worker: u32,
    /// AO clipmap updates that changed something (each a GPU compute
    /// submission), and the block splats (in or out) they ran.
    pub ao_clipmap_updates: u32,
    pub ao_clipmap_splats: u64,
    /// From the page's start to the first frame with a block on screen, and
    /// to the first complete frame (the ready marker), in ms (browser only).
    pub first_image_ms: f64,
    pub ready_ms: f64,
    #[serde(skip)]
    pub errors: u32,
    #[serde(skip)]
    pub last_error: Option<String>,
}

impl Stats {
    /// A main-thread task ended after `ms`; the WebGPU time noted during it is
    /// split off.
    pub fn note_main_thread_task(&mut self, kind: &'static str, ms: f64) {
        let webgpu = std::mem::take(&mut self.webgpu_ms_in_task).min(ms);
        let own = ms - webgpu;
        self.main_tasks += 1;
        self.own_tasks_over_4ms += (own > 4.0) as u32;
        if own > self.longest_own_task_ms {
            self.longest_own_task_ms = own;
            self.longest_own_task_kind = kind;
        }
        self.longest_main_task_ms = self.longest_main_task_ms.max(ms);
        self.longest_webgpu_ms = self.longest_webgpu_ms.max(webgpu);
    }

    /// The step `name` of a frame ended at `now`; `since` was its start and becomes `now`.
    pub fn note_phase(&mut self, name: &'static str, since: &mut f64, now: f64) {
        let longest = self.longest_phases_ms.entry(name).or_insert(0.0);
        *longest = longest.max(now - *since);
        *since = now;
    }

    /// `ms` of the running task went to WebGPU calls.
    pub fn note_webgpu(&mut self, ms: f64) {
        self.webgpu_ms_in_task += ms.max(0.0);
    }

    pub fn record_error(&mut self, message: String) {
        self.errors += 1;
        self.last_error = Some(message);
    }

    /// The stats line: short enough for one line of a narrow window.
    pub fn line(&self) -> String {
        let mut s = format!(
            "{:.1} ms · {} blocks drawn · {} faces · {} loaded · {:.2} MB fetched · {:.0}/{:.0} MiB GPU",
            self.frame_ms,
            self.blocks_drawn,
            self.faces_drawn,
            self.blocks_loaded,
            self.bytes_fetched as f64 / 1e6,
            self.resident_bytes as f64 / (1 << 20) as f64,
            self.budget_bytes as f64 / (1 << 20) as f64,
        );
        if let Some(t) = &self.gpu_timed {
            let sum = |ao: bool| {
                t.passes
                    .iter()
                    .filter(|p| crate::shaders::AoPass::is_ao_only_label(p.label) == ao)
                    .map(|p| p.ms)
                    .sum::<f64>()
            };
            s.push_str(&format!(" · GPU time {:.1} ms + AO {:.1} ms", sum(false), sum(true)));
        }
        if let Some(e) = &self.last_error {
            s.push_str(&format!(" · {} error(s), last: {e}", self.errors));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_uses_the_page_contract_names() {
        let s = Stats {
            frame_ms: 1.5,
            blocks_drawn: 2,
            bytes_fetched: 3,
            blocks_loaded: 4,
            faces_drawn: 5,
            pages_loaded: 6,
            ..Default::default()
        };
        let v: serde_json::Value = serde_json::to_value(&s).unwrap();
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        assert_eq!(keys.len(), 32);
        for k in [
            "frameMs",
            "blocksDrawn",
            "bytesFetched",
            "blocksLoaded",
            "facesDrawn",
            "pagesLoaded",
            "culledFrustum",
            "culledOcclusion",
            "residentBytes",
            "peakResidentBytes",
            "budgetBytes",
            "requestsInFlight",
            "requestsAborted",
            "blocksFailed",
            "aoVolumes",
            "aoVolumesFromWorker",
            "aoClipmapUpdates",
            "aoClipmapSplats",
            "longestOwnTaskKind",
            "ownTasksOver4ms",
            "longestTraversalMs",
            "longestPhasesMs",
            "framesDrawn",
            "gpuTimed",
        ] {
            assert!(keys.contains(&k), "missing {k}");
        }
    }

    #[test]
    fn webgpu_time_is_split_off_each_task() {
        let mut s = Stats::default();
        s.note_webgpu(30.0);
        s.note_main_thread_task("frame", 33.0);
        // A task without WebGPU calls: all its own.
        s.note_main_thread_task("block taken in", 5.0);
        assert_eq!((s.longest_main_task_ms, s.longest_own_task_ms, s.longest_webgpu_ms), (33.0, 5.0, 30.0));
        assert_eq!((s.longest_own_task_kind, s.main_tasks, s.own_tasks_over_4ms), ("block taken in", 2, 1));
        // Control: the WebGPU time does not leak into the next task.
        s.note_main_thread_task("frame", 6.0);
        assert_eq!((s.longest_own_task_ms, s.longest_own_task_kind, s.own_tasks_over_4ms), (6.0, "frame", 2));
    }

    #[test]
    fn gpu_pass_times_show_in_the_line_split_into_the_ao_and_the_rest() {
        use crate::pass_timer::{PassTime, TimedFrame};
        let mut s = Stats::default();
        assert!(!s.line().contains("GPU time"));
        let passes = [("voxels", 2.0), ("cs_trace", 0.5), ("cs_upsample", 0.25), ("fs_composite", 1.0)]
            .map(|(label, ms)| PassTime { label, ms })
            .to_vec();
        s.gpu_timed = Some(TimedFrame { frame: 7, passes });
        assert!(s.line().contains("GPU time 3.0 ms + AO 0.8 ms"), "{}", s.line());
    }

    #[test]
    fn errors_show_in_the_line() {
        let mut s = Stats::default();
        assert!(!s.line().contains("error"));
        s.record_error("block 0-0-0-0: bad magic".into());
        assert!(s.line().contains("1 error(s), last: block 0-0-0-0: bad magic"));
    }
}
