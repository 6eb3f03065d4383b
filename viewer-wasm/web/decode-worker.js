// Decode worker: fetches a block and decodes and checks it with the viewer's
// own wasm (voxstream_format), off the main thread. The main thread gets the
// voxels as a transferred ArrayBuffer, ready to upload.
//
//   in:  { id, url, key, voxels }   voxels: the count the manifest states, or -1
//        { abort: id }              the view no longer needs it
//   out: { id, key, ok: true, voxels: ArrayBuffer, fetched }
//        { id, key, ok: false, error, fetched }
import init, { decode_block_for_worker } from './pkg/voxstream_viewer.js';

const ready = init();
const inFlight = new Map();

self.onmessage = async (event) => {
  const msg = event.data;
  if (msg.abort !== undefined) {
    inFlight.get(msg.abort)?.abort();
    return;
  }
  const { id, url, key, voxels } = msg;
  const abort = new AbortController();
  inFlight.set(id, abort);
  let fetched = 0;
  try {
    const response = await fetch(url, { signal: abort.signal });
    if (!response.ok) throw new Error(`block ${key}: HTTP ${response.status}`);
    const bytes = new Uint8Array(await response.arrayBuffer());
    fetched = bytes.byteLength;
    await ready;
    const out = decode_block_for_worker(key, bytes, voxels);
    self.postMessage({ id, key, ok: true, voxels: out.buffer, fetched }, [out.buffer]);
  } catch (e) {
    const error = e && e.name === 'AbortError' ? 'aborted' : String(e && e.message ? e.message : e);
    self.postMessage({ id, key, ok: false, error, fetched });
  } finally {
    inFlight.delete(id);
  }
};
