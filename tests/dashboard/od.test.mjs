// The object dictionary, the PDO view and the controls of the dashboard in Debian's Chromium
// (issue 38 items 3, 4, 6 and 8): on one bus a TH (node 5, with a control interface), an
// E-Series with two magnets (node 10, without one) and the EDS I/O module (node 7, with one),
// and `canpos dashboard` on free loopback ports.
// * "Read all" fills every value of the TH; its DCF starts a unit (`canpos run --dcf`) on a bus
//   of its own that answers the same values over SDO (read back by `canpos dcf --node`).
// * A write out of range shows the node's SDO abort and changes nothing.
// * The E-Series' TPDO1 names channel 1's objects; a remap with an object that cannot be
//   mapped shows the abort and leaves the mapping as it was; a remap from the page makes
//   channel 2 appear.
// * The EDS device shows no sensor controls; the node without a control interface says how to
//   give it one.
// * "Read all" of a node that stops answering (the `stall` fault) ends with the reason.
// Screenshots go to $CANPOS_SHOTS (docs/ when refreshing the documentation), else target/.
// Run: node --test tests/dashboard/od.test.mjs
import { test, after } from "node:test";
import assert from "node:assert/strict";
import { execFileSync } from "node:child_process";
import { mkdirSync, readFileSync } from "node:fs";
import { join, resolve } from "node:path";
import { BIN, ROOT, freePorts, rig } from "./rig.mjs";

const SHOTS = resolve(ROOT, process.env.CANPOS_SHOTS || "target");
const r = rig("dash-od");
after(r.close);
const { tmp, start } = r;
const run = (args) => execFileSync(BIN, args, { encoding: "utf8", timeout: 60000 });

const [busPort, thCtl, ioCtl, webPort, bus2Port] = await freePorts(5);
const BUS = `socketcand://127.0.0.1:${busPort}/can0`;
const BUS2 = `socketcand://127.0.0.1:${bus2Port}/can0`;
const URL = `http://127.0.0.1:${webPort}/`;
await start(["run", "--node-id", "5", "--bus", BUS, "--control", `127.0.0.1:${thCtl}`,
  "--state-dir", join(tmp, "th"), "--magnet", "123.4"], /control interface on/);
await start(["run", "--order-code", "EP00600MD341C304241Z02", "--node-id", "10", "--bus", BUS,
  "--state-dir", join(tmp, "es"), "--magnet", "150", "--magnet", "420"], /sensor 0: /);
await start(["run", "--eds", join(ROOT, "examples/io-401.eds"), "--node-id", "7", "--bus", BUS,
  "--control", `127.0.0.1:${ioCtl}`, "--state-dir", join(tmp, "io")], /control interface on/);
await start(["dashboard", "--bus", BUS, "--listen", `127.0.0.1:${webPort}`,
  "--control", `127.0.0.1:${thCtl}`, "--control", `127.0.0.1:${ioCtl}`], /canpos dashboard: http/);

const { page } = await r.browser({ acceptDownloads: true, viewport: { width: 1500, height: 1400 } });
const th = page.locator('section.node[data-node="5"]');
const es = page.locator('section.node[data-node="10"]');
const io = page.locator('section.node[data-node="7"]');

