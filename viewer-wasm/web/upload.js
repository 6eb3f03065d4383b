// voxstream upload page: a dropped mesh goes up with tus 1.0 through the official tus-js-client
// (vendored by scripts/build-web.sh from its npm package into vendor/tus.min.js: chunks, retries
// with HEAD after a lost connection, resuming after a reload), its build is followed over
// server-sent events, and the catalog lists the scenes with thumbnails. Page contract:
// notes/CONTRACTS.md.

/* global tus */

const $ = (id) => document.getElementById(id);

/** Bytes per PATCH; `?chunk=<bytes>` (at least 64 KiB) overrides, e.g. to watch small files move. */
const CHUNK_BYTES = Math.max(Number(new URLSearchParams(window.location.search).get('chunk')) || 8 << 20, 64 << 10);
/** Waits between attempts to continue an upload after a lost connection; then it gives up. */
const RETRY_DELAYS_MS = [0, 1000, 2000, 4000, 8000, 15000];
/** Consecutive failed polls of a job before giving up. */
const MAX_RETRIES = 6;
const FORMATS = ['ply', 'obj', 'stl', 'glb', 'gltf'];
const TOKEN_KEY = 'voxstream.token';

// ---- small helpers --------------------------------------------------------------------------

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function authHeaders(headers = {}) {
  const token = $('token').value.trim();
  return token ? { ...headers, Authorization: `Bearer ${token}` } : headers;
}

function formatBytes(n) {
  if (!Number.isFinite(n)) return '–';
  const units = ['B', 'KiB', 'MiB', 'GiB', 'TiB'];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) {
    n /= 1024;
    i += 1;
  }
  return `${i === 0 ? n : n.toFixed(n < 10 ? 1 : 0)} ${units[i]}`;
}

function formatSeconds(s) {
  if (!Number.isFinite(s)) return '–';
  if (s < 60) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
  const m = Math.floor(s / 60);
  return m < 60 ? `${m} min ${Math.round(s % 60)} s` : `${Math.floor(m / 60)} h ${m % 60} min`;
}

const formatCount = (n) => (Number.isFinite(n) ? n.toLocaleString('en-US') : '–');

/** Sets a progress bar to `fraction` (0..1), keeping aria-valuenow in step for assistive tech and tests. */
function setBar(bar, fraction) {
  const percent = Math.round(Math.min(Math.max(fraction, 0), 1) * 1000) / 10;
  bar.value = percent;
  bar.setAttribute('aria-valuenow', String(percent));
}

/** A readable sentence for an API error (JSON body {"error": "..."}). */
function explain(status, message) {
  switch (status) {
    case 401:
      return `${message}. Enter the server's access token under Options.`;
    case 403:
      return `Not allowed: ${message}`;
    case 409:
      return `${message}; on this page: tick “replace” under Options, or enter another scene id.`;
    case 413:
      return `The file is too large for this server: ${message}`;
    case 415:
      return `The server cannot read this file: ${message}`;
    case 429:
      return `Slow down: ${message}`;
    default:
      return `${message} (HTTP ${status})`;
  }
}

function errorFromBody(status, text, statusText = '') {
  let message = statusText || 'request failed';
  try {
    const body = JSON.parse(text);
    if (body && typeof body.error === 'string') message = body.error;
  } catch {
    if (text) message = text.slice(0, 200);
  }
  const e = new Error(explain(status, message));
  e.status = status;
  return e;
}

async function api(method, url, { headers = {}, body } = {}) {
  const resp = await fetch(url, { method, headers: authHeaders(headers), body });
  if (!resp.ok) throw errorFromBody(resp.status, await resp.text(), resp.statusText);
  return resp;
}

function showError(message) {
  const el = $('error');
  el.textContent = message;
  el.hidden = !message;
}

// ---- one upload and build ---------------------------------------------------------------------

/** The upload and build in progress: { file, upload, jobId, events, cancelled, finished }. */
let current = null;

function uploadMetadata(file) {
  const meta = { filename: file.name };
  if (file.type) meta.filetype = file.type;
  const id = $('scene-id').value.trim();
  if (id) meta.id = id;
  const resolution = $('resolution').value;
  if (resolution) meta.resolution = resolution;
  if ($('replace').checked) meta.replace = 'true';
  return meta;
}

/** The sentence for a failed tus request: the server's JSON error, or a lost connection. */
function uploadError(err, confirmed) {
  const res = err && err.originalResponse;
  const status = res ? res.getStatus() : 0;
  if (status > 0) return errorFromBody(status, res.getBody() || '', '');
  return new Error(
    `the upload stopped at ${formatBytes(confirmed)}: the server could not be reached ` +
      `${RETRY_DELAYS_MS.length} times in a row. Drop the same file again to resume.`,
  );
}

