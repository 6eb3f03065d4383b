// The AO benchmark's Chromium times: GPU time of each pass, from timestamp queries, in headless
// Chromium with its SwiftShader (CPU) WebGPU adapter. `voxstream ao-bench --browser` writes the
// spec, serves the scenes and reads the result; run by hand it needs a server already up.
//
//   node tests/browser/ao-bench.mjs <spec.json> <out.json>
//
// spec.json: {
//   "base": "http://127.0.0.1:PORT/",            a server with the viewer and the scenes
//   "width": W, "height": H,                      the canvas at scale 1 (CSS px = device px)
//   "runs": R,                                    timed frames with AO and as many without
//   "views":  [{"name", "scene", "camera": [ex,ey,ez, tx,ty,tz, fov_y_deg]}],  source units
//   "points": [{"label", "settings": {AoSettings fields}, "scale", "frames"}]
// }
// out.json: {"adapter", "rows": [{"view", "point", "width", "height", "eye_grid" (the page's eye, grid
//   units), "passes_ms": [{pass, ms}],
//   "passes_no_ao_ms": [...], "ao_ms", "frame_no_ao_ms", "ao_over_frame", "wall_ms", "wall_no_ao_ms"}]}
// where ao_ms sums the AO passes (trace, upsample, temporal) of the frame with AO and
// frame_no_ao_ms every timed pass of the frame without: the ratio `voxstream ao-bench` reports
// for the native renderer. Medians over R frames, each drawn after the previous one was timed.
//
// Environment: VOXSTREAM_CHROMIUM (browser binary), VOXSTREAM_AO_BENCH_TIMEOUT_MS (whole run,
// default 1800000).

import { readFileSync, writeFileSync } from 'node:fs';
import { chromiumExecutable, launchPage, startSession } from './chromium.mjs';

// The AO's own passes (viewer-wasm/src/shaders.rs AoPass::AO_ONLY).
const AO_PASSES = ['cs_trace', 'cs_upsample', 'cs_retrace', 'cs_temporal'];

function die(msg) {
  console.error(`ao-bench.mjs: ${msg}`);
  process.exit(1);
}

const [specPath, outPath] = process.argv.slice(2);
if (!specPath || !outPath) die('usage: node tests/browser/ao-bench.mjs <spec.json> <out.json>');
let spec;
try {
  spec = JSON.parse(readFileSync(specPath, 'utf8'));
} catch (e) {
  die(`${specPath}: ${e.message}`);
}
for (const key of ['base', 'width', 'height', 'runs', 'views', 'points']) {
  if (spec[key] === undefined) die(`${specPath}: no "${key}"`);
}
const browser = chromiumExecutable();
if (browser.error) die(browser.error);
const timeoutMs = Number(process.env.VOXSTREAM_AO_BENCH_TIMEOUT_MS || 1800000);
const { userDataDir, since } = startSession('ao-bench.mjs', timeoutMs);

const median = (xs) => {
  const s = xs.filter(Number.isFinite).sort((a, b) => a - b);
  return s.length ? s[Math.floor(s.length / 2)] : null;
};

/** Per-label medians over frames, in first-seen order (a label twice in a frame is summed first). */
function passMedians(frames) {
  const labels = [...new Set(frames.flatMap((f) => f.map((p) => p.label)))];
  return labels.map((pass) => ({
    pass,
    ms: median(frames.map((f) => f.filter((p) => p.label === pass).reduce((a, p) => a + p.ms, 0))),
  })).filter((p) => p.ms !== null);
}

/** In the page: draws frames until `count` have been timed after frame `after`; their passes and wall times. */
async function timedFrames(page, after, count) {
  return page.evaluate(
    async ({ after, count }) => {
      const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
      const out = [];
      let last = after;
      for (let tries = 0; out.length < count; tries++) {
        if (tries > 5 * count + 10) {
          throw new Error(`only ${out.length} of ${count} frames timed (does the adapter offer timestamp-query?)`);
        }
        window.voxstream.set({});
        const t0 = performance.now();
        while (performance.now() - t0 < 2000) {
          await sleep(2);
          const s = window.voxstream.stats();
          const g = s.gpuTimed;
          if (g && g.frame > last) {
            last = g.frame;
            out.push({ passes: g.passes, wall: s.frameMs });
            break;
          }
        }
      }
      return out;
    },
    { after, count },
  );
}

