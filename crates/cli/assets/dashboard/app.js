// canpos dashboard page: starts from the snapshot the page came with (#initial), then polls
// /api/snapshot for what is new; actions through the JSON API. Every failed request shows its
// error in #message.
"use strict";

const FAULTS = ["missing-magnet", "extra-magnet", "magnets-too-close", "sensor-error",
  "supply-voltage", "over-temperature", "storage-corrupt", "error-passive", "bus-off",
  "can-overrun", "communication", "pdo-length", "wrong-mapping", "wrong-vendor-id",
  "wrong-scale", "wrong-resolution", "no-system-data", "invalid-serial",
  "unexpected-system-data", "power-cycle"];
const NMT = ["start", "stop", "preop", "reset", "reset-comm"];

// State the tests read: plots and their data per node and channel.
const dash = { plots: {}, data: {}, window: 30, last: null, since: 0 };
window.canposDash = dash;

const $ = (sel, root = document) => root.querySelector(sel);
const el = (tag, attrs = {}, ...kids) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v; else if (k.startsWith("on")) e[k] = v; else e.setAttribute(k, v);
  }
  for (const k of kids) e.append(k);
  return e;
};

function show(text, kind = "error") {
  const m = $("#message");
  m.textContent = text;
  m.className = kind;
  m.hidden = false;
}

async function api(method, url, body) {
  const opts = { method, headers: {} };
  // The dashboard takes state changes only as JSON (docs/DASHBOARD.md): every request that is
  // not a read carries a JSON body, an empty object where there is nothing to say.
  if (method !== "GET" && method !== "HEAD") {
    opts.body = JSON.stringify(body ?? {});
    opts.headers["content-type"] = "application/json";
  }
  let r, j;
  try {
    r = await fetch(url, opts);
    j = await r.json();
  } catch (e) {
    show(`${method} ${url}: ${e}`);
    throw e;
  }
  if (!r.ok || j.ok === false) {
    show(`${r.status}: ${j.error || "request failed"}`);
    throw new Error(j.error);
  }
  return j;
}

function control(node, req) {
  return api("POST", `/api/nodes/${node}/control`, req).then((j) => {
    show(`node ${node}: ${req.cmd} done`, "info");
    return j;
  });
}

function nodeRow(n) {
  let tr = $(`#nodes tr[data-node="${n.node}"]`);
  if (!tr) {
    tr = el("tr", { "data-node": n.node });
    for (const c of ["node", "model", "name", "serial", "nmt", "pos", "errreg"]) tr.append(el("td", { class: c }));
    const rows = [...$("#nodes tbody").children];
    const after = rows.find((r) => Number(r.dataset.node) > n.node);
    $("#nodes tbody").insertBefore(tr, after || null);
  }
  $(".node", tr).textContent = n.node;
  $(".model", tr).textContent = n.product ? `${n.product} (${n.model})` : "unknown";
  $(".name", tr).textContent = n.name ?? "–";
  $(".serial", tr).textContent = n.serial ?? "–";
  $(".nmt", tr).textContent = n.nmt;
  $(".pos", tr).textContent = positionsText(n);
  $(".errreg", tr).textContent = n.error_register == null ? "–"
    : `0x${n.error_register.toString(16).padStart(2, "0").toUpperCase()} (${n.error_register_text})`;
}

// Each channel's position in mm (as the server's `positions_text` writes it).
function positionsText(n) {
  if (!n.positions || !n.positions.length) return "–";
  const d = (n.resolution && n.resolution.position_decimals) ?? 3;
  const out = n.positions.map((p) => (p == null ? "no position" : `${p.toFixed(d)} mm`));
  if (n.positions_from === "control") out.push("(control state; no TPDO)");
  return out.join(" · ");
}

// A y range of at least `span`: a still sensor's µm of noise is not blown up to fill the plot.
const atLeast = (span) => (u, min, max) => {
  if (min == null || max == null) return [0, span];
  if (max - min >= span) { const pad = (max - min) * 0.05; return [min - pad, max + pad]; }
  const mid = (min + max) / 2;
  return [mid - span / 2, mid + span / 2];
};