/**
 * Sends the file with tus-js-client, resuming an upload a reloaded page had started. Resolves with
 * the id of the build job the finished upload became (the server names it in `Voxstream-Job` on the
 * last PATCH, or on HEAD when the upload was already complete).
 */
function sendFile(run) {
  const size = run.file.size;
  const bar = $('upload-progress');
  const started = performance.now();
  let confirmed = 0;
  let firstSent = null;
  const show = (sent, note = '') => {
    // The bar shows what the server confirmed, so it never goes back after a lost connection;
    // 100 % only once the last byte is stored.
    setBar(bar, Math.min(confirmed / size, 0.999));
    if (firstSent === null) firstSent = sent;
    const seconds = (performance.now() - started) / 1000;
    const rate = seconds > 0.5 ? ` · ${formatBytes((sent - firstSent) / seconds)}/s` : '';
    $('upload-status').textContent = `${formatBytes(sent)} of ${formatBytes(size)}${rate}${note}`;
  };
  const meta = uploadMetadata(run.file);
  return new Promise((resolve, reject) => {
    const upload = new tus.Upload(run.file, {
      endpoint: '/api/uploads',
      chunkSize: CHUNK_BYTES,
      retryDelays: RETRY_DELAYS_MS,
      metadata: meta,
      headers: authHeaders(),
      // The same file with other options (id, resolution, replace) is another upload.
      fingerprint: (file) =>
        Promise.resolve(`voxstream:${JSON.stringify([file.name, file.size, file.lastModified, meta])}`),
      removeFingerprintOnSuccess: true,
      // Retry lost connections, server errors and offset disagreements on PATCH/HEAD; a refused
      // creation (409: the scene exists) is an answer, not a glitch.
      onShouldRetry: (err) => {
        const status = err.originalResponse ? err.originalResponse.getStatus() : 0;
        const method = err.originalRequest ? err.originalRequest.getMethod() : '';
        if (status === 0 || status >= 500) return true;
        return method !== 'POST' && (status === 409 || status === 423);
      },
      onProgress: (sent) => show(sent),
      onChunkComplete: (_chunk, accepted) => {
        confirmed = accepted;
        show(accepted);
      },
      onAfterResponse: (_req, res) => {
        const job = res.getHeader('Voxstream-Job');
        if (job) run.jobId = job;
        const offset = Number(res.getHeader('Upload-Offset'));
        if (Number.isFinite(offset) && offset > confirmed) confirmed = offset;
      },
      onSuccess: () => {
        if (run.jobId) resolve(run.jobId);
        else reject(new Error('the server stored the whole file but started no build'));
      },
      onError: (err) => reject(run.cancelled ? new Error('cancelled') : uploadError(err, confirmed)),
    });
    run.upload = upload;
    upload
      .findPreviousUploads()
      .then((previous) => {
        if (previous.length > 0) upload.resumeFromPreviousUpload(previous[0]);
        if (!run.cancelled) upload.start();
      })
      .catch(() => upload.start());
  });
}

function showJob(job) {
  setBar($('build-progress'), job.state === 'done' ? 1 : job.fraction || 0);
  const parts = [job.state];
  if (job.stage && job.state === 'running') parts.push(job.stage);
  parts.push(`${Math.round((job.state === 'done' ? 1 : job.fraction || 0) * 100)} %`);
  if (job.state === 'running' && Number.isFinite(job.eta_seconds)) {
    parts.push(`about ${formatSeconds(job.eta_seconds)} left`);
  }
  if (job.state === 'running' && job.triangles_per_second > 0) {
    parts.push(`${formatCount(Math.round(job.triangles_per_second))} triangles/s`);
  }
  $('build-status').textContent = parts.join(' · ');
}

/** Follows the job until it ends: server-sent events, or polling where EventSource cannot
 * authenticate (a server that protects reading). Resolves with the final job. */
function followJob(run) {
  const id = run.jobId;
  return new Promise((resolve, reject) => {
    let settled = false;
    const settle = (job) => {
      if (settled) return;
      showJob(job);
      if (!['done', 'failed', 'cancelled'].includes(job.state)) return;
      settled = true;
      run.events?.close();
      if (job.state === 'done') resolve(job);
      else if (job.state === 'cancelled') reject(new Error('cancelled'));
      else reject(new Error(`The build failed: ${job.error || 'no reason given'}`));
    };
    const poll = async () => {
      let failures = 0;
      while (!settled) {
        try {
          const resp = await api('GET', `/api/jobs/${id}`);
          settle(await resp.json());
          failures = 0;
        } catch (e) {
          failures += 1;
          if (e.status === 401 || e.status === 404 || failures > MAX_RETRIES) {
            settled = true;
            reject(e);
            return;
          }
        }
        await sleep(700);
      }
    };
    const events = new EventSource(`/api/jobs/${id}/events`);
    run.events = events;
    for (const name of ['progress', 'done', 'failed', 'cancelled']) {
      events.addEventListener(name, (e) => settle(JSON.parse(e.data)));
    }
    events.onerror = () => {
      // CONNECTING: the browser reconnects by itself. CLOSED: refused (e.g. 401); poll instead.
      if (events.readyState === EventSource.CLOSED && !settled) {
        events.close();
        poll();
      }
    };
  });
}

