// The dashboard in a real browser (Debian's Chromium, driven by playwright-core): a TH sensor
// on node 127 and `canpos dashboard` on free loopback ports; the page must list the node, plot
// a motion, move the magnet (checked by another SDO client), show the missing-magnet EMCY and
// alarm, and show a bad request's error. Run: node --test tests/dashboard/
import { test, after } from "node:test";
import assert from "node:assert/strict";
import { spawn, execFileSync } from "node:child_process";
import { mkdtempSync, mkdirSync, rmSync } from "node:fs";
import { createServer } from "node:net";
import { tmpdir } from "node:os";
import { join, dirname, resolve } from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const ROOT = resolve(dirname(fileURLToPath(import.meta.url)), "../..");
const BIN = process.env.CANPOS_BIN || join(ROOT, "target/release/canpos");
const CHROMIUM = process.env.CHROMIUM || "/usr/bin/chromium";
const SHOT = join(ROOT, "target/dashboard.png");

const freePort = () => new Promise((ok, fail) => {
  const s = createServer();
  s.on("error", fail);
  s.listen(0, "127.0.0.1", () => { const p = s.address().port; s.close(() => ok(p)); });
});

const children = [];
const tmp = mkdtempSync(join(tmpdir(), "canpos-dash-"));
function start(args, ready) {
  const c = spawn(BIN, args, { stdio: ["ignore", "pipe", "pipe"] });
  children.push(c);
  let out = "";
  return new Promise((ok, fail) => {
    const t = setTimeout(() => fail(new Error(`${args[0]}: not ready in 20 s:\n${out}`)), 20000);
    const look = (d) => { out += d; if (ready.test(out)) { clearTimeout(t); ok(out); } };
    c.stdout.on("data", look);
    c.stderr.on("data", look);
    c.on("exit", (code) => { clearTimeout(t); fail(new Error(`${args[0]} exited ${code}:\n${out}`)); });
  });
}

const [busPort, ctlPort, webPort] = [await freePort(), await freePort(), await freePort()];
const BUS = `socketcand://127.0.0.1:${busPort}/can0`;
const URL = `http://127.0.0.1:${webPort}/`;
await start(["run", "--node-id", "127", "--bus", BUS, "--control", `127.0.0.1:${ctlPort}`,
  "--state-dir", join(tmp, "state"), "--magnet", "100"], /control interface on/);
await start(["dashboard", "--bus", BUS, "--listen", `127.0.0.1:${webPort}`,
  "--control", `127.0.0.1:${ctlPort}`], /canpos dashboard: http/);

const profile = join(tmp, "chromium-profile");
mkdirSync(profile);
// A fresh profile; without the background-networking flags Chromium's own connections are
// refused on a closed network and slow everything down.
const ctx = await chromium.launchPersistentContext(profile, {
  executablePath: CHROMIUM,
  headless: true,
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync"],
  viewport: { width: 1400, height: 1800 },
});
const page = ctx.pages()[0] ?? await ctx.newPage();
const node = page.locator('section.node[data-node="127"]');

after(async () => {
  await ctx.close().catch(() => {});
  for (const c of children) c.kill("SIGINT");
  rmSync(tmp, { recursive: true, force: true });
});

/** 0x6020/1 in mm, read by `canpos sdo` (another SDO client than the dashboard). */
function sdoPositionMm() {
  const read = (ix, sub) => execFileSync(BIN, ["sdo", "--bus", BUS, "read", "127", ix, sub], { encoding: "utf8" });
  const num = (s) => Number(/-?\d+/.exec(s.replace(/0x[0-9a-f]+/gi, ""))[0]);
  const steps = num(read("0x6020", "1"));
  const stepNm = num(read("0x6005", "1"));
  return steps * stepNm / 1e6;
}

test("the page loads and goes live", async () => {
  const r = await page.goto(URL);
  assert.equal(r.status(), 200);
  assert.equal(await page.title(), "canpos dashboard");
  await page.locator("#link", { hasText: "live" }).waitFor({ timeout: 10000 });
});

test("node 127 is listed with its model and NMT state", async () => {
  const row = page.locator('#nodes tr[data-node="127"]');
  await row.locator(".nmt", { hasText: "pre-operational" }).waitFor({ timeout: 10000 });
  assert.match(await row.locator(".model").innerText(), /Temposonics TH/);
  // NMT start from the page: the TPDOs begin.
  await node.locator(".nmt-command").selectOption("start");
  await node.locator(".nmt-send").click();
  await row.locator(".nmt", { hasText: /^operational$/ }).waitFor({ timeout: 10000 });
});

