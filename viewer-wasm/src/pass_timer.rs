//! GPU time of each pass of a frame, from timestamp queries, on devices that
//! have them (native Vulkan, lavapipe included; the browser with `?gpu-timing=1`).
//! A frame's timed passes write a timestamp as they begin and end;
//! [`PassTimer::resolve`] copies them into a mappable buffer at the end of the
//! frame's encoder. A native caller reads them once the GPU is idle
//! ([`PassTimer::read`]); the browser maps the buffer asynchronously after the
//! submit ([`PassTimer::after_submit`]) and skips timing the frames drawn while
//! a read is under way, so no frame ever waits for one.
//!
//! Why timestamps and not the wall clock around a frame: on a real GPU the AO
//! passes take well under a millisecond, less than the CPU's own cost of
//! encoding and waiting, so `frame with AO − frame without` is mostly noise
//! there.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

/// Passes a frame can time (a query pair each).
pub const MAX_TIMED_PASSES: u32 = 16;

/// Timestamp queries over the passes of one frame.
pub struct PassTimer {
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    readback: wgpu::Buffer,
    /// Nanoseconds per timestamp tick.
    period_ns: f64,
    /// This frame's timed passes, in the order their pairs were handed out.
    labels: RefCell<Vec<&'static str>>,
    /// Passes resolved into `readback` by the last frame (its labels' prefix).
    resolved: Cell<u32>,
    /// The frame being recorded (the caller's number, from `begin_frame`).
    #[cfg_attr(not(target_arch = "wasm32"), allow(dead_code))]
    frame: Cell<u64>,
    /// Browser: `readback` is being mapped; frames resolve nothing meanwhile.
    mapping: Rc<Cell<bool>>,
    /// Browser: the last frame read back asynchronously.
    latest: Rc<RefCell<Option<TimedFrame>>>,
}

/// One pass's GPU time.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PassTime {
    pub label: &'static str,
    pub ms: f64,
}

/// The pass times of one frame, read back in the browser.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
#[serde(rename_all = "camelCase")]
pub struct TimedFrame {
    /// The number `begin_frame` was given for it.
    pub frame: u64,
    pub passes: Vec<PassTime>,
}

impl PassTimer {
    /// `None` when the device was not created with [`wgpu::Features::TIMESTAMP_QUERY`].
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Option<Self> {
        if !device.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            return None;
        }
        let count = 2 * MAX_TIMED_PASSES;
        let bytes = count as u64 * wgpu::QUERY_SIZE as u64;
        let query_set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("pass timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count,
        });
        let resolve = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pass timestamps, resolved"),
            size: bytes,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pass timestamps, readback"),
            size: bytes,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        Some(Self {
            query_set,
            resolve,
            readback,
            period_ns: queue.get_timestamp_period() as f64,
            labels: RefCell::new(Vec::new()),
            resolved: Cell::new(0),
            frame: Cell::new(0),
            mapping: Rc::new(Cell::new(false)),
            latest: Rc::new(RefCell::new(None)),
        })
    }

    /// Forgets the last frame's passes: the next pairs start at 0. `frame`
    /// numbers the frame for [`PassTimer::latest`].
    pub fn begin_frame(&self, frame: u64) {
        self.labels.borrow_mut().clear();
        self.frame.set(frame);
    }

    /// The next query pair for a pass named `label`; `None` once every pair is taken.
    fn pair(&self, label: &'static str) -> Option<u32> {
        let mut labels = self.labels.borrow_mut();
        let index = labels.len() as u32;
        (index < MAX_TIMED_PASSES).then(|| {
            labels.push(label);
            2 * index
        })
    }

    /// Timestamp writes for a render pass named `label`.
    pub fn render_writes(&self, label: &'static str) -> Option<wgpu::RenderPassTimestampWrites<'_>> {
        self.pair(label).map(|i| wgpu::RenderPassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: Some(i),
            end_of_pass_write_index: Some(i + 1),
        })
    }

    /// Timestamp writes for a compute pass named `label`.
    pub fn compute_writes(&self, label: &'static str) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        self.pair(label).map(|i| wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: Some(i),
            end_of_pass_write_index: Some(i + 1),
        })
    }

    /// Copies this frame's timestamps to the readback buffer (last in the frame's encoder).
    pub fn resolve(&self, encoder: &mut wgpu::CommandEncoder) {
        // A mapped (or mapping) buffer cannot be copied into: this frame goes untimed.
        let passes = if self.mapping.get() { 0 } else { self.labels.borrow().len() as u32 };
        self.resolved.set(passes);
        if passes == 0 {
            return;
        }
        encoder.resolve_query_set(&self.query_set, 0..2 * passes, &self.resolve, 0);
        encoder.copy_buffer_to_buffer(
            &self.resolve,
            0,
            &self.readback,
            0,
            2 * passes as u64 * wgpu::QUERY_SIZE as u64,
        );
    }

    /// Browser: after the submit of a frame that [`PassTimer::resolve`]d,
    /// maps the readback buffer; when the GPU is done the times become
    /// [`PassTimer::latest`]. Native: nothing (use [`PassTimer::read`]).
    pub fn after_submit(&self) {
        #[cfg(target_arch = "wasm32")]
        {
            let passes = self.resolved.replace(0) as usize;
            if passes == 0 {
                return;
            }
            self.mapping.set(true);
            let labels: Vec<&'static str> = self.labels.borrow()[..passes].to_vec();
            let (frame, period_ns) = (self.frame.get(), self.period_ns);
            let (mapping, latest, buffer) =
                (self.mapping.clone(), self.latest.clone(), self.readback.clone());
            self.readback.slice(..).map_async(wgpu::MapMode::Read, move |result| {
                if result.is_ok() {
                    let ticks: Option<Vec<u64>> = buffer.get_mapped_range(..).ok().map(|bytes| {
                        bytes
                            .chunks_exact(8)
                            .take(2 * passes)
                            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
                            .collect()
                    });
                    buffer.unmap();
                    if let Some(ticks) = ticks {
                        let passes = ticks_to_times(&ticks, &labels, period_ns);
                        *latest.borrow_mut() = Some(TimedFrame { frame, passes });
                    }
                }
                mapping.set(false);
            });
        }
    }

    /// The last frame read back by [`PassTimer::after_submit`] (browser).
    pub fn latest(&self) -> Option<TimedFrame> {
        self.latest.borrow().clone()
    }

    /// The last resolved frame's pass times, in pass order (native: blocks
    /// until the copy is done). A pass the device reports out of order (end
    /// before start) reads as NaN rather than a wrapped huge number.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn read(&self, device: &wgpu::Device) -> Result<Vec<PassTime>, crate::offscreen::OffscreenError> {
        let passes = self.resolved.get();
        if passes == 0 {
            return Ok(Vec::new());
        }
        let bytes = crate::offscreen::map_and_read_on(device, &self.readback)?;
        let ticks: Vec<u64> = bytes
            .chunks_exact(8)
            .take(2 * passes as usize)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
            .collect();
        let labels = self.labels.borrow();
        Ok(ticks_to_times(&ticks, &labels[..passes as usize], self.period_ns))
    }
}