function plot(target, label, unit, stroke) {
  const opts = {
    width: 520, height: 200, title: `${label} (${unit})`,
    scales: { x: { time: false }, y: { range: atLeast(unit === "mm" ? 1 : 10) } },
    // A wider y axis: its label clears tick labels like 1000.5.
    axes: [{ label: "s" }, { label: unit, size: 72, labelGap: 4 }],
    series: [{ label: "t / s" }, { label: `${label} / ${unit}`, stroke, width: 1.5 }],
  };
  return new uPlot(opts, [[], []], target);
}

function panel(n) {
  let sec = $(`section.node[data-node="${n.node}"]`);
  if (sec) return sec;
  sec = el("section", { class: "node", "data-node": n.node });
  sec.append(el("h2", {}, `Node ${n.node}`), el("div", { class: "channels" }),
    el("p", {}, "Alarms: ", el("span", { class: "alarms" }, "–"), " · Error register: ",
      el("span", { class: "errreg" }, "–")));
  const ctl = el("div", { class: "controls", hidden: "" });
  const slider = el("input", { type: "range", min: "0", max: "1000", step: "1", value: "0", class: "magnet" });
  const out = el("span", { class: "magnet-mm" }, "– mm");
  let pending = null, busy = false;
  const send = () => {
    if (busy || pending === null) return;
    const mm = pending; pending = null; busy = true;
    control(n.node, { cmd: "magnet", index: 0, mm }).catch(() => {}).finally(() => { busy = false; send(); });
  };
  slider.oninput = () => { out.textContent = `${slider.value} mm`; pending = Number(slider.value); send(); };
  const spec = el("input", { class: "motion-spec", size: "36", value: "sine:center=500,amp=300,period=4" });
  const faultSel = el("select", { class: "fault-name" }, ...FAULTS.map((f) => el("option", { value: f }, f)));
  const nmtSel = el("select", { class: "nmt-command" }, ...NMT.map((c) => el("option", { value: c }, c)));
  // The sensor's own controls: a device served from an EDS has no magnets, motion or faults.
  const sensorCtl = el("span", { class: "sensor-controls" },
    el("label", {}, "Magnet 0: ", slider, " ", out),
    el("span", {}, spec, el("button", { class: "motion-start", onclick: () => control(n.node, { cmd: "motion", spec: spec.value }).catch(() => {}) }, "Start motion")),
    el("span", {}, faultSel,
      el("button", { class: "fault-on", onclick: () => control(n.node, { cmd: "fault", name: faultSel.value, on: true }).catch(() => {}) }, "on"),
      el("button", { class: "fault-off", onclick: () => control(n.node, { cmd: "fault", name: faultSel.value, on: false }).catch(() => {}) }, "off")),
    el("button", { class: "power-cycle", onclick: () => control(n.node, { cmd: "power-cycle" }).catch(() => {}) }, "Power-cycle"));
  ctl.append(sensorCtl,
    el("span", {}, nmtSel, el("button", { class: "nmt-send", onclick: () => control(n.node, { cmd: "nmt", command: nmtSel.value }).catch(() => {}) }, "NMT")),
    el("span", { class: "faults" }));
  sec.append(ctl);
  // An EDS device's process objects: outputs as the master wrote them, inputs to set.
  sec.append(el("div", { class: "process", hidden: "" }, el("h3", {}, "Process objects"),
    el("table", { class: "process-objects" },
      el("thead", {}, el("tr", {}, ...["object", "name", "type", "direction", "value", "set"].map((h) => el("th", {}, h)))),
      el("tbody"))));
  sec.append(el("h3", {}, "EMCY log"), el("table", { class: "emcy" },
    el("thead", {}, el("tr", {}, ...["t / s", "code", "meaning", "register", "manufacturer bytes"].map((h) => el("th", {}, h)))),
    el("tbody")));
  // Object dictionary and PDOs: od.js.
  window.canposOd.attach(sec, n.node);
  $("#panels").append(sec);
  return sec;
}

