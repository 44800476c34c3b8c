// The dashboard in a real browser (Debian's Chromium, driven by playwright-core): a TH sensor
// on node 127 and `canpos dashboard` on free loopback ports; the page must list the node, plot
// a motion, move the magnet (checked by another SDO client), show the missing-magnet EMCY and
// alarm, and show a bad request's error; another site's page and a DNS-rebinding page change
// nothing. Run: node --test tests/dashboard/
import { test, after } from "node:test";
import assert from "node:assert/strict";
import { execFileSync } from "node:child_process";
import { mkdirSync } from "node:fs";
import { createServer as createHttpServer } from "node:http";
import { join, dirname } from "node:path";
import { BIN, ROOT, freePorts, rig } from "./rig.mjs";

const SHOT = join(ROOT, "target/dashboard.png");
const r = rig("dash");
const [busPort, ctlPort, webPort, evilPort] = await freePorts(4);
const BUS = `socketcand://127.0.0.1:${busPort}/can0`;
const URL = `http://127.0.0.1:${webPort}/`;
await r.start(["run", "--node-id", "127", "--bus", BUS, "--control", `127.0.0.1:${ctlPort}`,
  "--state-dir", join(r.tmp, "state"), "--magnet", "100"], /control interface on/);
await r.start(["dashboard", "--bus", BUS, "--listen", `127.0.0.1:${webPort}`,
  "--control", `127.0.0.1:${ctlPort}`], /canpos dashboard: http/);

// attacker.example resolves to the dashboard, as a DNS-rebinding attacker's name would.
const { ctx, page } = await r.browser({
  args: ["--host-resolver-rules=MAP attacker.example 127.0.0.1"],
  viewport: { width: 1400, height: 1800 },
});
const node = page.locator('section.node[data-node="127"]');

// Another site: a page on another loopback port that posts to the dashboard.
const evilSite = createHttpServer((req, res) => {
  res.writeHead(200, { "content-type": "text/html" });
  res.end("<!doctype html><title>another site</title>");
});
await new Promise((ok) => evilSite.listen(evilPort, "127.0.0.1", ok));

after(async () => {
  evilSite.close();
  await r.close();
});

/** The sensor's state from its control interface. */
const ctlState = () => JSON.parse(execFileSync(BIN, ["ctl", "--control", `127.0.0.1:${ctlPort}`, "state"], { encoding: "utf8" }));
const faultsOn = () => ctlState().faults;
const clearMessage = (p) => p.evaluate(() => { document.querySelector("#message").textContent = ""; });

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
    const json = { "content-type": "application/json" };
    const res = await fetch("/api/nodes/99/control", { method: "POST", headers: json, body: '{"cmd":"power-cycle"}' });
    // A body that is not typed JSON is refused, even from the page's own origin.
    const plain = await fetch("/api/nodes/127/control", { method: "POST", body: '{"cmd":"power-cycle"}' });
    await api("POST", "/api/nodes/99/control", { cmd: "power-cycle" }).catch(() => {});
    return [res.status, plain.status];
  });
  assert.deepEqual(r, [404, 415]);
  assert.match(await page.locator("#message").innerText(), /unknown node 99/);
  const od = await page.evaluate(async () => (await fetch("/api/nodes/127/sdo/0x1234/0")).status);
  assert.equal(od, 404);
});

test("the scan is sent from the page", async () => {
  await page.locator("#scan").click();
  await page.locator("#message", { hasText: "scan sent" }).waitFor({ timeout: 10000 });
});

