// Occupancy worker: builds the AO volume (splat, enclosed-space fill, mips) with the viewer's
// own wasm, off the main thread, which only uploads the result.
//
//   in:  { id, grid, sources: ArrayBuffer }   sources: ao::encode_sources
//   out: { id, mips: ArrayBuffer }            all mips back to back, finest first
//        { id, error }
import init, { occupancy_for_worker } from './pkg/voxstream_viewer.js';

const ready = init();

self.onmessage = async (event) => {
  const { id, grid, sources } = event.data;
  try {
    await ready;
    const mips = occupancy_for_worker(grid, new Uint8Array(sources));
    self.postMessage({ id, mips: mips.buffer }, [mips.buffer]);
  } catch (e) {
    self.postMessage({ id, error: String(e && e.message ? e.message : e) });
  }
};
