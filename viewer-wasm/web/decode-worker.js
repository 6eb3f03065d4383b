// Decode worker: fetches a block and decodes and checks it with the viewer's
// own wasm (voxstream_format), off the main thread. The main thread gets the
// voxels as a transferred ArrayBuffer, ready to upload, followed by the block's
// occupied cells and face count (DecodedBlock::to_message in decode.rs), so it
// never walks the voxels itself.
//
//   in:  { id, url, key, voxels, hash, start?, end? }
//        voxels: the count the manifest states, or -1; hash: the block's blake3, or ''
//        start/end: on a static site, the block's bytes [start, end] (inclusive) of the pack at url
//        { abort: id }              the view no longer needs it
//   out: { id, key, ok: true, voxels: ArrayBuffer (voxels, cells, face count), fetched }
//        { id, key, ok: false, error, fetched }
import init, { decode_block_for_worker } from './pkg/voxstream_viewer.js';
import { fetchBlockBytes } from './block-fetch.js';

const ready = init();
const inFlight = new Map();

self.onmessage = async (event) => {
  const msg = event.data;
  if (msg.abort !== undefined) {
    inFlight.get(msg.abort)?.abort();
    return;
  }
  const { id, url, key, voxels, hash, start, end } = msg;
  const abort = new AbortController();
  inFlight.set(id, abort);
  let fetched = 0;
  try {
    const range = start === undefined ? null : { start, end };
    const got = await fetchBlockBytes(url, range, key, abort.signal);
    fetched = got.fetched;
    await ready;
    // The hash check catches a wrong slice or a host that sent other bytes.
    const out = decode_block_for_worker(key, got.bytes, voxels, hash || '');
    self.postMessage({ id, key, ok: true, voxels: out.buffer, fetched }, [out.buffer]);
  } catch (e) {
    const error = e && e.name === 'AbortError' ? 'aborted' : String(e && e.message ? e.message : e);
    self.postMessage({ id, key, ok: false, error, fetched });
  } finally {
    inFlight.delete(id);
  }
};
