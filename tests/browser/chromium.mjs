// Headless Chromium with a SwiftShader (CPU) WebGPU adapter: what e2e.mjs and upload.mjs share.
//
// Environment: VOXSTREAM_CHROMIUM  browser binary (default /usr/bin/chromium)

import { chromium } from 'playwright-core';
import { existsSync, mkdtempSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';

export const CHROMIUM_ARGS = [
  '--headless=new',
  '--no-sandbox',
  '--enable-unsafe-webgpu',
  '--enable-features=Vulkan',
  '--use-webgpu-adapter=swiftshader',
  '--use-vulkan=swiftshader',
  '--use-angle=swiftshader',
  '--enable-unsafe-swiftshader',
  '--disable-background-networking',
  '--disable-component-update',
  '--disable-sync',
  '--no-first-run',
];

/** The browser binary, or a message saying how to get one. */
export function chromiumExecutable() {
  const path = process.env.VOXSTREAM_CHROMIUM || '/usr/bin/chromium';
  if (!existsSync(path)) {
    return { error: `${path} not found; run scripts/setup.sh (installs chromium) or set VOXSTREAM_CHROMIUM` };
  }
  return { path };
}

/**
 * A fresh browser profile dir, a clock for log lines (`since()`), and a watchdog: a wedged browser
 * must not hang the test, so after `watchdogMs` the dir is removed and the process exits 3.
 */
export function startSession(name, watchdogMs) {
  const userDataDir = mkdtempSync(join(tmpdir(), 'voxstream-chromium-'));
  const t0 = Date.now();
  const since = () => `${((Date.now() - t0) / 1000).toFixed(1)}s`;
  const watchdog = setTimeout(() => {
    console.error(`${name}: watchdog fired after ${since()}; aborting`);
    rmSync(userDataDir, { recursive: true, force: true });
    process.exit(3);
  }, watchdogMs);
  watchdog.unref();
  return { userDataDir, t0, since };
}

/**
 * Launches Chromium on a fresh `userDataDir` and returns its context and first page, with the
 * page's console and errors forwarded to stdout (errors also pushed onto `pageErrors`).
 */
export async function launchPage({ userDataDir, executablePath, viewport, since, pageErrors }) {
  const context = await chromium.launchPersistentContext(userDataDir, {
    executablePath,
    headless: true,
    args: CHROMIUM_ARGS,
    viewport,
    deviceScaleFactor: 1,
    timeout: 60000,
  });
  const page = context.pages()[0] ?? (await context.newPage());
  page.on('console', (m) => console.log(`[console.${m.type()} ${since()}] ${m.text()}`));
  page.on('pageerror', (e) => {
    pageErrors.push(String(e?.stack || e));
    console.log(`[pageerror ${since()}] ${e?.stack || e}`);
  });
  return { context, page };
}
