// The bench's live view: state pushed by nhfd.web.server over the WebSocket; operations back.
"use strict";
const $ = (id) => document.getElementById(id);
let ws = null;
let nextId = 1;
let seeded = false;  // sliders set from the daemon's state once, then left to the user
const pending = new Map();

// status.frames.refine: the tier of the view on the panel, how far its refinement went and the
// estimated PSNR (nhfctl status prints the same line).
function refineText(r) {
  if (!r) return "network (open loop)";
  const gain = r.psnr_db === null ? "no estimate yet"
    : `${r.psnr_db.toFixed(1)} dB (from ${r.start_psnr_db.toFixed(1)})`;
  const subframes = r.subframes > 1 ? `, ${r.subframes} subframes` : "";
  return `${r.tier}: ${r.iterations} iterations in ${r.seconds.toFixed(1)} s, ${gain}${subframes}; ${r.stop || "refining"}`;
}

function connect() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  ws = new WebSocket(`${scheme}//${location.host}/ws`);
  ws.onopen = () => { $("connection").textContent = "live"; $("connection").className = "ok"; };
  ws.onclose = () => {
    $("connection").textContent = "disconnected";
    $("connection").className = "bad";
    setTimeout(connect, 2000);
  };
  ws.onmessage = (event) => {
    const msg = JSON.parse(event.data);
    if (msg.type === "state") showState(msg);
    else if (msg.type === "reply") showReply(msg);
    else if (msg.type === "refused") showError(`${msg.count} sent too fast: ${msg.error.message}`);
  };
}

// The server takes at most daemon.web.messages_per_s messages a second from a page (20 by
// default) and drops the rest unanswered: a dragged slider sends its position at most every
// VIEW_INTERVAL_MS, and always the last one.
const VIEW_INTERVAL_MS = 100;
let viewTimer = null;
let viewDue = 0;
function sendView() {
  if (viewTimer !== null) return;  // the pending send reads the slider when it goes
  const wait = viewDue - Date.now();
  if (wait > 0) {
    viewTimer = setTimeout(() => { viewTimer = null; sendView(); }, wait);
    return;
  }
  viewDue = Date.now() + VIEW_INTERVAL_MS;
  send("view", { orbit: orbitNow() });
}

function showError(message) {
  const li = document.createElement("li");
  li.className = "bad";
  li.textContent = message;
  $("errors").prepend(li);
}

function send(op, params) {
  if (!ws || ws.readyState !== WebSocket.OPEN) return;
  const id = nextId++;
  pending.set(id, op);
  ws.send(JSON.stringify({ id, op, ...params }));
}

function text(id, value) { $(id).textContent = value; }

function showImage(which, thumb) {
  if (thumb === undefined) return;  // unchanged since the last push
  const img = $(which);
  if (thumb === null) { img.removeAttribute("src"); return; }
  img.src = thumb.png;
  const [h, w] = thumb.size_hw;
  const info = which === "slm" ? `${w} × ${h}, ${thumb.showing}`
    : `${w} × ${h}, peak ${thumb.peak_linear.toPrecision(3)}, ` +
      new Date(thumb.time_s * 1000).toLocaleTimeString();
  text(`${which}-info`, `(${info}${thumb.step > 1 ? `, every ${thumb.step}th pixel` : ""})`);
}

