// canpos dashboard: the bus tool (docs/DASHBOARD.md, "Trace", "Transmit", "Hub connection").
// A frame trace (one row per identifier, or a scrolling log), paused and filtered; bus load and
// frame rate in the header; the hub link's state; a transmitter (once or periodically) and NMT.
// Everything goes through the JSON API a script can call too: GET /api/trace, POST /api/send,
// POST /api/send/stop, POST /api/nmt, GET /api/trace/export. Uses app.js's `el`, `$` and `api`.
"use strict";

// State the tests read.
const trace = { seq: 0, paused: false, mode: "rows", last: null, polls: 0 };
window.canposTrace = trace;

// The lease of this page's periodic transmissions (D61): renewed while the page is open (by a
// worker, else by the trace poll), given up when it closes; a page that is gone without a word
// (a crash, a lost network) has its transmissions end within the server's 5 s.
const LEASE = `page-${Date.now().toString(36)}-${Math.random().toString(36).slice(2, 10)}`;
const lease = { worker: null, active: false, renewed: 0 };
trace.lease = LEASE;
function holdLease(list) {
  const active = list.some((p) => p.lease === LEASE);
  // The worker starts with the page's first transmission: a page that sends none runs none.
  if (active && lease.worker === null) {
    try { lease.worker = new Worker("/lease.js"); } catch (e) { lease.worker = false; }
  }
  if (active !== lease.active) {
    lease.active = active;
    if (lease.worker) lease.worker.postMessage({ lease: LEASE, active });
  }
  // Without a worker the poll renews, once a second.
  if (active && !lease.worker && Date.now() - lease.renewed > 1000) {
    lease.renewed = Date.now();
    api("POST", "/api/send/renew", { lease: LEASE }).catch(() => {});
  }
}
addEventListener("pagehide", () => {
  if (!lease.active) return;
  // keepalive: the request outlives the page.
  fetch("/api/send/stop", { method: "POST", keepalive: true, headers: { "Content-Type": "application/json" }, body: JSON.stringify({ lease: LEASE }) }).catch(() => {});
});

// Rows of the log view kept in the page at most, and asked for per poll (the server keeps more,
// for the export): at 10,000 frames/s nobody reads more, and the page stays responsive.
const LOG_ROWS = 200;

// Sets a cell's text only when it changed (a row per identifier is rewritten every poll).
const put = (cell, text) => { if (cell.textContent !== text) cell.textContent = text; };

function traceQuery() {
  const q = new URLSearchParams();
  for (const k of ["from", "to", "node"]) {
    const v = $(`#trace-${k}`).value.trim();
    if (v) q.set(k, v);
  }
  return q;
}

function exportLinks() {
  const q = traceQuery();
  for (const f of ["pcapng", "candump"]) {
    q.set("format", f);
    $(`#trace-${f}`).href = `/api/trace/export?${q}`;
  }
}

function fmtMs(v) {
  return v == null ? "–" : v.toFixed(3);
}

function traceRow(r) {
  const key = `${r.ext ? "x" : "s"}${r.id}${r.rtr ? "r" : ""}`;
  let tr = $(`#trace tbody tr[data-key="${key}"]`);
  if (!tr) {
    tr = el("tr", { "data-key": key, "data-id": r.id });
    for (const c of ["dir", "id", "dlc", "data", "count", "cycle", "decoded"]) tr.append(el("td", { class: c }));
    const rows = [...$("#trace tbody").children];
    const after = rows.find((x) => x.dataset.key > key);
    $("#trace tbody").insertBefore(tr, after || null);
  }
  const c = tr.children;
  put(c[0], r.dir);
  put(c[1], r.id + (r.ext ? " (ext)" : ""));
  put(c[2], String(r.dlc));
  put(c[3], r.rtr ? "RTR" : r.data);
  put(c[4], String(r.count));
  put(c[5], fmtMs(r.cycle_ms));
  put(c[6], r.decoded);
  tr.title = `last interval ${fmtMs(r.dt_ms)} ms`;
  return tr;
}

// The log view: the newest LOG_ROWS entries, newest first, written into rows made once (no rows added or
// removed while frames stream: at 10,000 frames/s that relayout was most of the page's time).
const logBuf = [];
function logRows(fresh, entries) {
  if (fresh) logBuf.length = 0;
  logBuf.push(...entries);
  if (logBuf.length > LOG_ROWS) logBuf.splice(0, logBuf.length - LOG_ROWS);
  const tb = $("#trace-log tbody");
  while (tb.children.length < LOG_ROWS) {
    const tr = el("tr", {});
    for (const c of ["t", "dir", "id", "dlc", "data", "decoded"]) tr.append(el("td", { class: c }));
    tb.append(tr);
  }
  const rows = tb.children;
  // Newest first: nothing to scroll, so no layout is forced while frames stream.
  for (let i = 0; i < LOG_ROWS; i++) {
    const e = logBuf[logBuf.length - 1 - i], tr = rows[i], c = tr.children;
    tr.hidden = !e;
    if (!e) continue;
    tr.dataset.id = e.id;
    tr.dataset.seq = e.seq;
    put(c[0], e.t.toFixed(6));
    put(c[1], e.dir);
    put(c[2], e.id + (e.ext ? " (ext)" : ""));
    put(c[3], String(e.dlc));
    put(c[4], e.rtr ? "RTR" : e.data);
    put(c[5], e.decoded);
  }
}

