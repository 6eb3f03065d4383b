// Browser end-to-end harness for the upload page.
//
//   node tests/browser/upload.mjs <base-url> <mesh-file> <out-dir>
//
// Opens <base-url>/upload.html?chunk=1048576 in headless Chromium (SwiftShader WebGPU, as e2e.mjs),
// drops <mesh-file> onto #drop-zone as a DataTransfer drop event, cuts the connection of the second
// PATCH once (the page must ask HEAD for the offset and go on), records every value the two
// progress bars take, waits for both at 100 % and the link into the viewer, screenshots the page
// into <out-dir>/upload.png, follows the link, waits for document.body.dataset.ready === "1" and
// writes what it saw to <out-dir>/upload.json. tests/tests/browser.rs checks the JSON.
//
// Environment: VOXSTREAM_CHROMIUM (default /usr/bin/chromium), VOXSTREAM_E2E_TIMEOUT_MS (default 240000).

import { mkdirSync, readFileSync, rmSync, writeFileSync } from 'node:fs';
import { basename, join } from 'node:path';
import { chromiumExecutable, launchPage, startSession } from './chromium.mjs';

const CHUNK = 1 << 20;

function die(msg) {
  console.error(`upload.mjs: ${msg}`);
  process.exit(1);
}

const [base, meshPath, outDir] = process.argv.slice(2);
if (!base || !meshPath || !outDir) die('usage: node tests/browser/upload.mjs <base-url> <mesh-file> <out-dir>');
const browser = chromiumExecutable();
if (browser.error) die(browser.error);
const executablePath = browser.path;
const timeoutMs = Number(process.env.VOXSTREAM_E2E_TIMEOUT_MS || 240000);

mkdirSync(outDir, { recursive: true });
const { userDataDir, t0, since } = startSession('upload.mjs', 2 * timeoutMs + 60000);

/** Drops a file onto #drop-zone the way a browser does: dragenter, dragover, drop with a DataTransfer. */
async function dropFile(page, name, bytes) {
  await page.evaluate(
    ({ b64, name }) => {
      const bin = atob(b64);
      const data = new Uint8Array(bin.length);
      for (let i = 0; i < bin.length; i++) data[i] = bin.charCodeAt(i);
      const transfer = new DataTransfer();
      transfer.items.add(new File([data], name, { type: 'application/octet-stream' }));
      const zone = document.getElementById('drop-zone');
      for (const type of ['dragenter', 'dragover', 'drop']) {
        zone.dispatchEvent(new DragEvent(type, { bubbles: true, cancelable: true, dataTransfer: transfer }));
      }
    },
    { b64: Buffer.from(bytes).toString('base64'), name },
  );
}

