// The dashboard page: polls /api/state, draws the target face and the distance curve as SVG,
// lists the services and port rates, and reloads the frame when the detector has a new one.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const POLL_MS = 500;
let frameVersion = 0;

function el(name, attrs, parent) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}

function cm(metres) {
  return (100 * metres).toFixed(1) + " cm";
}

function drawFace(state) {
  const svg = document.getElementById("face");
  svg.replaceChildren();
  const done = state.rollouts.filter((r) => r.r_m);
  const faceCm = 100 * state.face[state.face.length - 1].radius_m;
  let extent = faceCm + 2;
  for (const r of done) extent = Math.max(extent, 100 * Math.hypot(r.r_m[0], r.r_m[1]) + 2);
  svg.setAttribute("viewBox", `${-extent} ${-extent} ${2 * extent} ${2 * extent}`);
  for (const ring of [...state.face].reverse()) {
    el("circle", { cx: 0, cy: 0, r: 100 * ring.radius_m, fill: ring.colour,
      stroke: "#777", "stroke-width": 0.15, class: "ring" }, svg);
  }
  el("circle", { cx: 0, cy: 0, r: 100 * state.hit_radius_m, fill: "none", stroke: "#2e7d32",
    "stroke-width": 0.4, "stroke-dasharray": "1 0.6", class: "hit-ring" }, svg);
  const points = done.map((r) => [100 * r.r_m[0], -100 * r.r_m[1]]);
  if (points.length > 1) {
    el("polyline", { points: points.map((p) => p.join(",")).join(" "), fill: "none",
      stroke: "#90a4ae", "stroke-width": 0.25 }, svg);
  }
  done.forEach((r, k) => {
    const last = k === done.length - 1;
    const shade = done.length > 1 ? k / (done.length - 1) : 1;
    const dot = el("circle", {
      cx: points[k][0], cy: points[k][1], r: r.hit ? 1.3 : 0.9,
      fill: `hsl(${190 + 110 * shade}, 90%, ${70 - 20 * shade}%)`,
      stroke: last ? "#000" : "#fff", "stroke-width": last ? 0.4 : 0.2,
      class: "impact", "data-index": r.index,
    }, svg);
    el("title", {}, dot).textContent = `rollout ${r.index}: ${cm(r.distance_m)}${r.hit ? " (hit)" : ""}`;
  });
}

function drawCurve(state) {
  const svg = document.getElementById("curve");
  svg.replaceChildren();
  const W = 520, H = 260, L = 48, R = 12, T = 12, B = 34;
  const done = state.rollouts.filter((r) => r.distance_m !== null);
  const ys = done.map((r) => 100 * r.distance_m);
  const ymax = Math.max(100 * state.hit_radius_m * 1.5, ...ys, 1) * 1.1;
  const first = done.length ? done[0].index : 0;
  const span = Math.max(done.length ? done[done.length - 1].index - first : 1, 1);
  const x = (k) => L + ((done[k].index - first) * (W - L - R)) / span;
  const y = (v) => T + (H - T - B) * (1 - v / ymax);
  el("line", { x1: L, y1: H - B, x2: W - R, y2: H - B, stroke: "#444" }, svg);
  el("line", { x1: L, y1: T, x2: L, y2: H - B, stroke: "#444" }, svg);
  for (let i = 0; i <= 4; i++) {
    const v = (ymax * i) / 4;
    el("line", { x1: L - 4, y1: y(v), x2: L, y2: y(v), stroke: "#444" }, svg);
    el("text", { x: L - 6, y: y(v) + 4, "text-anchor": "end", "font-size": 11 }, svg)
      .textContent = v.toFixed(0);
  }
  el("text", { x: 12, y: T + (H - T - B) / 2, "font-size": 11, "text-anchor": "middle",
    transform: `rotate(-90 12 ${T + (H - T - B) / 2})` }, svg).textContent = "distance (cm)";
  el("text", { x: L + (W - L - R) / 2, y: H - 6, "font-size": 11, "text-anchor": "middle" }, svg)
    .textContent = "rollout";
  const hy = y(100 * state.hit_radius_m);
  el("line", { x1: L, y1: hy, x2: W - R, y2: hy, stroke: "#c62828", "stroke-dasharray": "5 4",
    class: "hit-line" }, svg);
  el("text", { x: W - R, y: hy - 4, "text-anchor": "end", "font-size": 11, fill: "#c62828" }, svg)
    .textContent = `${(100 * state.hit_radius_m).toFixed(0)} cm ring`;
  if (done.length > 1) {
    el("polyline", { points: ys.map((v, k) => `${x(k)},${y(v)}`).join(" "), fill: "none",
      stroke: "#1565c0", "stroke-width": 2, class: "distance-line" }, svg);
  }
  ys.forEach((v, k) => {
    el("circle", { cx: x(k), cy: y(v), r: done[k].hit ? 4 : 2.5,
      fill: done[k].hit ? "#2e7d32" : "#1565c0", class: "distance-point" }, svg);
  });
  if (done.length) {
    const last = done[done.length - 1].index;
    el("text", { x: L, y: H - B + 14, "font-size": 11, "text-anchor": "middle" }, svg)
      .textContent = first;
    el("text", { x: x(done.length - 1), y: H - B + 14, "font-size": 11, "text-anchor": "middle" },
      svg).textContent = last;
  }
}