// Where the bit rate of the load comes from (D60).
const RATE_FROM = {
  given: "given",
  bus: "the bus's",
  sensor: "a sensor's",
  assumed: "assumed: the bus names none; canpos dashboard --bitrate KBPS sets it",
};

function header(j) {
  $("#busload").textContent = `bus load ${j.bus_load_pct.toFixed(1)} % of ${j.bitrate_kbps} kbit/s (${RATE_FROM[j.bitrate_from] || j.bitrate_from}) · ${j.frames_per_s.toFixed(0)} frames/s`;
  $("#busload").dataset.bitrateFrom = j.bitrate_from;
  const hub = $("#hub");
  const l = j.link;
  const when = (s) => new Date(s * 1000).toLocaleTimeString();
  document.body.classList.toggle("hub-away", l.down_since != null);
  if (l.down_since != null) {
    hub.textContent = `bus connection lost at ${when(l.down_since)} (${l.down_why}); reconnecting… (the nodes below are as last heard)`;
    hub.className = "down";
  } else if (l.reconnections > 0) {
    hub.textContent = `reconnected to the bus at ${when(l.back_at)} (${l.reconnections}×); nodes scanned again`;
    hub.className = "back";
  } else {
    hub.textContent = "";
    hub.className = "";
  }
}

function periodicList(list) {
  const ul = $("#tx-periodic");
  const key = JSON.stringify(list);
  if (ul.dataset.key === key) return;
  ul.dataset.key = key;
  // A job of another page or a script says whose it is; this page's runs while it is open.
  const term = (p) => p.lease === LEASE ? "while this page is open"
    : p.lease ? `lease ${p.lease}, ends in ${Math.ceil(p.ends_in_s)} s unless renewed` : `for ${Math.ceil(p.ends_in_s)} s more`;
  ul.replaceChildren(...list.map((p) => el("li", { "data-id": p.id },
    `${p.id} [${p.dlc}] ${p.rtr ? "RTR" : p.data} every ${p.period_ms} ms, ${term(p)} (${p.sent} sent) `,
    el("button", { class: "tx-stop", onclick: () => api("POST", "/api/send/stop", { id: p.id, ext: p.ext }).then((j) => periodicList(j.periodic)).catch(() => {}) }, "Stop"))));
}

function render(j, fresh) {
  if (trace.mode === "rows") {
    const keep = new Set(j.rows.map((r) => traceRow(r)));
    for (const tr of [...$("#trace tbody").children]) if (!keep.has(tr)) tr.remove();
  } else {
    logRows(fresh, j.log);
  }
}

async function tracePoll(failures = 0) {
  let fresh = false;
  try {
    const q = traceQuery();
    // The log asks for what is new; a changed filter starts it again.
    const key = q.toString();
    if (key !== trace.filterKey) { trace.filterKey = key; trace.seq = 0; fresh = true; }
    if (trace.mode === "log" && !trace.paused) { q.set("since", trace.seq); q.set("limit", LOG_ROWS); }
    else q.set("since", "18446744073709551615");
    const r = await fetch(`/api/trace?${q}`);
    const j = await r.json();
    if (!r.ok) throw new Error(j.error || `HTTP ${r.status}`);
    trace.last = j;
    trace.polls++;
    header(j);
    holdLease(j.periodic);
    periodicList(j.periodic);
    $("#trace-error").textContent = "";
    if (!trace.paused) {
      render(j, fresh);
      if (trace.mode === "log") trace.seq = j.seq;
    }
    failures = 0;
  } catch (e) {
    failures++;
    $("#trace-error").textContent = `trace: ${e.message || e}`;
  }
  setTimeout(() => tracePoll(failures), failures ? Math.min(250 * 2 ** failures, 5000) : 250);
}