// The process objects of an EDS device's control state, one row each, kept across updates:
// values change in place and an input field being edited is left alone.
function processObjects(sec, n) {
  const box = $(".process", sec);
  const objs = (n.control && n.control.process) || null;
  box.hidden = !objs;
  if (!objs) return;
  const tb = $("tbody", box);
  for (const o of objs) {
    const key = `${o.index}/${o.sub}`;
    let tr = $(`tr[data-object="${key}"]`, tb);
    if (!tr) {
      tr = el("tr", { "data-object": key, class: o.direction });
      const set = el("td", { class: "set" });
      if (o.direction === "input") {
        const input = el("input", { class: "input-value", size: "8", value: String(o.value) });
        const go = () => control(n.node, { cmd: "set-input", index: o.index, sub: o.sub, value: input.value.trim() }).catch(() => {});
        input.onkeydown = (e) => { if (e.key === "Enter") go(); };
        set.append(input, el("button", { class: "input-set", onclick: go }, "Set"));
      }
      tr.append(el("td", {}, key), el("td", {}, o.name), el("td", {}, o.type),
        el("td", {}, o.direction), el("td", { class: "value" }), set);
      tb.append(tr);
    }
    $(".value", tr).textContent = String(o.value);
  }
}

function draw(node, i) {
  const d = dash.data[node][i], p = dash.plots[node][i];
  p.pos.setData([d.t, d.p]);
  p.vel.setData([d.t, d.v]);
}

const seen = new IntersectionObserver((entries) => {
  for (const e of entries) {
    const node = Number(e.target.closest("section.node").dataset.node), i = Number(e.target.dataset.ch);
    const p = dash.plots[node] && dash.plots[node][i];
    if (!p) continue;
    p.visible = e.isIntersecting;
    if (p.visible) draw(node, i);
  }
});

function channels(sec, n) {
  const box = $(".channels", sec);
  dash.plots[n.node] ??= [];
  dash.data[n.node] ??= [];
  n.channels.forEach((c, i) => {
    let ch = $(`.channel[data-ch="${i}"]`, box);
    if (!ch) {
      ch = el("div", { class: "channel", "data-ch": i });
      const pos = el("div", { class: "plot-pos" }), vel = el("div", { class: "plot-vel" });
      ch.append(pos, vel, el("div", { class: "states" }, el("h4", {}, `Channel ${i + 1}`),
        el("div", { class: "pos-now" }), el("div", {}, "Cams: ", el("span", { class: "cams" })),
        el("div", {}, "Work area: ", el("span", { class: "area" }))));
      box.append(ch);
      dash.data[n.node][i] = { t: [], p: [], v: [] };
      dash.plots[n.node][i] = { pos: plot(pos, "position", "mm", "#1565c0"), vel: plot(vel, "velocity", "mm/s", "#c62828"), visible: true };
      seen.observe(ch);
    }
    const d = dash.data[n.node][i];
    d.t.push(...c.t); d.p.push(...c.p); d.v.push(...c.v);
    const tmax = d.t.length ? d.t[d.t.length - 1] : 0;
    let cut = 0;
    while (cut < d.t.length && d.t[cut] < tmax - dash.window) cut++;
    if (cut) { d.t.splice(0, cut); d.p.splice(0, cut); d.v.splice(0, cut); }
    // Off-screen plots are not redrawn (with many nodes most are): their data still grows.
    if ((c.t.length || cut) && dash.plots[n.node][i].visible) draw(n.node, i);
    const res = n.resolution || {};
    $(".pos-now", ch).textContent = c.pos == null ? "no position"
      : `${c.pos.toFixed(res.position_decimals ?? 3)} mm, ${c.vel == null ? "–" : c.vel.toFixed(res.velocity_decimals ?? 2)} mm/s`;
    $(".cams", ch).textContent = c.cam == null ? "–" : (c.cam_labels.join(", ") || "all cams inactive");
    $(".area", ch).textContent = c.area == null ? "–" : (c.area_labels.join(", ") || "inside the work area");
  });
}