let context;
let failure = null;
const pageErrors = [];
const requests = [];
try {
  let page;
  const viewport = { width: 1000, height: 800 };
  ({ context, page } = await launchPage({ userDataDir, executablePath, viewport, since, pageErrors }));
  page.on('response', (r) => {
    if (r.url().includes('/api/uploads')) {
      requests.push({ method: r.request().method(), status: r.status(), offset: r.headers()['upload-offset'] ?? null });
    }
    if (r.status() >= 400) console.log(`[http ${r.status()} ${since()}] ${r.request().method()} ${r.url()}`);
  });

  // Cut the second PATCH once, before the server sees it: the page must resume from HEAD's offset.
  let patches = 0;
  let cut = 0;
  await page.route('**/api/uploads/*', async (route) => {
    if (route.request().method() === 'PATCH' && ++patches === 2) {
      cut += 1;
      console.log(`[upload ${since()}] cutting PATCH #${patches}`);
      await route.abort('connectionreset');
      return;
    }
    await route.continue();
  });

  const url = `${base}/upload.html?chunk=${CHUNK}`;
  console.log(`[upload ${since()}] opening ${url}`);
  await page.goto(url, { waitUntil: 'load', timeout: 60000 });
  await page.waitForSelector('#scenes-empty:not([hidden])', { timeout: 30000 });

  // Every value each bar takes, in order.
  await page.evaluate(() => {
    window.__bars = { upload: [], build: [] };
    for (const [name, id] of [['upload', 'upload-progress'], ['build', 'build-progress']]) {
      const bar = document.getElementById(id);
      new MutationObserver(() => {
        const v = Number(bar.getAttribute('aria-valuenow'));
        const seen = window.__bars[name];
        if (seen[seen.length - 1] !== v) seen.push(v);
      }).observe(bar, { attributes: true, attributeFilter: ['aria-valuenow'] });
    }
  });

  // The page uploads through the vendored tus-js-client (window.tus), not code of its own.
  const tusClient = await page.evaluate(
    () => typeof window.tus?.Upload === 'function' && typeof window.tus?.isSupported === 'boolean',
  );
  const bytes = readFileSync(meshPath);
  const name = basename(meshPath);
  console.log(`[upload ${since()}] dropping ${name} (${bytes.length} bytes) onto #drop-zone`);
  await dropFile(page, name, bytes);

  console.log(`[upload ${since()}] waiting for both bars at 100 % and the viewer link`);
  try {
    await page.waitForFunction(
      () => {
        const err = document.getElementById('error');
        if (!err.hidden && err.textContent) throw new Error(`page error: ${err.textContent}`);
        return (
          document.getElementById('upload-progress').getAttribute('aria-valuenow') === '100' &&
          document.getElementById('build-progress').getAttribute('aria-valuenow') === '100' &&
          !document.getElementById('open-viewer').hidden
        );
      },
      null,
      { timeout: timeoutMs, polling: 100 },
    );
  } catch (e) {
    const state = await page.evaluate(() => ({
      upload: document.getElementById('upload-status').textContent,
      build: document.getElementById('build-status').textContent,
      error: document.getElementById('error').textContent,
    }));
    throw new Error(`the upload never finished: ${JSON.stringify(state)} (${e.message.split('\n')[0]})`);
  }
  const sceneRow = 'tr[data-scene] img.thumb';
  await page.waitForFunction(
    (sel) => [...document.querySelectorAll(sel)].some((img) => img.complete && img.naturalWidth > 0),
    sceneRow,
    { timeout: 60000, polling: 100 },
  );
  console.log(`[upload ${since()}] build done; scene listed with its thumbnail`);

  const page1 = await page.evaluate(() => {
    const text = (id) => document.getElementById(id).textContent;
    const rows = [...document.querySelectorAll('#scene-list tbody tr')].map((tr) => ({
      id: tr.dataset.scene,
      cells: [...tr.cells].map((td) => td.textContent.trim()),
      thumbnail: (() => {
        const img = tr.querySelector('img.thumb');
        return { width: img.naturalWidth, height: img.naturalHeight, src: img.src };
      })(),
      links: [...tr.querySelectorAll('a')].map((a) => a.getAttribute('href')),
    }));
    return {
      bars: window.__bars,
      upload: { value: text('upload-status'), aria: document.getElementById('upload-progress').getAttribute('aria-valuenow') },
      build: { value: text('build-status'), aria: document.getElementById('build-progress').getAttribute('aria-valuenow') },
      uploadValue: document.getElementById('upload-progress').value,
      buildValue: document.getElementById('build-progress').value,
      link: document.getElementById('open-viewer').getAttribute('href'),
      error: document.getElementById('error').hidden ? null : text('error'),
      rows,
    };
  });
  await page.screenshot({ path: join(outDir, 'upload.png'), fullPage: true });

  console.log(`[upload ${since()}] following ${page1.link}`);
  await Promise.all([page.waitForURL(/index\.html\?scene=/, { timeout: 60000 }), page.click('#open-viewer')]);
  try {
    await page.waitForFunction(() => document.body && document.body.dataset.ready === '1', null, {
      timeout: timeoutMs,
      polling: 250,
    });
  } catch (e) {
    const statsLine = await page.evaluate(() => document.getElementById('voxstream-stats')?.textContent);
    throw new Error(`the viewer never became ready: ${statsLine} (${e.message.split('\n')[0]})`);
  }
  const viewer = await page.evaluate(() => ({
    url: location.href,
    stats: window.voxstream.stats(),
    uploadLink: document.getElementById('voxstream-upload-link')?.getAttribute('href') ?? null,
  }));
  console.log(`[upload ${since()}] viewer ready: ${JSON.stringify(viewer.stats)}`);
  await page.screenshot({ path: join(outDir, 'upload-viewer.png') });

  // Errors read as sentences: a file that is no mesh, and the same scene uploaded again.
  await page.goto(`${base}/upload.html`, { waitUntil: 'load', timeout: 60000 });
  await page.waitForSelector('tr[data-scene]', { timeout: 30000 });
  const errorAfterDrop = async (fileName, data) => {
    await dropFile(page, fileName, data);
    await page.waitForSelector('#error:not([hidden])', { timeout: 30000 });
    return page.evaluate(() => document.getElementById('error').textContent);
  };
  const errors = {
    notMesh: await errorAfterDrop('notes.txt', Buffer.from('not a mesh')),
    exists: await errorAfterDrop(name, bytes),
  };
  console.log(`[upload ${since()}] error messages: ${JSON.stringify(errors)}`);

  writeFileSync(
    join(outDir, 'upload.json'),
    JSON.stringify(
      { base, file: name, bytes: bytes.length, chunk: CHUNK, tusClient, cutPatches: cut, requests, page: page1, viewer, errors, pageErrors, elapsedMs: Date.now() - t0 },
      null,
      2,
    ),
  );
  console.log(`[upload ${since()}] wrote ${join(outDir, 'upload.json')}`);
} catch (e) {
  failure = e;
} finally {
  if (context) await context.close().catch(() => {});
  rmSync(userDataDir, { recursive: true, force: true });
}
if (failure) die(failure?.stack || String(failure));
process.exit(0);
