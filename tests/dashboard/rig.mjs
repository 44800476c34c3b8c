// The set-up the dashboard's browser tests (and measurements) share: canpos processes on free
// loopback ports, a temporary directory, Debian's Chromium in a fresh profile, and the cleanup
// of all three. Not a test itself (node --test runs *.test.mjs only).
import { spawn } from "node:child_process";
import { mkdtempSync, mkdirSync, rmSync } from "node:fs";
import { createServer } from "node:net";
import { tmpdir } from "node:os";
import { join, dirname, resolve } from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

export const ROOT = resolve(dirname(fileURLToPath(import.meta.url)), "../..");
export const BIN = process.env.CANPOS_BIN || join(ROOT, "target/release/canpos");
export const CHROMIUM = process.env.CHROMIUM || "/usr/bin/chromium";
export const DOCS = join(ROOT, "docs");

/** A TCP port free on loopback now. */
export const freePort = () => new Promise((ok, fail) => {
  const s = createServer();
  s.on("error", fail);
  s.listen(0, "127.0.0.1", () => { const p = s.address().port; s.close(() => ok(p)); });
});

/** `n` free ports. */
export async function freePorts(n) {
  const out = [];
  for (let i = 0; i < n; i++) out.push(await freePort());
  return out;
}

// Without the background-networking flags Chromium's own connections are refused on a closed
// network and slow everything down.
const CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
  "--disable-background-networking", "--disable-component-update", "--disable-sync"];

/**
 * A rig named `name`: `tmp`, a directory removed by `close()`;
 * `spawn(args, ready, ms)`, canpos started with `args`: `{ child, ready }`, `ready` a promise of
 * its output once it matches the regex `ready` (rejected if it exits first or after `ms`);
 * `start(args, ready, ms)`, the same, waited for: the child process;
 * `browser(options)`, Chromium on a fresh profile (extra `args`, `viewport`, any other
 * playwright option): `{ ctx, page }`;
 * `close()`, which ends the browser and every process started, and removes `tmp`.
 */
export function rig(name) {
  const tmp = mkdtempSync(join(tmpdir(), `canpos-${name}-`));
  const children = [];
  let ctx = null;
  function spawnCanpos(args, ready, ms = 30000) {
    const child = spawn(BIN, args, { stdio: ["ignore", "pipe", "pipe"] });
    children.push(child);
    let out = "";
    const up = new Promise((ok, fail) => {
      const t = setTimeout(() => fail(new Error(`${args.join(" ")}: not ready in ${ms / 1000} s:\n${out}`)), ms);
      const look = (d) => { out += d; if (ready.test(out)) { clearTimeout(t); ok(out); } };
      child.stdout.on("data", look);
      child.stderr.on("data", look);
      child.on("exit", (code) => { clearTimeout(t); fail(new Error(`${args[0]} exited ${code}:\n${out}`)); });
    });
    return { child, ready: up };
  }
  async function start(args, ready, ms) {
    const { child, ready: up } = spawnCanpos(args, ready, ms);
    await up;
    return child;
  }
  async function browser({ args = [], ...options } = {}) {
    const profile = join(tmp, "chromium-profile");
    mkdirSync(profile);
    ctx = await chromium.launchPersistentContext(profile, {
      executablePath: CHROMIUM, headless: true, args: [...CHROMIUM_ARGS, ...args], ...options,
    });
    return { ctx, page: ctx.pages()[0] ?? await ctx.newPage() };
  }
  async function close() {
    if (ctx) await ctx.close().catch(() => {});
    for (const c of children) c.kill("SIGINT");
    rmSync(tmp, { recursive: true, force: true });
  }
  return { tmp, spawn: spawnCanpos, start, browser, close };
}

/** `f()` every 100 ms until it gives something truthy, which is returned; fails after `ms`. */
export async function until(what, f, ms = 15000) {
  const t0 = Date.now();
  let last;
  while (Date.now() - t0 < ms) {
    last = await f();
    if (last) return last;
    await new Promise((ok) => setTimeout(ok, 100));
  }
  throw new Error(`${what}: not within ${ms / 1000} s (last: ${JSON.stringify(last)})`);
}