function showServices(state) {
  const list = document.getElementById("services");
  list.replaceChildren();
  for (const s of state.services) {
    const li = document.createElement("li");
    li.dataset.service = s.name;
    li.dataset.alive = String(s.alive);
    li.textContent = `${s.name} ${s.alive ? "alive" : "not alive"}`;
    list.appendChild(li);
  }
  const l = state.learner;
  const parts = [`learner: ${l.state || "?"}`];
  if (l.rollouts !== undefined) {
    parts.push(l.budget !== undefined ? `${l.rollouts} of ${l.budget} rollouts` : `${l.rollouts} rollouts`);
  }
  if (l.best_distance_m !== undefined) parts.push(`best ${cm(l.best_distance_m)}`);
  if (l.hit_at !== undefined) parts.push(`hit at rollout ${l.hit_at}`);
  document.getElementById("learner-state").textContent = parts.join(" · ");
}

function showRates(state) {
  const body = document.querySelector("#rates tbody");
  body.replaceChildren();
  const prefix = state.robot + "/";
  for (const r of state.rates) {
    const tr = document.createElement("tr");
    tr.dataset.key = r.key;
    if (r.hz === 0) tr.className = "silent";
    const key = document.createElement("td");
    key.textContent = r.key.startsWith(prefix) ? r.key.slice(prefix.length) : r.key;
    const hz = document.createElement("td");
    hz.className = "hz";
    hz.textContent = r.hz === null ? "…" : r.hz.toFixed(1);
    tr.append(key, hz);
    body.appendChild(tr);
  }
}

function showFrame(state) {
  const note = document.getElementById("frame-note");
  if (state.frame.version !== frameVersion && state.frame.version > 0) {
    frameVersion = state.frame.version;
    const img = document.getElementById("frame");
    img.src = `/api/frame.png?v=${frameVersion}`;
    img.alt = `detector frame ${frameVersion}`;
  }
  note.textContent = frameVersion ? `frame ${frameVersion}` : state.frame.error || "no frame measured yet";
}

function show(state) {
  document.getElementById("robot").textContent = state.robot;
  document.getElementById("session").textContent =
    state.session ? `session ${state.session}` : "no session yet";
  const done = state.rollouts.filter((r) => r.distance_m !== null);
  const latest = done[done.length - 1];
  document.getElementById("latest-distance").textContent = latest ? cm(latest.distance_m) : "–";
  document.getElementById("rollout-count").textContent = state.rollouts.length;
  document.getElementById("hit-count").textContent = done.filter((r) => r.hit).length;
  drawFace(state);
  drawCurve(state);
  showServices(state);
  showRates(state);
  showFrame(state);
}

async function poll() {
  const connection = document.getElementById("connection");
  try {
    const response = await fetch("/api/state", { cache: "no-store" });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    show(await response.json());
    connection.textContent = `updated ${new Date().toLocaleTimeString()}`;
    connection.className = "ok";
  } catch (err) {
    connection.textContent = `dashboard unreachable (${err.message})`;
    connection.className = "stale";
  }
  setTimeout(poll, POLL_MS);
}

poll();
