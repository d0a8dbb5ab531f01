// fieldguard console: reads /api/* (GET only) and redraws. Nothing here can change the box.
"use strict";
const $ = (id) => document.getElementById(id);
const fmt = (v, d = 1) => (v === null || v === undefined) ? "-" : Number(v).toFixed(d);

function cell(tr, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  tr.appendChild(td);
  return td;
}

function fill(tbody, rows) {
  tbody.replaceChildren(...rows);
}

function drawStatus(s) {
  const banner = $("banner");
  banner.className = "state-" + (s.state || "unknown");
  $("state").textContent = s.state || "?";
  $("reason").textContent = s.reason || "";
  $("mode").textContent = "mode " + (s.mode || "?");
  $("cycles").textContent = "· cycle " + (s.cycles ?? "-");
  $("conn").textContent = "";
  const devs = Object.entries(s.devices || {}).map(([name, h]) => {
    const tr = document.createElement("tr");
    tr.dataset.device = name;
    cell(tr, name);
    cell(tr, h.kind || "");
    cell(tr, h.state || "?", h.state === "ok" ? "ok" : "bad");
    cell(tr, h.age_s === null || h.age_s === undefined ? "-" : fmt(h.age_s, 2) + " s");
    cell(tr, h.reason || (h.required ? "required" : "optional"));
    return tr;
  });
  fill($("devices").tBodies[0], devs);
  $("faults").textContent = (s.faults || []).join(" · ");
  const t = s.timing_ms || {}, b = s.budget_ms || {};
  const rows = Object.keys(t).map((k) => {
    const tr = document.createElement("tr");
    cell(tr, k);
    for (const q of ["last", "p50", "p99", "max"]) cell(tr, fmt(t[k][q], 2));
    cell(tr, b[k] === undefined ? (k === "cycle" ? "period" : "") : fmt(b[k], 0));
    return tr;
  });
  fill($("timing").tBodies[0], rows);
  const sk = Object.entries(s.skipped || {}).map(([k, v]) => k + " " + v).join(", ");
  $("loopinfo").textContent = "overruns " + (s.overruns ?? "-") + (sk ? " · skipped " + sk : "") +
    (s.sim ? " · sim " + fmt(s.sim.distance_m, 0) + " m driven, " + (s.sim.collisions ?? 0) + " collisions" : "");
  const tracks = s.tracks || [];
  fill($("tracks").tBodies[0], tracks.map((k) => {
    const tr = document.createElement("tr");
    cell(tr, String(k.id ?? ""));
    cell(tr, fmt(k.x_m));
    cell(tr, fmt(k.y_m));
    cell(tr, k.vx_mps === undefined ? "-" : fmt(Math.hypot(k.vx_mps, k.vy_mps || 0)));
    cell(tr, (k.sources || []).join(", ") || String(k.label ?? k.class ?? ""));
    return tr;
  }));
  $("notracks").hidden = tracks.length > 0;
}

async function getJSON(url) {
  const r = await fetch(url, { cache: "no-store" });
  if (!r.ok) throw new Error(url + ": " + r.status);
  return r.json();
}

async function tickStatus() {
  try {
    drawStatus(await getJSON("/api/status"));
  } catch (e) {
    $("banner").className = "state-unknown";
    $("state").textContent = "NO DATA";
    $("reason").textContent = "the console cannot reach the box (" + e.message + ")";
  }
}

function reloadImage(img, url) {
  const next = new Image();
  next.onload = () => { img.src = next.src; img.hidden = false; };
  next.onerror = () => { if (img.id === "view") { img.hidden = true; $("view-cap").textContent = "no camera picture (no camera in this configuration, or none yet)"; } };
  next.src = url + "?t=" + Date.now();
}

function tickImages() {
  reloadImage($("view"), "/api/view.jpg");
  reloadImage($("grid"), "/api/grid.jpg");
}

async function tickLists() {
  try {
    const stops = await getJSON("/api/stops");
    fill($("stops"), stops.slice().reverse().map((s) => {
      const d = document.createElement("div");
      d.className = "stop";
      const img = document.createElement("img");
      img.src = s.image;
      img.alt = "stop " + s.n;
      const p = document.createElement("div");
      p.textContent = s.wall + " (t " + fmt(s.stamp_s) + " s): " + s.reason;
      d.append(img, p);
      return d;
    }));
    if (!stops.length) $("stops").textContent = "no stop since the console started";
    const inc = await getJSON("/api/incidents");
    $("incdir").textContent = inc.dir ? "recorded under " + inc.dir : "incident recording is off ([status] incident_dir)";
    fill($("incidents"), inc.incidents.map((i) => {
      const li = document.createElement("li");
      const a = document.createElement("a");
      a.href = i.download;
      a.textContent = i.name;
      a.setAttribute("download", i.name + ".tar");
      li.append(a, document.createTextNode(" " + (i.reason || "") + " (" + fmt(i.bytes / 1e6) + " MB)"));
      return li;
    }));
  } catch (e) { /* the status banner already says when the box is unreachable */ }
}

tickStatus(); tickImages(); tickLists();
setInterval(tickStatus, 1000);
setInterval(tickImages, 500);
setInterval(tickLists, 5000);
