// Measurement, not a test: how busy the page is with N nodes at 1 kHz (long tasks, time per
// event). Usage: node tests/dashboard/measure.mjs http://127.0.0.1:PORT/ [seconds]
import { chromium } from "playwright-core";
import { mkdtempSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";

const [url, secs = "10"] = process.argv.slice(2);
const ctx = await chromium.launchPersistentContext(mkdtempSync(join(tmpdir(), "canpos-measure-")), {
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium", headless: true,
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync"],
  viewport: { width: 1400, height: 1000 },
});
const page = ctx.pages()[0] ?? await ctx.newPage();
await page.goto(url);
await page.waitForTimeout(3000);
const r = await page.evaluate(async (ms) => {
  const long = [];
  new PerformanceObserver((l) => long.push(...l.getEntries().map((e) => e.duration))).observe({ entryTypes: ["longtask"] });
  const times = [];
  const orig = window.update;
  let n = 0;
  // The page's own stream calls the global `update`: time it there.
  window.update = (s) => { const t0 = performance.now(); orig(s); times.push(performance.now() - t0); n++; };
  const f0 = performance.now();
  let frames = 0;
  const raf = () => { frames++; if (performance.now() - f0 < ms) requestAnimationFrame(raf); };
  requestAnimationFrame(raf);
  await new Promise((ok) => setTimeout(ok, ms));
  window.update = orig;
  times.sort((a, b) => a - b);
  return { events: n, median_ms: times[times.length >> 1], max_ms: times[times.length - 1],
    long_tasks: long.length, long_ms_total: long.reduce((a, b) => a + b, 0),
    nodes: window.canposDash.last.nodes.length, frames_per_s: frames / (ms / 1000) };
}, Number(secs) * 1000);
console.log(JSON.stringify(r));
await ctx.close();