function showState(msg) {
  showImage("slm", msg.slm);
  showImage("camera", msg.camera);
  if (msg.daemon_error) { text("daemon", msg.daemon_error); $("daemon").className = "bad"; return; }
  const s = msg.status;
  text("daemon", `daemon ${s.daemon.state}, version ${s.daemon.version}`);
  $("daemon").className = "";
  const laser = s.laser;
  if (laser.armed) {
    text("armed", `ARMED, ${Math.round(laser.armed_remaining_s)} s left`);
    $("armed").className = "armed";
  } else {
    text("armed", laser.backend === "none" ? "no laser" : "not armed");
    $("armed").className = "";
  }
  const rows = Object.entries(laser.channels || {}).map(([name, c]) =>
    `<tr><td>${name}</td><td>${c.enabled ? "on" : "off"}</td><td>${c.power_pct}%</td></tr>`);
  $("channels").tBodies[0].innerHTML = rows.join("");
  const stage = s.devices.stage || {};
  text("stage", stage.position_mm !== undefined
    ? `${stage.position_mm.toFixed(3)} mm${stage.homed ? ", homed" : ""}${stage.moving ? ", moving" : ""}`
    : (stage.error || "none"));
  text("display", s.display);
  text("scene", s.scene ? `${s.scene.path} (${s.scene.gaussians} Gaussians)` : "none");
  text("model", typeof s.model === "string" ? s.model : `${s.model.path} (${s.model.profile || "?"})`
    + (s.model.tuned_for ? `, tuned for calibration ${s.model.tuned_for.calibration}` : ""));
  const cal = s.calibration || {};
  text("calibration", cal.loaded ? `${cal.file}` : (cal.error || "none (uncalibrated focus mapping)"));
  text("fps", msg.fps === null ? "–" : `${msg.fps.toFixed(1)} frames/s (${s.frames.frames_shown} shown)`);
  text("refine", refineText(s.frames.refine));
  const errors = (s.errors || []).slice(-5).reverse();
  $("errors").innerHTML = errors.length ? "" : '<li class="hint">none</li>';
  for (const e of errors) {
    const li = document.createElement("li");
    li.textContent = `${e.source}: ${e.message}`;
    $("errors").appendChild(li);
  }
  if (!seeded) {
    seeded = true;
    const [lo, hi] = cal.focus_range_mm || [-5, 5];
    $("focus").min = lo; $("focus").max = hi;
    const orbit = s.view.requested;
    if (orbit && orbit.kind === "orbit") setOrbit(orbit);
  }
}

function setOrbit(v) {
  $("azimuth").value = v.azimuth_deg; text("az-value", Math.round(v.azimuth_deg));
  $("elevation").value = v.elevation_deg; text("el-value", Math.round(v.elevation_deg));
  $("radius").value = v.radius;
}

function showReply(msg) {
  const op = pending.get(msg.id) || msg.op;
  pending.delete(msg.id);
  if (!msg.ok) {
    const li = document.createElement("li");
    li.className = "bad";
    li.textContent = `${op}: ${msg.error.name}: ${msg.error.message}`;
    $("errors").prepend(li);
    if (op === "snapshot") text("snapshot-result", `failed: ${msg.error.message}`);
    return;
  }
  if (op === "view" && msg.result.view && msg.result.view.kind === "orbit") setOrbit(msg.result.view);
  if (op === "snapshot") {
    const r = msg.result;
    const p = $("snapshot-result");
    p.textContent = "";
    if (r.url) {
      const a = document.createElement("a");
      a.href = r.url; a.textContent = r.path.split("/").pop(); a.download = "";
      p.append("saved ", a);
    } else {
      p.textContent = `job ${r.job} ${r.state}`;
    }
  }
}

function orbitNow() {
  return { azimuth_deg: +$("azimuth").value, elevation_deg: +$("elevation").value,
           radius: +$("radius").value };
}

$("focus").addEventListener("input", () => text("focus-value", (+$("focus").value).toFixed(2)));
$("focus").addEventListener("change", () => send("focus", { z_mm: +$("focus").value }));
for (const id of ["azimuth", "elevation"]) {
  $(id).addEventListener("input", () => {
    text(id === "azimuth" ? "az-value" : "el-value", $(id).value);
    sendView();
  });
}
$("radius").addEventListener("change", sendView);
for (const b of document.querySelectorAll("[data-orbit]")) {
  b.addEventListener("click", () => {
    const [da, de, dr] = b.dataset.orbit.split(",").map(Number);
    send("view", { relative: { d_azimuth_deg: da, d_elevation_deg: de, d_radius: dr } });
  });
}
$("snapshot").addEventListener("click", () => { text("snapshot-result", "capturing…"); send("snapshot", {}); });
$("stop").addEventListener("click", () => send("stop", {}));
$("lasers-off").addEventListener("click", () => send("lasers_off", {}));
connect();