const frameNumber = (page) => page.evaluate(() => window.voxstream.stats().framesDrawn);

let context;
const rows = [];
let adapter = null;
try {
  let page;
  const pageErrors = [];
  ({ context, page } = await launchPage({
    userDataDir,
    executablePath: browser.path,
    viewport: { width: spec.width, height: spec.height },
    since,
    pageErrors,
  }));
  for (const view of spec.views) {
    for (const scale of [...new Set(spec.points.map((p) => p.scale))]) {
      const [w, h] = [spec.width * scale, spec.height * scale];
      const url = new URL(spec.base);
      url.searchParams.set('scene', view.scene);
      url.searchParams.set('camera', view.camera.join(','));
      url.searchParams.set('gpu-timing', '1');
      url.searchParams.set('fade', '0');
      // The page's own bars take part of the window: grow the window until the canvas draws w×h.
      let viewport = { width: w, height: h };
      let drawn;
      for (let attempt = 0; ; attempt++) {
        await page.setViewportSize(viewport);
        await page.goto(url.toString());
        await page.waitForFunction(() => document.body.dataset.ready === '1', null, { timeout: 600000 });
        if (pageErrors.length) throw new Error(`page error: ${pageErrors[0]}`);
        drawn = await page.evaluate(() => window.voxstream.view());
        if (drawn.width === w && drawn.height === h) break;
        if (attempt === 2) throw new Error(`the canvas draws ${drawn.width}x${drawn.height}, not ${w}x${h}`);
        viewport = { width: viewport.width + w - drawn.width, height: viewport.height + h - drawn.height };
      }
      const probe = await page.evaluate(() => window.voxstream.stats());
      adapter ??= await page.evaluate(async () => {
        const info = (await navigator.gpu.requestAdapter())?.info;
        const browser = navigator.userAgent.match(/(Chrom(e|ium))\/[0-9.]+/)?.[0] ?? 'Chromium';
        return `${browser}, WebGPU adapter ${info?.vendor ?? '?'} ${info?.architecture ?? '?'}`;
      });

      console.log(`[${since()}] ${view.name} ${w}x${h}: ready (${probe.blocksDrawn} blocks)`);
      for (const point of spec.points.filter((p) => p.scale === scale)) {
        const times = {};
        for (const [key, ao] of [['with', 1], ['without', 0]]) {
          await page.evaluate(([settings, ao]) => window.voxstream.set({ aoSettings: settings, ao }), [point.settings, ao]);
          // The point's accumulation frames (and at least two) settle before timing starts;
          // frames drawn before the change are never counted.
          await timedFrames(page, await frameNumber(page), Math.max(2, point.frames));
          times[key] = await timedFrames(page, await frameNumber(page), spec.runs);
        }
        const passes = passMedians(times.with.map((f) => f.passes));
        const passesNoAo = passMedians(times.without.map((f) => f.passes));
        const aoMs = passes.filter((p) => AO_PASSES.includes(p.pass)).reduce((a, p) => a + (p.ms ?? 0), 0);
        const frameNoAo = passesNoAo.reduce((a, p) => a + (p.ms ?? 0), 0);
        const row = {
          view: view.name,
          point: point.label,
          width: w,
          height: h,
          eye_grid: drawn.camera.eye,
          passes_ms: passes,
          passes_no_ao_ms: passesNoAo,
          ao_ms: aoMs,
          frame_no_ao_ms: frameNoAo,
          ao_over_frame: frameNoAo > 0 ? aoMs / frameNoAo : null,
          wall_ms: median(times.with.map((f) => f.wall)),
          wall_no_ao_ms: median(times.without.map((f) => f.wall)),
        };
        rows.push(row);
        console.log(
          `[${since()}]   ${point.label}: AO ${aoMs.toFixed(2)} ms, frame without AO ${frameNoAo.toFixed(2)} ms, ` +
            `ratio ${row.ao_over_frame?.toFixed(2)}`,
        );
      }
    }
  }
  writeFileSync(outPath, JSON.stringify({ adapter, rows }, null, 1));
} catch (e) {
  console.error(`ao-bench.mjs: ${e?.stack || e}`);
  process.exitCode = 1;
} finally {
  await context?.close().catch(() => {});
}
process.exit(process.exitCode ?? 0);