/// Pass times from (start, end) tick pairs in pass order.
pub fn ticks_to_times(ticks: &[u64], labels: &[&'static str], period_ns: f64) -> Vec<PassTime> {
    labels
        .iter()
        .zip(ticks.chunks_exact(2))
        .map(|(&label, pair)| PassTime {
            label,
            ms: match pair[1].checked_sub(pair[0]) {
                Some(d) => d as f64 * period_ns * 1e-6,
                None => f64::NAN,
            },
        })
        .collect()
}

/// Median milliseconds per pass label over several frames' times (labels in
/// first-seen order; a pass missing from some frames has the median of those
/// it is in; NaN samples are left out).
pub fn median_by_label(frames: &[Vec<PassTime>]) -> Vec<PassTime> {
    let mut labels: Vec<&'static str> = Vec::new();
    for t in frames.iter().flatten() {
        if !labels.contains(&t.label) {
            labels.push(t.label);
        }
    }
    labels
        .into_iter()
        .map(|label| {
            // A label twice in a frame (e.g. two passes of one kind) is summed first.
            let mut samples: Vec<f64> = frames
                .iter()
                .filter(|f| f.iter().any(|t| t.label == label))
                .map(|f| f.iter().filter(|t| t.label == label).map(|t| t.ms).sum::<f64>())
                .filter(|ms| ms.is_finite())
                .collect();
            samples.sort_by(f64::total_cmp);
            let ms = samples.get(samples.len() / 2).copied().unwrap_or(f64::NAN);
            PassTime { label, ms }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_become_milliseconds_in_pass_order() {
        // 1 tick = 1 ns: 2 ms and 0.5 ms.
        let t = ticks_to_times(&[1_000_000, 3_000_000, 3_000_000, 3_500_000], &["a", "b"], 1.0);
        assert_eq!(t, vec![PassTime { label: "a", ms: 2.0 }, PassTime { label: "b", ms: 0.5 }]);
        // Control: a pass whose end precedes its start is NaN, not 1.8e13 ms.
        let t = ticks_to_times(&[5, 4], &["a"], 1.0);
        assert!(t[0].ms.is_nan());
        // A period other than 1 ns scales.
        let t = ticks_to_times(&[0, 1000], &["a"], 2.5);
        assert!((t[0].ms - 0.0025).abs() < 1e-12);
    }

    #[test]
    fn medians_are_per_label_and_sum_repeats_within_a_frame() {
        let frame = |v: &[(&'static str, f64)]| v.iter().map(|&(label, ms)| PassTime { label, ms }).collect();
        let frames = vec![
            frame(&[("draw", 1.0), ("ao", 0.2), ("ao", 0.1)]),
            frame(&[("draw", 3.0), ("ao", 0.4)]),
            frame(&[("draw", 2.0), ("ao", f64::NAN)]),
        ];
        let m = median_by_label(&frames);
        assert_eq!(m[0], PassTime { label: "draw", ms: 2.0 });
        // ao: 0.3 (summed), 0.4, NaN left out: the upper of two.
        assert_eq!(m[1].label, "ao");
        assert!((m[1].ms - 0.4).abs() < 1e-12, "{m:?}");
        assert_eq!(median_by_label(&[]), Vec::new());
    }
}
