// Measurement, not a test (issue 38): the bus trace with 10 TH sensors at a 1 ms event timer on
// one bus (10,000 frames/s). Starts a hub, a scenario of 10 operational sensors and a standalone
// `canpos dashboard` on free loopback ports, opens the page in Debian's Chromium and measures,
// for the trace's row view, its log view and the row view paused in turn: the page's animation frames per second,
// its long tasks, and the CPU time of the dashboard process (/proc/PID/stat utime + stime).
// Usage: CANPOS_BIN=target/release/canpos node tests/dashboard/measure-trace.mjs [seconds]
import { spawn } from "node:child_process";
import { readFileSync, writeFileSync } from "node:fs";
import { join } from "node:path";
import { BIN, freePorts, rig } from "./rig.mjs";

const secs = Number(process.argv[2] || "10");
const SENSORS = 10;
const rg = rig("measure-trace");
const { tmp } = rg;
const start = (args, ready) => rg.start(args, ready, 60000);

try {
  const [busPort, webPort] = await freePorts(2);
  const bus = `socketcand://127.0.0.1:${busPort}/can0`;
  await start(["bus", "serve", "--listen", `127.0.0.1:${busPort}`], /listening on/);
  let toml = `bus = "${bus}"\nstate_dir = "${join(tmp, "state")}"\n`;
  for (let i = 0; i < SENSORS; i++) {
    toml += `\n[[sensor]]\nmodel = "th"\nnode_id = ${i + 1}\nserial = ${2001 + i}\nmotion = "sine:center=500,amp=300,period=4"\n`;
  }
  writeFileSync(join(tmp, "ten.toml"), toml);
  await start(["scenario", join(tmp, "ten.toml")], /sensor 9|node-id 10/);
  const dash = await start(["dashboard", "--bus", bus, "--listen", `127.0.0.1:${webPort}`], /canpos dashboard: http/);
  // All operational: 10 TPDOs every millisecond.
  await new Promise((ok) => spawn(BIN, ["nmt", "--bus", bus, "start"]).on("exit", ok));
  const cpu = () => {
    const f = readFileSync(`/proc/${dash.pid}/stat`, "utf8").split(") ")[1].split(" ");
    return (Number(f[11]) + Number(f[12])) / 100; // utime + stime, clock ticks of 10 ms
  };
  const { page } = await rg.browser({ viewport: { width: 1400, height: 1000 } });
  await page.goto(`http://127.0.0.1:${webPort}/`);
  await page.waitForTimeout(3000);
  const measure = async (mode) => {
    // "paused": the row view, paused (what the rest of the page costs).
    await page.locator("#trace-mode").selectOption(mode === "paused" ? "rows" : mode);
    if (mode === "paused") await page.locator("#trace-pause").click();
    await page.locator("#bus-tool-box").scrollIntoViewIfNeeded();
    await page.waitForTimeout(1000);
    const c0 = cpu();
    const r = await page.evaluate(async (ms) => {
      const long = [];
      new PerformanceObserver((l) => long.push(...l.getEntries().map((e) => e.duration))).observe({ entryTypes: ["longtask"] });
      const p0 = window.canposTrace.polls;
      // trace.js's `render` is a global: time each call there (the rest of a poll is network).
      const times = [];
      const orig = window.render;
      window.render = (...a) => { const t0 = performance.now(); orig(...a); times.push(performance.now() - t0); };
      const f0 = performance.now();
      let frames = 0;
      const raf = () => { frames++; if (performance.now() - f0 < ms) requestAnimationFrame(raf); };
      requestAnimationFrame(raf);
      await new Promise((ok) => setTimeout(ok, ms));
      window.render = orig;
      times.sort((x, y) => x - y);
      const t = window.canposTrace.last;
      return { frames_per_s: frames / (ms / 1000), long_tasks: long.length,
        long_ms_total: Math.round(long.reduce((a, b) => a + b, 0)),
        trace_polls_per_s: (window.canposTrace.polls - p0) / (ms / 1000),
        render_median_ms: times.length ? Number(times[times.length >> 1].toFixed(2)) : null,
        render_max_ms: times.length ? Number(times[times.length - 1].toFixed(2)) : null,
        rows: t.rows.length, bus_frames_per_s: Math.round(t.frames_per_s), bus_load_pct: t.bus_load_pct };
    }, secs * 1000);
    const used = cpu() - c0;
    return { mode, ...r, dashboard_cpu_s: Number(used.toFixed(2)), dashboard_cpu_pct_of_one_core: Number((used / secs * 100).toFixed(1)) };
  };
  for (const m of ["rows", "log", "paused"]) console.log(JSON.stringify(await measure(m)));
} finally {
  await rg.close();
}
