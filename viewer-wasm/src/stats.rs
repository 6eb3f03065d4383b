//! Numbers the page shows in its stats line and returns from `window.voxstream.stats()`.

use serde::Serialize;

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Stats {
    /// Time of the last frame from the start of its encoding until the GPU finished it.
    pub frame_ms: f64,
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
    /// The longest main-thread task of the viewer's own code so far (a frame's
    /// encoding, a worker result taken in), in ms: WebGPU's own work excluded.
    pub longest_main_task_ms: f64,
    /// AO occupancy volumes uploaded so far, and how many of them a worker built.
    pub ao_volumes: u32,
    pub ao_volumes_from_worker: u32,
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
    pub fn note_main_thread_task(&mut self, ms: f64) {
        self.longest_main_task_ms = self.longest_main_task_ms.max(ms);
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
        assert_eq!(keys.len(), 21);
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
        ] {
            assert!(keys.contains(&k), "missing {k}");
        }
    }

    #[test]
    fn errors_show_in_the_line() {
        let mut s = Stats::default();
        assert!(!s.line().contains("error"));
        s.record_error("block 0-0-0-0: bad magic".into());
        assert!(s.line().contains("1 error(s), last: block 0-0-0-0: bad magic"));
    }
}