test("dragging the magnet changes 0x6020 as another SDO client reads it", async () => {
  const before = sdoPositionMm();
  const slider = node.locator("input.magnet");
  await slider.waitFor();
  const box = await slider.boundingBox();
  const y = box.y + box.height / 2;
  await page.mouse.move(box.x + box.width * 0.1, y);
  await page.mouse.down();
  for (let i = 1; i <= 10; i++) await page.mouse.move(box.x + box.width * (0.1 + 0.06 * i), y);
  await page.mouse.up();
  const target = Number(await slider.inputValue());
  assert.ok(target > 500, `slider at ${target} mm`);
  let now = before;
  for (let i = 0; i < 50 && Math.abs(now - target) > 1; i++) {
    await page.waitForTimeout(100);
    now = sdoPositionMm();
  }
  assert.ok(Math.abs(now - target) <= 1, `0x6020 reads ${now} mm, the slider says ${target} mm (before: ${before} mm)`);
  assert.ok(Math.abs(now - before) > 300);
});

test("the position plot moves while a motion profile runs", async () => {
  await node.locator(".motion-spec").fill("sine:center=500,amp=300,period=2");
  await node.locator(".motion-start").click();
  const canvas = node.locator('.channel[data-ch="0"] .plot-pos canvas');
  await page.waitForTimeout(1200);
  const shot1 = await canvas.screenshot();
  const span1 = await page.evaluate(() => {
    const d = window.canposDash.data[127][0];
    const recent = d.p.slice(-50).filter((v) => v != null);
    return [Math.min(...recent), Math.max(...recent), d.t[d.t.length - 1]];
  });
  await page.waitForTimeout(700);
  const shot2 = await canvas.screenshot();
  const t2 = await page.evaluate(() => { const d = window.canposDash.data[127][0]; return d.t[d.t.length - 1]; });
  assert.ok(span1[1] - span1[0] > 100, `the last second spans ${span1[0]}…${span1[1]} mm`);
  assert.ok(t2 > span1[2], "new points arrived");
  assert.ok(!shot1.equals(shot2), "the plot's pixels changed");
});

test("missing-magnet shows the EMCY and the alarm", async () => {
  await node.locator(".fault-name").selectOption("missing-magnet");
  await node.locator(".fault-on").click();
  const emcy = node.locator('.emcy tr[data-code="0x5000"]').first();
  await emcy.waitFor({ timeout: 10000 });
  assert.match(await emcy.innerText(), /transducer error/);
  await node.locator(".alarms", { hasText: "missing magnet" }).waitFor({ timeout: 10000 });
  mkdirSync(dirname(SHOT), { recursive: true });
  await page.screenshot({ path: SHOT, fullPage: true });
  await node.locator(".fault-off").click();
  await node.locator('.emcy tr[data-code="0x0000"]').first().waitFor({ timeout: 10000 });
});

test("an object is written and read over SDO from the object dictionary", async () => {
  await node.locator(".od-load").click();
  const row = node.locator('.od tr[data-key="0x1017/0"]');
  await row.waitFor({ timeout: 10000 });
  assert.match(await row.innerText(), /heartbeat/i);
  assert.match(await row.innerText(), /UNSIGNED16/);
  await row.locator(".write-value").fill("100");
  await row.locator(".write").click();
  await row.locator(".value", { hasText: /^100 / }).waitFor({ timeout: 10000 });
  const other = execFileSync(BIN, ["sdo", "--bus", BUS, "read", "127", "0x1017", "0"], { encoding: "utf8" });
  assert.match(other, /\b100\b/);
});

test("a bad request shows its error in the page and changes nothing", async () => {
  const r = await page.evaluate(async () => {
    const res = await fetch("/api/nodes/99/control", { method: "POST", body: '{"cmd":"power-cycle"}' });
    await api("POST", "/api/nodes/99/control", { cmd: "power-cycle" }).catch(() => {});
    return res.status;
  });
  assert.equal(r, 404);
  assert.match(await page.locator("#message").innerText(), /unknown node 99/);
  const od = await page.evaluate(async () => (await fetch("/api/nodes/127/sdo/0x1234/0")).status);
  assert.equal(od, 404);
});

test("a browser that leaves holds no event stream", async () => {
  await ctx.close();
  let streams = -1;
  for (let i = 0; i < 50 && streams !== 0; i++) {
    await new Promise((ok) => setTimeout(ok, 100));
    streams = (await (await fetch(`${URL}api/status`)).json()).streams;
  }
  assert.equal(streams, 0);
});