async function startUpload(file) {
  showError('');
  if (current && !current.finished) {
    showError('An upload is still running: cancel it or wait for it to finish.');
    return;
  }
  const ext = file.name.includes('.') ? file.name.split('.').pop().toLowerCase() : '';
  if (!FORMATS.includes(ext)) {
    showError(`${file.name}: “.${ext}” is not a mesh format this server reads (PLY, OBJ, STL, GLB, glTF).`);
    return;
  }
  if (file.size === 0) {
    showError(`${file.name} is empty.`);
    return;
  }
  const run = { file, cancelled: false, finished: false };
  current = run;
  $('job').hidden = false;
  $('job-file').textContent = `${file.name} (${formatBytes(file.size)})`;
  $('open-viewer').hidden = true;
  $('cancel').disabled = false;
  setBar($('upload-progress'), 0);
  setBar($('build-progress'), 0);
  $('upload-status').textContent = 'starting…';
  $('build-status').textContent = 'waits for the upload';
  try {
    run.jobId = await sendFile(run);
    setBar($('upload-progress'), 1);
    $('upload-status').textContent = `${formatBytes(file.size)} uploaded`;
    $('build-status').textContent = 'queued';
    const job = await followJob(run);
    const link = $('open-viewer');
    link.href = `index.html?scene=${encodeURIComponent(job.scene_id)}`;
    link.textContent = `Open “${job.scene_id}” in the viewer`;
    link.hidden = false;
    try {
      const scene = await (await api('GET', `/api/scenes/${encodeURIComponent(job.scene_id)}`)).json();
      const seconds = scene.build_seconds == null ? '' : ` in ${formatSeconds(scene.build_seconds)}`;
      $('build-status').textContent = `done · ${formatCount(scene.voxels)} voxels, ${formatBytes(scene.bytes_on_disk)}${seconds}`;
    } catch {
      // The job's own "done" line stays.
    }
  } catch (e) {
    if (run.cancelled || e.message === 'cancelled') {
      $('build-status').textContent = run.jobId ? 'cancelled' : $('build-status').textContent;
      if (!run.jobId) $('upload-status').textContent = 'cancelled';
    } else {
      showError(e.message);
    }
  } finally {
    run.finished = true;
    $('cancel').disabled = true;
    refreshScenes();
  }
}

async function cancelRun() {
  const run = current;
  if (!run || run.finished) return;
  try {
    if (run.jobId) {
      // The job ends as cancelled; its event stream reports it.
      await api('POST', `/api/jobs/${run.jobId}/cancel`);
    } else {
      run.cancelled = true;
      // Stops the PATCH in flight and DELETEs the upload on the server (tus termination).
      await run.upload?.abort(true);
    }
  } catch (e) {
    showError(e.message);
  }
}

// ---- the catalog ------------------------------------------------------------------------------

let thumbnailUrls = [];

/** Thumbnails go through fetch so a token travels with them (an <img src> cannot send one). */
async function loadThumbnail(img, id) {
  try {
    const resp = await api('GET', `/api/scenes/${encodeURIComponent(id)}/thumbnail.png`);
    const url = URL.createObjectURL(await resp.blob());
    thumbnailUrls.push(url);
    img.src = url;
  } catch (e) {
    img.alt = 'no thumbnail';
    img.title = e.message;
  }
}

function cell(row, content, className) {
  const td = row.insertCell();
  if (className) td.className = className;
  if (content instanceof Node) td.append(content);
  else td.textContent = content;
  return td;
}

