// canpos dashboard, a node's object dictionary and PDOs (docs/DASHBOARD.md "Object dictionary",
// "PDO mappings"): the table with each object's range, "Read all" with its progress, writes,
// the DCF of the values read and the model's EDS; each TPDO's parameters and mapping read over
// SDO and a remap; the note on nodes without a control interface. Everything through the same
// HTTP API a script calls. Uses app.js's api(), show(), el() and $() (loaded after this file).
"use strict";

window.canposOd = (() => {
  // Per node: the rows of its object table by "INDEX/SUB", and its last snapshot entry.
  const nodes = {};
  const state = (node) => (nodes[node] ??= { rows: new Map(), entries: null, snap: null, reading: false });

  // One request, its status and JSON answer; never throws (a network error is status 0).
  async function call(method, url, body) {
    const opts = { method, headers: {} };
    if (method !== "GET") {
      opts.body = JSON.stringify(body ?? {});
      opts.headers["content-type"] = "application/json";
    }
    try {
      const r = await fetch(url, opts);
      const j = await r.json().catch(() => ({ ok: false, error: `HTTP ${r.status}` }));
      return { status: r.status, j };
    } catch (e) {
      return { status: 0, j: { ok: false, error: String(e) } };
    }
  }

  // A value as the page shows it: the typed value and the bytes; a position (0x6020) also in
  // mm with the resolution of the node's position step (0x6005/1).
  function valueText(node, e, r) {
    let text = `${r.value} [${r.hex}]`;
    const res = state(node).snap && state(node).snap.resolution;
    const steps = Number.parseInt(r.value, 10);
    if (e.index === "0x6020" && e.sub > 0 && res && res.position_step_nm && Number.isFinite(steps)) {
      text += ` = ${(steps * res.position_step_nm / 1e6).toFixed(res.position_decimals)} mm`;
    }
    return text;
  }

  function attach(sec, node) {
    const st = state(node);
    const box = el("div", { class: "od-box" });
    const progress = el("span", { class: "od-progress" });
    const readAll = el("button", { class: "od-read-all", title: "SDO upload of every readable object" }, "Read all");
    readAll.onclick = () => readAllOd(node, box, progress, readAll);
    sec.append(el("h3", {}, "Object dictionary ",
      el("button", { class: "od-load", onclick: () => loadOd(node, box) }, "Load"), " ", readAll, " ",
      el("button", { class: "od-dcf", title: "the values read, as a DCF (canpos run --dcf FILE)", onclick: () => download(node, "dcf") }, "Export DCF"), " ",
      el("button", { class: "od-eds", title: "the model's EDS", onclick: () => download(node, "eds") }, "EDS"), " ",
      progress), box);
    const pdoBox = el("div", { class: "pdo-box" });
    sec.append(el("h3", {}, "PDO mappings ",
      el("button", { class: "pdo-load", onclick: () => loadPdo(node, pdoBox) }, "Read TPDOs")), pdoBox);
    st.box = box;
  }

  // The DCF / EDS as a file download; an error (nothing read yet, an EDS device) is shown.
  async function download(node, kind) {
    const r = await fetch(`/api/nodes/${node}/${kind}`).catch((e) => ({ ok: false, statusText: String(e) }));
    if (!r.ok) {
      const j = r.json ? await r.json().catch(() => ({})) : {};
      show(`${r.status ?? ""}: ${j.error || r.statusText}`);
      return;
    }
    const name = (/filename="([^"]+)"/.exec(r.headers.get("content-disposition") || "") || [])[1] || `node-${node}.${kind}`;
    const url = URL.createObjectURL(await r.blob());
    const a = el("a", { href: url, download: name });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  }

  async function loadOd(node, box) {
    const j = await api("GET", `/api/nodes/${node}/od`).catch(() => null);
    if (!j) return null;
    const st = state(node);
    st.rows.clear();
    const tb = el("tbody");
    for (const e of j.entries) {
      const key = `${e.index}/${e.sub}`;
      const val = el("td", { class: "value" }, "");
      const range = e.range ? e.range.text : "";
      const input = el("input", { class: "write-value", placeholder: range, title: `${e.type}: ${range}` });
      const read = async () => {
        const r = await api("GET", `/api/nodes/${node}/sdo/${e.index}/${e.sub}`).catch(() => null);
        if (r) { val.textContent = valueText(node, e, r); val.className = "value"; }
      };
      const write = async () => {
        const r = await api("PUT", `/api/nodes/${node}/sdo/${e.index}/${e.sub}`, { value: input.value }).catch(() => null);
        if (r) show(`node ${node}: wrote ${key}`, "info");
        // Read back either way: a refused write shows the value it left unchanged.
        if (e.access !== "wo") await read();
      };
      const acts = el("td", {});
      if (e.access !== "wo") acts.append(el("button", { class: "read", onclick: read }, "read"));
      if (e.access === "rw" || e.access === "wo") {
        input.onkeydown = (ev) => { if (ev.key === "Enter") write(); };
        acts.append(input, el("button", { class: "write", onclick: write }, "write"));
      }
      const tr = el("tr", { "data-key": key }, el("td", {}, e.index), el("td", {}, String(e.sub)),
        el("td", {}, e.name), el("td", {}, e.type), el("td", {}, e.access), el("td", { class: "range" }, range), val, acts);
      tb.append(tr);
      st.rows.set(key, { e, val });
    }
    st.entries = j.entries;
    box.replaceChildren(el("table", { class: "od" },
      el("thead", {}, el("tr", {}, ...["index", "sub", "name", "type", "access", "range", "value", ""].map((h) => el("th", {}, h)))), tb));
    return j.entries;
  }

  // Every readable object, one SDO upload after the other. An object the node refuses (SDO
  // abort) shows the abort and the run goes on; anything else (no answer twice, the bus busy
  // or gone) ends it with the reason, so a node that stops answering ends it at its first
  // object without an answer.
  async function readAllOd(node, box, progress, button) {
    const st = state(node);
    if (st.reading) return;
    st.reading = true;
    button.disabled = true;
    try {
      const entries = await loadOd(node, box);
      if (!entries) return;
      const todo = entries.filter((e) => e.access !== "wo");
      let done = 0, refused = 0;
      progress.className = "od-progress";
      for (const e of todo) {
        const key = `${e.index}/${e.sub}`;
        const row = st.rows.get(key);
        progress.textContent = `reading ${key}: ${done} of ${todo.length}` + (refused ? ` (${refused} refused)` : "");
        let { status, j } = await call("GET", `/api/nodes/${node}/sdo/${e.index}/${e.sub}`);
        // No answer: tried once more (a loaded host may answer late, D45), then the run ends.
        if (status === 502 && /SDO timeout/.test(j.error || "")) {
          ({ status, j } = await call("GET", `/api/nodes/${node}/sdo/${e.index}/${e.sub}`));
        }
        if (status === 200 && j.ok) {
          row.val.textContent = valueText(node, e, j);
          row.val.className = "value";
        } else if (status === 502 && /SDO abort/.test(j.error || "")) {
          refused++;
          row.val.textContent = (j.error || "").replace(/^node \d+: /, "");
          row.val.className = "value refused";
        } else {
          const why = `read all of node ${node} stopped at ${key}: ${j.error || `HTTP ${status}`}; ${done} of ${todo.length} objects read`;
          progress.textContent = why;
          progress.className = "od-progress error";
          show(why);
          return;
        }
        done++;
      }
      progress.textContent = `read all: ${done} of ${todo.length} objects` + (refused ? ` (${refused} refused by the node)` : "") + "; Export DCF saves them";
      progress.className = "od-progress done";
    } finally {
      st.reading = false;
      button.disabled = false;
    }
  }

  const mappedText = (m) => `${m.name ?? "unknown object"} (${m.index}/${m.sub}, ${m.bits} bit)`;

  async function loadPdo(node, box) {
    const j = await api("GET", `/api/nodes/${node}/pdo`).catch(() => null);
    if (!j) return;
    const tb = el("tbody");
    for (const t of j.tpdos) {
      const input = el("input", { class: "remap-objects", size: "30",
        value: t.mapping.map((m) => `${m.index}/${m.sub}`).join(", "),
        title: "objects to map, in order: INDEX/SUB, comma-separated (the list below names those the node may map)" });
      const ttype = el("input", { class: "remap-type", size: "3", value: String(t.transmission_type), title: "transmission type (0…255)" });
      const event = el("input", { class: "remap-event", size: "5", value: t.event_ms == null ? "" : String(t.event_ms), title: "event timer, ms (0…65535)" });
      if (t.event_ms == null) event.disabled = true;
      const go = async () => {
        const mapping = input.value.split(/[\s,;]+/).filter(Boolean);
        const body = { mapping };
        // Numbers as typed: the server refuses what is no number of the range, before the bus.
        const asNumber = (v) => (/^\s*\d+\s*$/.test(v) ? Number(v) : v);
        if (ttype.value.trim() !== String(t.transmission_type)) body.transmission_type = asNumber(ttype.value);
        if (!event.disabled && event.value.trim() !== String(t.event_ms)) body.event_ms = asNumber(event.value);
        const { status, j } = await call("PUT", `/api/nodes/${node}/pdo/${t.tpdo}`, body);
        // Shown again as the node has it now (unchanged after a refusal), then the outcome.
        await loadPdo(node, box);
        if (j.ok) show(`node ${node}: TPDO ${t.tpdo} remapped: ${j.tpdo.mapping.map((m) => m.name ?? m.raw).join(", ") || "nothing mapped"}`, "info");
        else show(`${status}: ${j.error || "request failed"}`);
      };
      input.onkeydown = (ev) => { if (ev.key === "Enter") go(); };
      tb.append(el("tr", { "data-tpdo": t.tpdo, class: t.valid ? "valid" : "invalid" },
        el("td", {}, `TPDO ${t.tpdo}`),
        el("td", { class: "cob" }, `${t.cob_id} (${t.valid ? `CAN-ID ${t.can_id}` : "invalid"})`),
        el("td", { class: "ttype" }, `${t.transmission_type}: ${t.transmission}`),
        el("td", { class: "inhibit" }, t.inhibit_ms == null ? "–" : `${t.inhibit_ms} ms`),
        el("td", { class: "event" }, t.event_ms == null ? "–" : `${t.event_ms} ms`),
        el("td", { class: "mapped" }, ...(t.mapping.length ? t.mapping.map((m) => el("div", {}, mappedText(m))) : ["nothing mapped"])),
        el("td", { class: "remap" }, input, " type ", ttype, " event ", event, " ms ",
          el("button", { class: "remap-go", onclick: go }, "Remap"))));
    }
    box.replaceChildren(
      el("table", { class: "pdo" }, el("thead", {}, el("tr", {}, ...["TPDO", "COB-ID (0x180x/1)", "transmission type", "inhibit time", "event timer", "mapped objects (0x1A0x)", "remap (invalidate, count 0, entries, count, validate)"].map((h) => el("th", {}, h)))), tb),
      el("details", { class: "mappable" }, el("summary", {}, `objects this model's TPDOs may map (${j.mappable.length})`),
        el("ul", {}, ...j.mappable.map((m) => el("li", {}, `${m.index}/${m.sub} ${m.name} (${m.bits} bit)`)))));
  }

  // Called with each snapshot: keeps the node's resolution and says, on a node without a
  // control interface, how to give it one.
  function update(sec, n) {
    state(n.node).snap = n;
    let note = $(".control-note", sec);
    if (!note) {
      note = el("p", { class: "control-note" },
        "No control interface known to the dashboard for this node: no magnet, motion, fault or power-cycle controls. ",
        "Start the sensor with --control ADDR and start the dashboard with the same --control ADDR ",
        "(or use --web on canpos run / scenario, whose sensors the dashboard drives directly).");
      $(".controls", sec).after(note);
    }
    note.hidden = !!n.control;
  }

  return { attach, update, loadOd, loadPdo };
})();