/** `[section]` → {key: value} of the ParameterValue lines of a DCF. */
function parameterValues(text) {
  const out = {};
  let sec = null;
  for (const line of text.split(/\r?\n/)) {
    const s = /^\[([0-9A-Fa-f]{4})(?:sub([0-9A-Fa-f]+))?\]$/.exec(line.trim());
    if (s) { sec = `0x${s[1].toUpperCase()}/${s[2] ? parseInt(s[2], 16) : 0}`; continue; }
    if (/^\[/.test(line)) { sec = null; continue; }
    const v = /^ParameterValue=(.*)$/.exec(line.trim());
    if (sec && v) out[sec] = v[1];
  }
  return out;
}
const num = (s) => Number(BigInt.asIntN(64, BigInt(s.trim())));
/** Waits for the page's message to say `what`; a timeout says what it said instead. */
async function message(what, timeout = 60000) {
  try {
    await page.locator("#message", { hasText: what }).waitFor({ timeout });
  } catch (e) {
    throw new Error(`the page's message is "${await page.locator("#message").innerText()}", not ${what}: ${e.message}`);
  }
}
const clearMessage = () => page.evaluate(() => { const m = document.querySelector("#message"); m.textContent = ""; m.hidden = true; });

test("the page lists the three nodes", async () => {
  const r = await page.goto(URL);
  assert.equal(r.status(), 200);
  await page.locator("#link", { hasText: "live" }).waitFor({ timeout: 60000 });
  for (const n of [5, 7, 10]) await page.locator(`#nodes tr[data-node="${n}"]`).waitFor({ timeout: 60000 });
  // The TH's model is known once the dashboard has identified it.
  await page.locator('#nodes tr[data-node="5"] .model', { hasText: "TH" }).waitFor({ timeout: 60000 });
  await page.locator('#nodes tr[data-node="10"] .model', { hasText: "E-Series" }).waitFor({ timeout: 60000 });
});

test("sensor controls show only where the dashboard knows a control interface", async () => {
  // The TH: its control interface is known.
  await th.locator(".power-cycle").waitFor({ state: "visible", timeout: 60000 });
  assert.equal(await th.locator(".control-note").isVisible(), false);
  // The EDS I/O module: a control interface (NMT, inputs) but no sensor controls.
  await io.locator(".nmt-send").waitFor({ state: "visible", timeout: 60000 });
  for (const c of [".magnet", ".motion-start", ".fault-on", ".power-cycle"]) {
    assert.equal(await io.locator(c).isVisible(), false, `${c} shown on the EDS device`);
  }
  // The E-Series was started without one: no controls, and a note saying how to give it one.
  const note = es.locator(".control-note");
  await note.waitFor({ state: "visible", timeout: 60000 });
  assert.match(await note.innerText(), /--control ADDR/);
  for (const c of [".magnet", ".motion-start", ".fault-on", ".power-cycle", ".nmt-send"]) {
    assert.equal(await es.locator(c).isVisible(), false, `${c} shown without a control interface`);
  }
  mkdirSync(SHOTS, { recursive: true });
  await io.screenshot({ path: join(SHOTS, "dashboard-eds-device.png") });
});

/** Writes `value` into the TH's object `key` from the object browser's row; `expect` is the
 * message it must show. A write the node did not answer in time (the dashboard's 1 s SDO
 * timeout on a loaded machine) is sent again once, as its user would. */
async function writeRow(key, value, expect) {
  const row = th.locator(`.od tr[data-key="${key}"]`);
  await row.locator(".write-value").fill(String(value));
  for (let i = 0; ; i++) {
    await clearMessage();
    await row.locator(".write").click();
    const said = page.locator("#message", { hasText: expect });
    const late = page.locator("#message", { hasText: /SDO timeout/ });
    await said.or(late).first().waitFor({ timeout: 60000 });
    if (i > 0 || !(await late.isVisible())) break;
  }
  await message(expect);
  return row;
}

let exported = null;
test("read all fills every value of the TH and its DCF starts a unit that answers the same values", async (t) => {
  await th.locator(".od-load").click();
  await th.locator('.od tr[data-key="0x1017/0"]').waitFor({ timeout: 60000 });
  // The range of a write is shown with the object.
  assert.match(await th.locator('.od tr[data-key="0x1017/0"] .range').innerText(), /^0 … 65535$/);
  // Values that are not the defaults, so that the DCF has to carry them.
  for (const [key, v] of [["0x1017/0", 250], ["0x6301/1", 1], ["0x6310/1", 12345]]) {
    await writeRow(key, v, `wrote ${key}`);
  }
  const started = Date.now();
  await th.locator(".od-read-all").click();
  await th.locator(".od-progress.done").waitFor({ timeout: 120000 });
  t.diagnostic(`read all took ${Date.now() - started} ms`);
  const progress = await th.locator(".od-progress").innerText();
  const rows = await th.locator(".od tbody tr").count();
  assert.match(progress, new RegExp(`read all: ${rows} of ${rows} objects`), progress);
  // Every value is filled. The only objects without one are the error history's entries
  // (0x1003/1…), which the TH answers "no data available" (CiA 301) while 0x1003/0 counts 0.
  const keys = await th.locator(".od tbody tr").evaluateAll((trs) => trs.map((tr) => tr.dataset.key));
  const values = await th.locator(".od tbody tr .value").allInnerTexts();
  assert.equal(values.length, rows);
  const empty = keys.filter((k, i) => !/\[[0-9A-F ]*\]/.test(values[i]));
  const refused = keys.filter((k, i) => /^SDO abort 0x08000024/.test(values[i]));
  assert.deepEqual(empty, refused, "values neither read nor refused");
  assert.ok(refused.every((k) => /^0x1003\/[1-9]/.test(k)), `refused: ${refused}`);
  assert.match(await th.locator('.od tr[data-key="0x1003/0"] .value').innerText(), /^0 /);
  assert.match(await th.locator('.od tr[data-key="0x1017/0"] .value').innerText(), /^250 /);
  // A position is shown with its resolution (0x6005/1): as many decimals as the step has.
  const snap = await page.evaluate(() => window.canposDash.last.nodes.find((n) => n.node === 5));
  const d = snap.resolution.position_decimals;
  assert.match(await th.locator('.od tr[data-key="0x6020/1"] .value').innerText(), new RegExp(`= \\d+\\.\\d{${d}} mm$`));
  assert.match(await page.locator('#nodes tr[data-node="5"] .pos').innerText(), new RegExp(`^\\d+\\.\\d{${d}} mm`));
  mkdirSync(SHOTS, { recursive: true });
  // The heading with its buttons and progress, and the table scrolled to the positions.
  await th.locator('.od tr[data-key="0x6020/1"]').evaluate((tr) => { tr.closest(".od").scrollTop = tr.offsetTop - 120; });
  const heading = th.locator("h3", { has: page.locator(".od-read-all") });
  await heading.evaluate((h) => h.scrollIntoView());
  const head = await heading.boundingBox();
  const table = await th.locator(".od-box").boundingBox();
  await page.screenshot({ path: join(SHOTS, "dashboard-od.png"),
    clip: { x: table.x, y: head.y, width: table.width, height: table.y + table.height - head.y } });

  // The DCF, downloaded as the page's user gets it.
  const [dl] = await Promise.all([page.waitForEvent("download", { timeout: 60000 }), th.locator(".od-dcf").click()]);
  assert.match(dl.suggestedFilename(), /^canpos-th-5\.dcf$/);
  const file = join(tmp, "th.dcf");
  await dl.saveAs(file);
  exported = readFileSync(file, "utf8");
  const mine = parameterValues(exported);
  assert.equal(num(mine["0x1017/0"]), 250);
  assert.equal(num(mine["0x6310/1"]), 12345);

  // A unit started from it on a bus of its own answers the same values over SDO.
  await start(["run", "--dcf", file, "--bus", BUS2, "--state-dir", join(tmp, "from-dcf")], /sensor 0: /);
  const theirs = parameterValues(run(["dcf", "--node", "5", "--bus", BUS2, "--timeout", "3000"]));
  const od = await page.evaluate(async () => (await (await fetch("/api/nodes/5/od")).json()).entries);
  const config = od.filter((e) => e.access === "rw").map((e) => `${e.index}/${e.sub}`).filter((k) => k in mine);
  assert.ok(config.length > 50, `${config.length} configuration objects in the DCF`);
  const differ = config.filter((k) => !(k in theirs) || num(mine[k]) !== num(theirs[k]));
  assert.deepEqual(differ.map((k) => `${k}: ${mine[k]} → ${theirs[k]}`), []);
});

test("a write out of range shows the node's SDO abort and changes nothing", async () => {
  const before = run(["sdo", "--bus", BUS, "read", "5", "0x2101", "0"]);
  // BOOLEAN: 2 fits the byte, not the object.
  const row = await writeRow("0x2101/0", 2, /SDO abort 0x0609003\d/);
  await row.locator(".value", { hasText: /^0 / }).waitFor({ timeout: 60000 });
  assert.equal(run(["sdo", "--bus", BUS, "read", "5", "0x2101", "0"]), before);
  // A value the type cannot hold is refused before the bus.
  await writeRow("0x1017/0", 70000, /does not fit/);
  assert.match(run(["sdo", "--bus", BUS, "read", "5", "0x1017", "0"]), /\b250\b/);
});

test("the E-Series' TPDO1 names channel 1's objects; a remap from the page makes channel 2 appear", async () => {
  await es.locator(".pdo-load").click();
  const tpdo1 = es.locator('.pdo tr[data-tpdo="1"]');
  await tpdo1.waitFor({ timeout: 60000 });
  const mapped = await tpdo1.locator(".mapped").innerText();
  assert.match(mapped, /Position value channel 1 \(0x6020\/1, 32 bit\)/i);
  assert.doesNotMatch(mapped, /channel 2/i);
  assert.match(await tpdo1.locator(".cob").innerText(), /0x[04]000018A \(CAN-ID 0x18A\)/);
  // The node sends its TPDOs (NMT start), with channel 1 only.
  run(["nmt", "--bus", BUS, "--node", "10", "start"]);
  await es.locator('.channel[data-ch="0"] .pos-now', { hasText: "mm" }).waitFor({ timeout: 60000 });
  assert.equal(await es.locator('.channel[data-ch="1"]').count(), 0);

  // An object no TPDO can carry: the node's abort is shown and the mapping stays.
  await clearMessage();
  await tpdo1.locator(".remap-objects").fill("0x6020/1, 0x1017/0");
  await tpdo1.locator(".remap-go").click();
  await message(/SDO abort 0x06040041/);
  assert.match(await page.locator("#message").innerText(), /written back/);
  await es.locator('.pdo tr[data-tpdo="1"] .mapped', { hasText: mapped.split("\n")[0] }).waitFor({ timeout: 60000 });
  assert.equal(await es.locator('.pdo tr[data-tpdo="1"] .mapped').innerText(), mapped);

  // Only the page's own origin remaps (the dashboard's guard): another site's request, or one
  // without a JSON body, is refused before the bus.
  const other = await fetch(`${URL}api/nodes/10/pdo/1`, { method: "PUT", body: '{"mapping":[]}',
    headers: { "content-type": "application/json", origin: "http://attacker.example" } });
  assert.equal(other.status, 403);
  const plain = await fetch(`${URL}api/nodes/10/pdo/1`, { method: "PUT", body: '{"mapping":[]}' });
  assert.equal(plain.status, 415);
  assert.equal(await es.locator('.pdo tr[data-tpdo="1"] .mapped').innerText(), mapped);

  // Both positions in TPDO1: channel 2 appears with its position.
  await clearMessage();
  await es.locator('.pdo tr[data-tpdo="1"] .remap-objects').fill("0x6020/1, 0x6020/2");
  await es.locator('.pdo tr[data-tpdo="1"] .remap-go').click();
  await message("TPDO 1 remapped");
  await es.locator('.pdo tr[data-tpdo="1"] .mapped', { hasText: /Position value channel 2/i }).waitFor({ timeout: 60000 });
  const ch2 = es.locator('.channel[data-ch="1"] .pos-now');
  await ch2.waitFor({ timeout: 60000 });
  await es.locator('.channel[data-ch="1"] .pos-now', { hasText: /^4\d\d\.\d+ mm/ }).waitFor({ timeout: 60000 });
  // The event timer from the page; a transmission type that is no number is refused first.
  const row1 = es.locator('.pdo tr[data-tpdo="1"]');
  await clearMessage();
  await row1.locator(".remap-type").fill("fast");
  await row1.locator(".remap-go").click();
  await message(/^400: bad body: `transmission_type`/);
  await clearMessage();
  await es.locator('.pdo tr[data-tpdo="1"] .remap-event').fill("5");
  await es.locator('.pdo tr[data-tpdo="1"] .remap-go').click();
  await message("TPDO 1 remapped");
  assert.equal(await es.locator('.pdo tr[data-tpdo="1"] .event').innerText(), "5 ms");
  assert.match(await es.locator('.pdo tr[data-tpdo="1"] .mapped').innerText(), /channel 2/);
  await es.locator(".pdo-box").screenshot({ path: join(SHOTS, "dashboard-pdo.png") });
});

test("read all of a node that stops answering ends with the reason", async () => {
  await clearMessage();
  // The TH takes no frame for up to 60 s (ended below once the page has shown the reason).
  run(["ctl", "--control", `127.0.0.1:${thCtl}`, "fault", "stall", "on", "--value", "60"]);
  try {
    await th.locator(".od-read-all").click();
    await th.locator(".od-progress.error").waitFor({ timeout: 30000 });
    const why = await th.locator(".od-progress").innerText();
    assert.match(why, /read all of node 5 stopped at 0x1000\/0: .*SDO timeout.*; 0 of \d+ objects read/, why);
    assert.match(await page.locator("#message").innerText(), /SDO timeout/);
    // The button is usable again; the PDO view of the silent node says why it has nothing.
    assert.equal(await th.locator(".od-read-all").isEnabled(), true);
    await clearMessage();
    await th.locator(".pdo-load").click();
    await message(/reading 0x1800\/1: node 5: SDO timeout/);
  } finally {
    run(["ctl", "--control", `127.0.0.1:${thCtl}`, "fault", "stall", "off"]);
  }
  // Once the stall is over the node answers.
  assert.match(run(["sdo", "--bus", BUS, "read", "5", "0x1017", "0"]), /\b250\b/);
});
