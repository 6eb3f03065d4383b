// tus-js-client 4 (the official JavaScript tus client, npm `tus-js-client`) in Node against
// `voxstream serve`, run by server/tests/tus_clients.rs:
//
//   node tests/browser/tus_client.mjs create <endpoint> <file> <token> <scene-id> <chunk-bytes>
//       starts the upload and aborts it after the first chunk (the connection is cut); prints the URL.
//   node tests/browser/tus_client.mjs resume <upload-url> <file> <token> <chunk-bytes>
//       a new process resumes from the upload URL alone (HEAD for the offset) and finishes;
//       prints the offset it started from and the final one.

import { readFileSync } from 'node:fs';
import { basename } from 'node:path';
import * as tus from 'tus-js-client';

function die(msg) {
  console.error(`tus_client.mjs: ${msg}`);
  process.exit(1);
}

const [mode, ...args] = process.argv.slice(2);

if (mode === 'create') {
  const [endpoint, path, token, scene, chunk] = args;
  const bytes = readFileSync(path);
  const upload = new tus.Upload(bytes, {
    endpoint,
    chunkSize: Number(chunk),
    headers: { Authorization: `Bearer ${token}` },
    metadata: { filename: basename(path), id: scene },
    retryDelays: [],
    onChunkComplete: () => {
      // The first chunk is stored: cut here, as a closed laptop would.
      upload.abort(false).then(() => {
        console.log(upload.url);
        process.exit(0);
      });
    },
    onError: (e) => die(`create: ${e}`),
    onSuccess: () => die('create: the upload finished in one chunk; use a smaller chunk'),
  });
  upload.start();
} else if (mode === 'resume') {
  const [url, path, token, chunk] = args;
  const bytes = readFileSync(path);
  let start = null;
  const upload = new tus.Upload(bytes, {
    uploadUrl: url,
    chunkSize: Number(chunk),
    headers: { Authorization: `Bearer ${token}` },
    retryDelays: [],
    // The first PATCH starts at the offset the server reported (HEAD): where this process resumed.
    onBeforeRequest: (req) => {
      if (start === null && req.getMethod() === 'PATCH') start = req.getHeader('Upload-Offset');
    },
    onError: (e) => die(`resume: ${e}`),
    onSuccess: () => {
      console.log(`${start} ${bytes.length}`);
      process.exit(0);
    },
  });
  upload.start();
} else {
  die(`unknown mode ${mode}`);
}
