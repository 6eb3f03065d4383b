// Browser end-to-end harness for voxstream.
//
//   node tests/browser/e2e.mjs <url> <out-dir>
//
// Opens <url> in headless Chromium with a SwiftShader (CPU) WebGPU adapter, forwards the page's
// console to stdout, waits until the viewer sets document.body.dataset.ready = "1", then writes
//   <out-dir>/browser.png   screenshot of the #voxstream-canvas element
//   <out-dir>/browser.json  { stats, view, viewAfter, ... } from window.voxstream
// Exit status 0 on success, non-zero (with a reason on stderr) otherwise. The Rust test
// tests/tests/browser.rs drives this script and checks the outputs.
//
// Environment:
//   VOXSTREAM_CHROMIUM        browser binary (default /usr/bin/chromium)
//   VOXSTREAM_E2E_TIMEOUT_MS  how long to wait for dataset.ready (default 240000; SwiftShader is slow)
//   VOXSTREAM_E2E_CPU_PROFILE  write the page's V8 CPU profile (load to ready) to this .cpuprofile
//                              file, for DevTools or scripts/cpuprofile-summary.py
//   VOXSTREAM_E2E_TRACE        write the page's trace (load to ready; devtools.timeline, with each
//                              main-thread task's wall and thread time) to this .json file, for
//                              DevTools or scripts/trace-tasks.py