function update(s) {
  dash.last = s;
  dash.since = s.seq;
  dash.window = s.window_s;
  $("#bus").textContent = `bus ${s.bus}`;
  $("#rate").textContent = `${s.frames_per_s.toFixed(0)} frames/s`;
  $("#load").textContent = s.bus_load ? `bus load ${JSON.stringify(s.bus_load.value)} (${s.bus_load.key})` : "";
  if (s.bus_error) show(`bus connection ended: ${s.bus_error}`);
  for (const n of s.nodes) {
    nodeRow(n);
    const sec = panel(n);
    $("h2", sec).textContent = `Node ${n.node} — ${n.product ?? "unknown model"} · ${n.nmt}`;
    channels(sec, n);
    const al = $(".alarms", sec);
    al.textContent = n.alarms == null ? "–" : (n.alarm_labels.join(", ") || "none");
    al.className = "alarms " + (n.alarms ? "alarm" : "ok");
    $(".errreg", sec).textContent = n.error_register == null ? "–"
      : `0x${n.error_register.toString(16).padStart(2, "0").toUpperCase()} (${n.error_register_text})`;
    const ctl = $(".controls", sec);
    ctl.hidden = !n.control;
    window.canposOd.update(sec, n);
    processObjects(sec, n);
    if (n.control) {
      $(".sensor-controls", ctl).hidden = n.control.device === "eds";
      const late = n.control.clock && n.control.clock.events_late_us;
      const bus = [n.control.bus_off ? "bus-off" : null, n.control.bus_state ? `CAN ${JSON.stringify(n.control.bus_state)}` : null,
        late && late.max > 1000 ? `host late: max ${(late.max / 1000).toFixed(1)} ms (frames kept their times)` : null].filter(Boolean);
      $(".faults", ctl).textContent = (bus.length ? `${bus.join(", ")} · ` : "") + `faults on: ${(n.control.faults || []).map((f) => (typeof f === "string" ? f : JSON.stringify(f))).join(", ") || "none"}`;
      const slider = $(".magnet", ctl);
      const mm = n.control.true_mm && n.control.true_mm[0];
      if (mm != null && document.activeElement !== slider && !slider.dataset.set) {
        slider.value = mm; slider.dataset.set = "1";
        $(".magnet-mm", ctl).textContent = `${mm.toFixed((n.resolution && n.resolution.position_decimals) ?? 3)} mm`;
      }
    }
    const tb = $(".emcy tbody", sec);
    tb.replaceChildren(...n.emcy.map((e) => el("tr", { "data-code": e.code },
      el("td", {}, e.t.toFixed(3)), el("td", {}, e.code), el("td", {}, e.meaning),
      el("td", {}, `${e.register} (${e.register_text})`), el("td", {}, e.msef))));
  }
}

// What is new, five times a second: one plain GET each time that ends at once, so no request
// stays open (a screenshot tool waiting for the network, or its virtual-time budget, finishes).
// A failed poll says so in the header and is retried, less often while it keeps failing.
async function poll(failures = 0) {
  try {
    const r = await fetch(`/api/snapshot?since=${dash.since}`);
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    update(await r.json());
    $("#link").textContent = "live";
    failures = 0;
  } catch (e) {
    failures++;
    const at = dash.last ? `${dash.last.t.toFixed(1)} s` : "the page's load";
    $("#link").textContent = `no connection to the dashboard (${e.message || e}): showing the bus at ${at}, retrying`;
  }
  setTimeout(() => poll(failures), failures ? Math.min(200 * 2 ** failures, 5000) : 200);
}

$("#scan").onclick = () => api("POST", "/api/scan").then(() => show("scan sent", "info")).catch(() => {});
try {
  update(JSON.parse($("#initial").textContent));
  $("#link").textContent = `snapshot at ${dash.last.t.toFixed(1)} s, connecting for updates…`;
} catch (e) {
  $("#link").textContent = `the page came without its data (${e}): connecting…`;
}
if (typeof fetch === "function") poll();
else $("#link").textContent = "this browser cannot fetch updates: the page shows the bus at its load; reload for new values";