test("another site's page and a DNS-rebinding page change nothing", async () => {
  assert.deepEqual(faultsOn(), []);
  const fault = JSON.stringify({ cmd: "fault", name: "missing-magnet", on: true });
  // Another site: a text/plain POST needs no preflight; the dashboard refuses its Origin.
  const evil = await ctx.newPage();
  await evil.goto(`http://127.0.0.1:${evilPort}/`);
  const target = `http://127.0.0.1:${webPort}/api/nodes/127/control`;
  const [resp] = await Promise.all([
    evil.waitForResponse((r) => r.url() === target),
    evil.evaluate(([url, body]) => fetch(url, { method: "POST", mode: "no-cors", body }), [target, fault]),
  ]);
  assert.equal(resp.status(), 403);
  // A JSON one needs a preflight, which is not granted: the browser never sends the POST.
  const refused = await evil.evaluate(([url, body]) =>
    fetch(url, { method: "POST", headers: { "content-type": "application/json" }, body })
      .then(() => "sent", (e) => String(e)), [target, fault]);
  assert.match(refused, /TypeError/);
  await evil.close();
  // DNS rebinding: attacker.example is the dashboard, the page is its own; its Host is not.
  const rebound = await ctx.newPage();
  const r = await rebound.goto(`http://attacker.example:${webPort}/`);
  assert.equal(r.status(), 200, "reads are open to any page");
  const sec = rebound.locator('section.node[data-node="127"]');
  await sec.locator(".fault-on").waitFor({ timeout: 10000 });
  await sec.locator(".fault-name").selectOption("missing-magnet");
  await sec.locator(".fault-on").click();
  await rebound.locator("#message", { hasText: /^403: .*attacker\.example/ }).waitFor({ timeout: 10000 });
  await clearMessage(rebound);
  await sec.locator(".power-cycle").click();
  await rebound.locator("#message", { hasText: /^403: .*attacker\.example/ }).waitFor({ timeout: 10000 });
  await rebound.close();
  const st = ctlState();
  assert.deepEqual(st.faults, []);
  assert.equal(st.nmt, "operational", "no power cycle (a boot leaves the node pre-operational)");
  // The page's own origin still does (and undoes).
  await clearMessage(page);
  await node.locator(".fault-name").selectOption("missing-magnet");
  await node.locator(".fault-on").click();
  await page.locator("#message", { hasText: "node 127: fault done" }).waitFor({ timeout: 10000 });
  assert.deepEqual(faultsOn(), ["missing-magnet"]);
  await node.locator(".fault-off").click();
  for (let i = 0; i < 50 && faultsOn().length; i++) await page.waitForTimeout(100);
  assert.deepEqual(faultsOn(), []);
});

test("the page holds no event stream and keeps updating by polling", async () => {
  // The node sends TPDOs (plot points with sequence numbers) however the tests before went.
  execFileSync(BIN, ["nmt", "--bus", BUS, "--node", "127", "start"]);
  // A page of its own: the requests it makes from its load on are counted.
  const p = await ctx.newPage();
  const polls = [];
  p.on("request", (r) => { if (r.url().includes("/api/snapshot")) polls.push((/[?&]since=(\d*)/.exec(r.url()) || [])[1]); });
  await p.goto(URL);
  await p.locator("#link", { hasText: "live" }).waitFor({ timeout: 10000 });
  const first = await p.evaluate(() => ({ t: window.canposDash.last.t, seq: window.canposDash.since }));
  await p.waitForTimeout(2000);
  const later = await p.evaluate(() => ({ t: window.canposDash.last.t, seq: window.canposDash.since }));
  // The bus time shown and the sequence number asked from both move on: the page updates.
  assert.ok(later.t > first.t, `the page's bus time stayed at ${first.t} s`);
  assert.ok(later.seq > first.seq, `the page asks from seq ${first.seq} still`);
  // Five a second, each from where the last answer ended (a loaded machine polls less often).
  assert.ok(polls.length >= 3, `${polls.length} polls in 2 s: ${polls}`);
  assert.ok(polls.some((s) => Number(s) > 0), `every poll asked for everything: ${polls}`);
  // While it is live it holds no stream open (the server counts them).
  const status = await (await fetch(`${URL}api/status`)).json();
  assert.equal(status.streams, 0);
  // A closed page asks no more.
  await p.close();
  const n = polls.length;
  await new Promise((ok) => setTimeout(ok, 600));
  assert.equal(polls.length, n);
});