import { mkdirSync, rmSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { chromiumExecutable, launchPage, startSession } from './chromium.mjs';

const VIEWPORT = { width: 640, height: 480 };
const CANVAS = '#voxstream-canvas';

function die(msg) {
  console.error(`e2e.mjs: ${msg}`);
  process.exit(1);
}

const [url, outDir] = process.argv.slice(2);
if (!url || !outDir) die('usage: node tests/browser/e2e.mjs <url> <out-dir>');
const browser = chromiumExecutable();
if (browser.error) die(browser.error);
const executablePath = browser.path;
const readyTimeoutMs = Number(process.env.VOXSTREAM_E2E_TIMEOUT_MS || 240000);
if (!Number.isFinite(readyTimeoutMs) || readyTimeoutMs <= 0) die('bad VOXSTREAM_E2E_TIMEOUT_MS');

mkdirSync(outDir, { recursive: true });
const { userDataDir, t0, since } = startSession('e2e.mjs', readyTimeoutMs + 120000);

let context;
let failure = null;
const pageErrors = [];
try {
  let page;
  ({ context, page } = await launchPage({ userDataDir, executablePath, viewport: VIEWPORT, since, pageErrors }));
  page.on('requestfailed', (r) => console.log(`[requestfailed ${since()}] ${r.url()} ${r.failure()?.errorText}`));
  page.on('response', (r) => {
    if (r.status() >= 400) console.log(`[http ${r.status()} ${since()}] ${r.url()}`);
  });
  page.on('crash', () => console.log(`[crash ${since()}] page crashed`));

  const cpuProfile = process.env.VOXSTREAM_E2E_CPU_PROFILE;
  let profiler = null;
  if (cpuProfile) {
    profiler = await context.newCDPSession(page);
    await profiler.send('Profiler.enable');
    await profiler.send('Profiler.setSamplingInterval', { interval: 100 });
    await profiler.send('Profiler.start');
  }
  const tracePath = process.env.VOXSTREAM_E2E_TRACE;
  let tracer = null;
  const traceEvents = [];
  let traceDone = null;
  if (tracePath) {
    tracer = await context.newCDPSession(page);
    tracer.on('Tracing.dataCollected', (e) => traceEvents.push(...e.value));
    traceDone = new Promise((resolve) => tracer.once('Tracing.tracingComplete', resolve));
    await tracer.send('Tracing.start', {
      transferMode: 'ReportEvents',
      traceConfig: {
        includedCategories: ['devtools.timeline', 'disabled-by-default-devtools.timeline', 'toplevel', 'v8.execute'],
        excludedCategories: ['*'],
      },
    });
  }
  console.log(`[e2e ${since()}] opening ${url}`);
  await page.goto(url, { waitUntil: 'load', timeout: 60000 });
  const gpu = await page.evaluate(async () => {
    if (!navigator.gpu) return { error: 'navigator.gpu is undefined (WebGPU unavailable)' };
    const a = await navigator.gpu.requestAdapter();
    if (!a) return { error: 'requestAdapter() returned null' };
    return { vendor: a.info?.vendor, architecture: a.info?.architecture, description: a.info?.description };
  });
  console.log(`[e2e ${since()}] WebGPU adapter: ${JSON.stringify(gpu)}`);
  if (gpu.error) throw new Error(gpu.error);

  console.log(`[e2e ${since()}] waiting up to ${readyTimeoutMs / 1000}s for document.body.dataset.ready === "1"`);
  try {
    await page.waitForFunction(() => document.body && document.body.dataset.ready === '1', null, {
      timeout: readyTimeoutMs,
      polling: 250,
    });
  } catch (e) {
    const state = await page
      .evaluate(() => ({
        ready: document.body?.dataset.ready ?? null,
        statsLine: document.getElementById('voxstream-stats')?.textContent ?? null,
        hasApi: typeof window.voxstream === 'object' && window.voxstream !== null,
        stats: window.voxstream?.stats?.() ?? null,
      }))
      .catch((err) => ({ evaluateFailed: String(err) }));
    throw new Error(`page never became ready within ${readyTimeoutMs / 1000}s: ${JSON.stringify(state)} (${e.message.split('\n')[0]})`);
  }
  console.log(`[e2e ${since()}] page ready`);
  if (profiler) {
    const { profile } = await profiler.send('Profiler.stop');
    writeFileSync(cpuProfile, JSON.stringify(profile));
    console.log(`[e2e ${since()}] wrote the CPU profile to ${cpuProfile}`);
  }
  if (tracer) {
    await tracer.send('Tracing.end');
    await traceDone;
    writeFileSync(tracePath, JSON.stringify({ traceEvents }));
    console.log(`[e2e ${since()}] wrote ${traceEvents.length} trace events to ${tracePath}`);
  }

  const snapshot = () =>
    page.evaluate(() => {
      if (typeof window.voxstream?.stats !== 'function' || typeof window.voxstream?.view !== 'function') {
        throw new Error('window.voxstream.stats()/view() missing');
      }
      return { stats: window.voxstream.stats(), view: window.voxstream.view() };
    });
  const before = await snapshot();
  const canvas = page.locator(CANVAS);
  if ((await canvas.count()) !== 1) throw new Error(`expected exactly one ${CANVAS} element`);
  const canvasBox = await canvas.evaluate((c) => ({
    width: c.width,
    height: c.height,
    clientWidth: c.clientWidth,
    clientHeight: c.clientHeight,
  }));
  await canvas.screenshot({ path: join(outDir, 'browser.png'), animations: 'disabled', timeout: 60000 });
  const after = await snapshot();

  // VOXSTREAM_E2E_INTERACT=1: the screenshot button and double-click re-centring, after the
  // still-view checks above (they move the camera).
  let interact = null;
  if (process.env.VOXSTREAM_E2E_INTERACT === '1') {
    const [download] = await Promise.all([
      page.waitForEvent('download', { timeout: 60000 }),
      page.click('#vs-screenshot'),
    ]);
    await download.saveAs(join(outDir, 'download.png'));
    const pickAfter = async (x, y) => {
      const answered = await page.evaluate(() => window.voxstream.view().picksAnswered);
      await canvas.dblclick({ position: { x, y } });
      await page.waitForFunction((n) => window.voxstream.view().picksAnswered > n, answered, {
        timeout: 60000,
        polling: 100,
      });
      return (await snapshot()).view;
    };
    const corner = await pickAfter(2, 2);
    const centre = await pickAfter(canvasBox.clientWidth / 2, canvasBox.clientHeight / 2);
    interact = {
      download: download.suggestedFilename(),
      cornerPick: corner.pick,
      cornerTarget: corner.camera.target,
      centrePick: centre.pick,
      centreTarget: centre.camera.target,
    };
    console.log(`[e2e ${since()}] interactions ${JSON.stringify(interact)}`);
  }

  const result = {
    url,
    elapsedMs: Date.now() - t0,
    userAgent: await page.evaluate(() => navigator.userAgent),
    adapter: gpu,
    viewport: VIEWPORT,
    canvas: canvasBox,
    stats: before.stats,
    view: before.view,
    statsAfter: after.stats,
    viewAfter: after.view,
    interact,
    pageErrors,
  };
  writeFileSync(join(outDir, 'browser.json'), JSON.stringify(result, null, 2));
  console.log(`[e2e ${since()}] stats ${JSON.stringify(before.stats)}`);
  console.log(`[e2e ${since()}] wrote ${join(outDir, 'browser.png')} and browser.json`);
} catch (e) {
  failure = e;
} finally {
  if (context) await context.close().catch(() => {});
  rmSync(userDataDir, { recursive: true, force: true });
}
if (failure) die(failure?.stack || String(failure));
process.exit(0);