function buildTrace() {
  const hdr = $("header");
  hdr.insertBefore(el("span", { id: "busload", title: "from the frames' own timestamps over the last second, at the bit rate named: --bitrate, else the bus's or a sensor's, else 1000 kbit/s assumed (a socketcand hub names none)" }, ""), $("#link"));
  hdr.insertBefore(el("span", { id: "hub", role: "status" }, ""), $("#link"));
  const sel = el("select", { id: "trace-mode" }, el("option", { value: "rows" }, "one row per identifier"),
    el("option", { value: "log" }, "scrolling log"));
  const pause = el("button", { id: "trace-pause" }, "Pause");
  pause.onclick = () => {
    trace.paused = !trace.paused;
    pause.textContent = trace.paused ? "Resume" : "Pause";
    pause.classList.toggle("paused", trace.paused);
  };
  sel.onchange = () => {
    trace.mode = sel.value;
    $("#trace").hidden = trace.mode !== "rows";
    $("#trace-log-box").hidden = trace.mode !== "log";
    trace.filterKey = null;
  };
  const filt = (k, ph, size) => el("label", {}, `${k} `, el("input", { id: `trace-${k}`, placeholder: ph, size: String(size), oninput: exportLinks }));
  const clear = el("button", { id: "trace-clear" }, "Clear");
  clear.onclick = () => api("POST", "/api/trace/clear").then(() => {
    $("#trace tbody").replaceChildren(); logRows(true, []); trace.seq = 0;
  }).catch(() => {});
  const cols = (...h) => el("thead", {}, el("tr", {}, ...h.map((x) => el("th", {}, x))));
  // Transmit: one frame, or one every `period` ms; NMT to all nodes or one.
  const tx = (id, attrs = {}) => el("input", { id, ...attrs });
  const send = el("button", { id: "tx-send" }, "Send");
  send.onclick = () => {
    const body = { id: $("#tx-id").value.trim(), ext: $("#tx-ext").checked, rtr: $("#tx-rtr").checked, data: $("#tx-data").value };
    const dlc = $("#tx-dlc").value.trim();
    if (dlc) body.dlc = Number(dlc);
    const per = $("#tx-period").value.trim();
    if (per) { body.period_ms = Number(per); body.lease = LEASE; }
    api("POST", "/api/send", body).then((j) => {
      show(per ? `sending ${j.id} every ${per} ms while this page is open` : `sent ${j.id}`, "info");
      if (j.periodic) { holdLease(j.periodic); periodicList(j.periodic); }
    }).catch(() => {});
  };
  const nmtCmd = el("select", { id: "nmt-all-command" }, ...["start", "stop", "preop", "reset", "reset-comm"].map((c) => el("option", { value: c }, c)));
  const nmtNode = tx("nmt-all-node", { size: "4", value: "0", title: "0: all nodes" });
  const nmtSend = el("button", { id: "nmt-all-send" }, "Send NMT");
  nmtSend.onclick = () => api("POST", "/api/nmt", { command: nmtCmd.value, node: Number(nmtNode.value) })
    .then((j) => show(`NMT ${j.command} sent to ${j.node ? `node ${j.node}` : "all nodes"}`, "info")).catch(() => {});
  const box = el("section", { id: "bus-tool-box" },
    el("h2", {}, "Bus trace"),
    el("div", { class: "trace-controls" }, el("label", {}, "view ", sel), pause,
      filt("from", "0x000", 8), filt("to", "0x7FF", 8), filt("node", "1…127", 4),
      el("span", {}, "export ", el("a", { id: "trace-pcapng", download: "canpos-trace.pcapng" }, "pcapng"), " · ",
        el("a", { id: "trace-candump", download: "canpos-trace.log" }, "candump")), clear,
      el("span", { id: "trace-error", class: "alarm" })),
    el("table", { id: "trace" }, cols("dir", "identifier", "DLC", "data", "count", "cycle / ms", "decoded"), el("tbody")),
    el("div", { id: "trace-log-box", hidden: "" }, el("table", { id: "trace-log" }, cols("time / s", "dir", "identifier", "DLC", "data", "decoded"), el("tbody"))),
    el("h3", {}, "Transmit"),
    el("div", { class: "tx" },
      el("label", {}, "identifier ", tx("tx-id", { size: "10", placeholder: "0x123" })),
      el("label", {}, tx("tx-ext", { type: "checkbox" }), " extended"),
      el("label", {}, tx("tx-rtr", { type: "checkbox" }), " remote"),
      el("label", {}, "DLC ", tx("tx-dlc", { size: "2", placeholder: "auto" })),
      el("label", {}, "data ", tx("tx-data", { size: "24", placeholder: "11 22 33" })),
      el("label", {}, "every ", tx("tx-period", { size: "6", placeholder: "once" }), " ms"), send),
    el("ul", { id: "tx-periodic" }),
    el("div", { class: "tx" }, el("label", {}, "NMT ", nmtCmd), el("label", {}, " to node ", nmtNode, " (0: all)"), nmtSend));
  $("#bus-tool").append(box);
  exportLinks();
}

buildTrace();
if (typeof fetch === "function") tracePoll();
