//! upload → expand: one capped staging write a frame into runs of the face arena that the
//! residency grants within the hard byte budget, and the budget enforced after a change.

use rustc_hash::FxHashSet as HashSet;

use voxstream_format::BlockKey;

use super::{Scene, frame_target_bytes};
use crate::ao::AoStructure;
use crate::expand::{UPLOAD_BYTES_PER_FRAME, UploadPacer, upload_buffer};
use crate::render::{FADE_BUFFER_BYTES, Renderer};

impl Scene {
    /// GPU bytes of the frame's own targets: colour and depth at the viewport
    /// size, the G-buffer and AO targets, the occupancy volume with its mips,
    /// the clipmap (cells and source voxels), uniforms, the upload buffer.
    pub(super) fn fixed_gpu_bytes(&self, occupancy_cells: u32, ao_downscale: u32, clipmap_bytes: u64) -> u64 {
        let occupancy: u64 =
            (0..=occupancy_cells.max(1).ilog2()).map(|m| ((occupancy_cells >> m) as u64).pow(3)).sum();
        frame_target_bytes(self.viewport.0, self.viewport.1, ao_downscale)
            + occupancy
            + clipmap_bytes
            + 512
            + UPLOAD_BYTES_PER_FRAME
            + FADE_BUFFER_BYTES
    }

    /// Decoded needed blocks not on the GPU yet, most needed first (the request order).
    pub(super) fn awaiting_upload(&self) -> Vec<BlockKey> {
        self.needed
            .in_order()
            .map(|(k, _)| *k)
            .filter(|k| self.decoded.contains_key(k) && !self.gpu.contains_key(k))
            .collect()
    }

    /// Whether decoded blocks wait for the GPU.
    pub fn has_pending_uploads(&mut self) -> bool {
        self.update_traversal();
        self.needed.in_order().any(|(k, _)| self.decoded.contains_key(k) && !self.gpu.contains_key(k))
    }

    /// One frame's upload: needed decoded blocks, most needed first, up to
    /// `cap` bytes, in one staging write and one compute pass recorded into
    /// `encoder`, each into pooled buffers the residency grants within the
    /// budget. The caller submits `encoder` before the upload buffer is written
    /// again. Returns how many blocks went up.
    pub(super) fn upload_into(
        &mut self,
        renderer: &Renderer,
        encoder: &mut wgpu::CommandEncoder,
        cap: u64,
    ) -> usize {
        // Fixed targets first: they shrink the block budget the traversal plans within.
        self.residency.set_fixed_bytes(self.fixed_gpu_bytes(
            renderer.occupancy_cells(),
            renderer.ao.downscale(),
            if renderer.ao.structure == AoStructure::Clipmap {
                renderer.clipmap.budget_bytes(self.manifest.grid.resolution)
            } else {
                renderer.clipmap.gpu_bytes()
            },
        ));
        self.update_traversal();
        let todo = self.awaiting_upload();
        if todo.is_empty() {
            return 0;
        }
        // What this frame can draw: the needed blocks and hidden ones already
        // loaded. Last frame's other blocks will not be drawn again, so they may go.
        let mut protected: HashSet<BlockKey> = self.needed().keys().copied().collect();
        protected.extend(self.traversal.hidden.iter().filter(|k| self.gpu.contains_key(k)).copied());
        // The pacer times what the bytes cost: packing, the write, the expansion (not the traversal).
        let packing_from = (self.clock)();
        let mut batch = std::mem::take(&mut self.batch);
        for key in todo {
            let Some(cached) = self.decoded.get(&key) else { continue };
            if !batch.fits(&cached.block, cap) {
                break;
            }
            let faces = cached.faces;
            let allocate_from = (self.clock)();
            let placed = self.residency.place(
                &renderer.device,
                &renderer.block_layout,
                key,
                faces,
                self.frame_counter,
                &protected,
            );
            self.stats.note_webgpu((self.clock)() - allocate_from);
            for victim in &placed.evicted {
                self.gpu.remove(victim);
            }
            let Some(slot) = placed.slot else {
                self.stats.uploads_refused += 1;
                break;
            };
            batch.push(&cached.block, faces, slot);
        }
        if batch.is_empty() {
            self.batch = batch;
            return 0;
        }
        let webgpu_from = (self.clock)();
        let upload = self.upload.get_or_insert_with(|| upload_buffer(&renderer.device));
        batch.write(&renderer.queue, upload);
        let uploaded_bytes = batch.byte_len();
        self.stats.bytes_uploaded += uploaded_bytes;
        let blocks = renderer.expander.expand_batch(
            &renderer.device,
            encoder,
            &mut batch,
            self.residency.arena_mut(),
            upload,
            renderer.pass_timer.as_ref(),
        );
        self.batch = batch;
        let now = (self.clock)();
        self.stats.note_webgpu(now - webgpu_from);
        if let Some(pacer) = &mut self.pacer {
            pacer.record(uploaded_bytes, now - packing_from);
        }
        let n = blocks.len();
        for g in blocks {
            self.gpu.insert(g.key, g);
        }
        self.note_residency();
        n
    }

    /// Uploads until nothing needed waits (native loops; the browser uploads once per frame).
    pub fn upload_all(&mut self, renderer: &Renderer) {
        // Each batch rewrites the upload buffer, so each is submitted before the next.
        loop {
            let mut encoder = renderer
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("upload blocks") });
            if self.upload_into(renderer, &mut encoder, UPLOAD_BYTES_PER_FRAME) == 0 {
                return;
            }
            renderer.queue.submit([encoder.finish()]);
        }
    }

    /// Paces each frame's upload to `budget_ms` of main thread ([`UploadPacer`]);
    /// without it a frame uploads up to the whole upload buffer.
    pub fn pace_uploads(&mut self, budget_ms: f64) {
        self.pacer = Some(UploadPacer::new(budget_ms));
    }

    pub(super) fn note_residency(&mut self) {
        self.stats.resident_bytes = self.residency.used_bytes();
        self.stats.peak_resident_bytes = self.residency.peak_bytes();
        self.stats.budget_bytes = self.residency.budget();
    }

    /// After a budget change: evicts until within it, never what was just drawn.
    pub(super) fn enforce_budget(&mut self) {
        let protected: HashSet<BlockKey> = self.drawn.iter().copied().collect();
        for victim in self.residency.enforce_budget(&protected) {
            self.gpu.remove(&victim);
        }
    }
}
