// canpos dashboard: keeps the page's periodic transmissions going while the page is open
// (docs/DASHBOARD.md, "Transmit"; D61). The server ends a leased transmission 5 s after its
// lease's last renewal; this worker renews the page's lease every second while the page says it
// holds transmissions. A worker, not the page's own timer: a browser throttles the timers of a
// hidden tab to one a minute after a while, a worker's it does not.
"use strict";
let lease = null, active = false;
async function renew() {
  if (!lease || !active) return;
  try {
    await fetch("/api/send/renew", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ lease }) });
  } catch (e) { /* the next second tries again; the lease allows for four misses */ }
}
onmessage = (e) => { lease = e.data.lease; const was = active; active = e.data.active; if (active && !was) renew(); };
setInterval(renew, 1000);