function sceneRow(tbody, scene) {
  const row = tbody.insertRow();
  row.dataset.scene = scene.id;
  const viewerUrl = `index.html?scene=${encodeURIComponent(scene.id)}`;

  const img = document.createElement('img');
  img.className = 'thumb';
  img.width = 96;
  img.height = 96;
  img.alt = `${scene.name}`;
  const thumbLink = document.createElement('a');
  thumbLink.href = viewerUrl;
  thumbLink.append(img);
  cell(row, thumbLink);
  loadThumbnail(img, scene.id);

  const name = document.createElement('a');
  name.href = viewerUrl;
  name.className = 'scene-name';
  name.textContent = scene.name;
  const source = document.createElement('small');
  source.textContent = `${scene.id} · ${scene.source_file} · ${scene.resolution}³`;
  const nameCell = cell(row, name);
  nameCell.append(document.createElement('br'), source);

  cell(row, formatCount(scene.triangles), 'num');
  cell(row, formatCount(scene.voxels), 'num');
  cell(row, formatBytes(scene.bytes_on_disk), 'num');
  cell(row, scene.build_seconds == null ? '–' : formatSeconds(scene.build_seconds), 'num');

  const rename = document.createElement('button');
  rename.type = 'button';
  rename.textContent = 'Rename';
  rename.onclick = async () => {
    const next = prompt(`New display name for ${scene.id}`, scene.name);
    if (next === null || next.trim() === '' || next === scene.name) return;
    try {
      await api('PATCH', `/api/scenes/${encodeURIComponent(scene.id)}`, {
        headers: { 'Content-Type': 'application/json' },
        body: JSON.stringify({ name: next.trim() }),
      });
      refreshScenes();
    } catch (e) {
      showError(e.message);
    }
  };
  const del = document.createElement('button');
  del.type = 'button';
  del.textContent = 'Delete';
  del.onclick = async () => {
    if (!confirm(`Delete scene “${scene.name}” (${scene.id})? This cannot be undone.`)) return;
    try {
      await api('DELETE', `/api/scenes/${encodeURIComponent(scene.id)}`);
      refreshScenes();
    } catch (e) {
      showError(e.message);
    }
  };
  const actions = cell(row, rename, 'row-actions');
  actions.append(del);
}

let refreshing = null;

async function refreshScenes() {
  // One refresh at a time; a request during one runs once it ends.
  if (refreshing) {
    refreshing.again = true;
    return;
  }
  refreshing = { again: false };
  try {
    const scenes = await (await api('GET', '/api/scenes')).json();
    const tbody = $('scene-list').tBodies[0];
    for (const url of thumbnailUrls) URL.revokeObjectURL(url);
    thumbnailUrls = [];
    tbody.replaceChildren();
    for (const scene of scenes) sceneRow(tbody, scene);
    $('scenes-empty').hidden = scenes.length > 0;
    $('scene-list').hidden = scenes.length === 0;
  } catch (e) {
    showError(`Cannot list the scenes: ${e.message}`);
  } finally {
    const again = refreshing.again;
    refreshing = null;
    if (again) refreshScenes();
  }
}

// ---- wiring -----------------------------------------------------------------------------------

function init() {
  const token = $('token');
  try {
    token.value = localStorage.getItem(TOKEN_KEY) || '';
  } catch {
    // No storage: the token lives for this page only.
  }
  token.addEventListener('change', () => {
    try {
      if (token.value.trim()) localStorage.setItem(TOKEN_KEY, token.value.trim());
      else localStorage.removeItem(TOKEN_KEY);
    } catch {
      // As above.
    }
    refreshScenes();
  });

  const zone = $('drop-zone');
  const input = $('file-input');
  zone.addEventListener('click', () => input.click());
  zone.addEventListener('keydown', (e) => {
    if (e.key === 'Enter' || e.key === ' ') {
      e.preventDefault();
      input.click();
    }
  });
  input.addEventListener('change', () => {
    if (input.files.length > 0) startUpload(input.files[0]);
    input.value = ''; // the same file can be chosen again
  });
  for (const type of ['dragenter', 'dragover']) {
    zone.addEventListener(type, (e) => {
      e.preventDefault();
      zone.classList.add('over');
    });
  }
  zone.addEventListener('dragleave', () => zone.classList.remove('over'));
  zone.addEventListener('drop', (e) => {
    e.preventDefault();
    zone.classList.remove('over');
    const files = e.dataTransfer?.files;
    if (!files || files.length === 0) {
      showError('Nothing to upload: drop a file, not a link or text.');
      return;
    }
    startUpload(files[0]);
    if (files.length > 1) showError(`Uploading ${files[0].name} only: one file at a time.`);
  });
  // A file dropped beside the zone must not replace the page with the file.
  window.addEventListener('dragover', (e) => e.preventDefault());
  window.addEventListener('drop', (e) => e.preventDefault());

  // Enter in an option field must not submit (and reload) the page.
  $('options-form').addEventListener('submit', (e) => e.preventDefault());
  $('cancel').addEventListener('click', cancelRun);
  $('refresh').addEventListener('click', refreshScenes);
  refreshScenes();
}

init();
