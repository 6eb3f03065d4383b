//! AO beside draw: which resident blocks feed the AO structure (the occupancy volume, built
//! in a worker in the browser, or the clipmap, splatted on the GPU), and when to rebuild it.

use rustc_hash::FxHashSet as HashSet;

use voxstream_format::BlockKey;

use super::Scene;
use crate::ao::{AoStructure, OccupancyVolume, encode_sources};
use crate::clipmap::{CLIP_CELLS, ClipmapLayout, view_forward};
use crate::render::Renderer;

/// While streaming, rebuild the occupancy volume at most this often.
const OCCUPANCY_REBUILD_MS: f64 = 400.0;

impl Scene {
    /// The occupancy payload ([`encode_sources`]) to hand to the worker, once.
    pub fn take_occupancy_job(&mut self) -> Option<Vec<u8>> {
        self.occupancy_job.take()
    }

    /// The worker's answer to the last job: the volume's mips, uploaded; an
    /// error is reported and the volume is built on the main thread from then on.
    pub fn finish_occupancy_job(&mut self, renderer: &Renderer, mips: Result<Vec<u8>, String>) {
        self.occupancy_job_in_flight = false;
        match mips.and_then(|b| OccupancyVolume::from_bytes(self.manifest.grid.resolution, &b)) {
            Ok(volume) if volume.cells == renderer.occupancy_cells() => {
                let webgpu_from = (self.clock)();
                renderer.upload_occupancy(&volume);
                self.stats.note_webgpu((self.clock)() - webgpu_from);
                self.stats.ao_volumes += 1;
                self.stats.ao_volumes_from_worker += 1;
            }
            Ok(_) => {}
            Err(e) => {
                self.stats.record_error(format!("AO volume worker: {e}; building on the main thread"));
                self.occupancy_offload = false;
                self.occupancy_for = None;
            }
        }
    }

    /// The blocks the occupancy volume is splatted from: the drawn blocks, each
    /// finer than an occupancy cell replaced by its cached ancestor whose voxels
    /// are one cell wide. Those ancestors are few, cheap to splat, and mostly
    /// independent of the view, so orbiting and refining rarely rebuild the
    /// volume and the AO does not change with the LOD.
    pub(super) fn occupancy_sources(&self, drawn: &[BlockKey], cells: u32) -> Vec<BlockKey> {
        let cell_level = (self.manifest.grid.resolution / cells.max(1)).max(1).ilog2() as u8;
        self.sources_at_level(drawn, cell_level)
    }

    /// The drawn blocks, each finer than `cell_level` replaced by its decoded
    /// ancestor at that level (a cut of the hierarchy: no two overlap).
    pub(super) fn sources_at_level(&self, drawn: &[BlockKey], cell_level: u8) -> Vec<BlockKey> {
        let mut sources: Vec<BlockKey> = drawn
            .iter()
            .map(|key| {
                let mut a = *key;
                while a.level < cell_level {
                    a = a.parent();
                }
                if self.decoded.contains_key(&a) { a } else { *key }
            })
            .collect();
        sources.sort();
        sources.dedup();
        sources
    }

    /// Rebuilds and uploads the occupancy volume when its sources changed; at
    /// most every [`OCCUPANCY_REBUILD_MS`] while blocks are still streaming in.
    pub(super) fn update_occupancy(
        &mut self,
        renderer: &mut Renderer,
        encoder: &mut wgpu::CommandEncoder,
        drawn: &[BlockKey],
        settled: bool,
        now_ms: f64,
    ) {
        if self.ao_strength <= 0.0 {
            return;
        }
        if renderer.ao.structure == AoStructure::Clipmap {
            self.update_clipmap(renderer, encoder, drawn);
            return;
        }
        let sources = self.occupancy_sources(drawn, renderer.occupancy_cells());
        if self.occupancy_for.as_ref() == Some(&sources)
            || !(settled || now_ms - self.occupancy_built_ms >= OCCUPANCY_REBUILD_MS)
        {
            return;
        }
        if self.occupancy_offload && self.occupancy_job_in_flight {
            // One build at a time; the sources are compared again after its answer.
            return;
        }
        // Nothing drawn yet: the texture starts out empty, no need to splat nothing.
        if self.occupancy_offload && (!sources.is_empty() || self.occupancy_for.is_some()) {
            self.occupancy_job = Some(encode_sources(sources.iter().filter_map(|k| self.block(k))));
            self.occupancy_job_in_flight = true;
        } else if !sources.is_empty() || self.occupancy_for.is_some() {
            let volume = OccupancyVolume::build(
                self.manifest.grid.resolution,
                sources.iter().filter_map(|k| self.block(k)),
            );
            if volume.cells == renderer.occupancy_cells() {
                renderer.upload_occupancy(&volume);
                self.stats.ao_volumes += 1;
            }
        }
        self.occupancy_for = Some(sources);
        self.occupancy_built_ms = now_ms;
    }

    /// Brings the clipmap to this frame's camera and drawn blocks, every
    /// frame (incremental: only scrolled-in slabs and blocks that arrived or
    /// left are splatted, on the GPU). Level k splats the drawn blocks cut at
    /// its cell's LOD level; the finest cell is the finest drawn voxel.
    pub(super) fn update_clipmap(
        &mut self,
        renderer: &mut Renderer,
        encoder: &mut wgpu::CommandEncoder,
        drawn: &[BlockKey],
    ) {
        let Some(finest) = drawn.iter().map(|k| k.level).min() else { return };
        let resolution = self.manifest.grid.resolution;
        let layout = ClipmapLayout::for_scene(resolution, 1u32 << finest.min(30), CLIP_CELLS);
        let sources: Vec<Vec<BlockKey>> =
            (0..layout.levels).map(|k| self.sources_at_level(drawn, layout.cell(k).ilog2() as u8)).collect();
        let eye = self.eye();
        let forward = view_forward(self.view_proj(), eye);
        self.give_clipmap_room(renderer, &sources, drawn);
        let before = renderer.clipmap.counters;
        renderer.update_clipmap(encoder, resolution, layout, (eye, forward), &sources, |k| self.block(k));
        let after = renderer.clipmap.counters;
        self.stats.ao_clipmap_updates += (after.updates - before.updates) as u32;
        self.stats.ao_clipmap_splats += after.splats - before.splats;
    }

    /// The clipmap's source voxels are GPU memory too: before its buffer
    /// grows to hold `sources`, the residency makes room for them (evicting
    /// blocks neither drawn nor needed), and the clipmap may grow only into
    /// the room there is, so the budget holds.
    fn give_clipmap_room(&mut self, renderer: &mut Renderer, sources: &[Vec<BlockKey>], drawn: &[BlockKey]) {
        let mut distinct: HashSet<BlockKey> = HashSet::default();
        let mut words = 0u64;
        for key in sources.iter().flatten() {
            if distinct.insert(*key)
                && let Some(b) = self.block(key)
            {
                words += b.voxels.len() as u64;
            }
        }
        let held = renderer.clipmap.source_bytes();
        if words * 4 > held && words * 4 - held > self.residency.headroom() {
            let mut protected: HashSet<BlockKey> = self.needed().keys().copied().collect();
            protected.extend(drawn.iter().copied());
            for victim in self.residency.make_headroom(words * 4 - held, &protected) {
                self.gpu.remove(&victim);
            }
        }
        renderer.clipmap.limit_source_bytes(held + self.residency.headroom());
    }
}
