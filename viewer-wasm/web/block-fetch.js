// One block's bytes. Through the API: GET its own URL. On a static site (voxstream publish):
// GET `packs/<hash>.vxp?r=<start>-<end>` with `Range: bytes=<start>-<end>`; the query gives
// each block a URL of its own, so no cache mixes two ranges of one pack. A host that honours
// Range answers 206 with the block; one that ignores it answers 200 with the whole pack, which
// is sliced here. Either way the caller checks the block's hash.
//
//   range: null, or { start, end } (inclusive byte offsets in the pack)
//   returns { bytes: Uint8Array, fetched: bytes received }
export async function fetchBlockBytes(url, range, key, signal) {
  const init = { signal };
  if (range) init.headers = { Range: `bytes=${range.start}-${range.end}` };
  const response = await fetch(url, init);
  if (!response.ok) throw new Error(`block ${key}: HTTP ${response.status}`);
  const body = new Uint8Array(await response.arrayBuffer());
  if (!range) return { bytes: body, fetched: body.byteLength };
  const want = range.end - range.start + 1;
  if (response.status === 206) {
    if (body.byteLength !== want) {
      throw new Error(`block ${key}: HTTP 206 with ${body.byteLength} bytes, asked for ${want}`);
    }
    return { bytes: body, fetched: body.byteLength };
  }
  // 200: the host ignored Range and sent the whole pack.
  if (body.byteLength <= range.end) {
    throw new Error(`block ${key}: the pack is ${body.byteLength} bytes, the block ends at byte ${range.end}`);
  }
  return { bytes: body.subarray(range.start, range.end + 1), fetched: body.byteLength };
}
