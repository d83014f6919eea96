// The dashboard page: polls /api/state for the chosen robot, shows the frame of each rollout
// with a caption, the scene view while its panel is open, draws the target face (impacts
// coloured by rollout, with a colour bar) and the distance curve as SVG, lists the services and
// port rates, and offers the robots alive on the router. GETs change nothing on the server: the
// page POSTs (with the server's token) the robot it follows and, with each poll while the scene
// panel is open, that it shows the scene view. While the session waits for the operator (the
// learner's status: `operator`), a banner says what for; a dashboard started with --operator
// (the state's `operator: true`) adds a Confirm button, which POSTs the request number it shows.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const POLL_MS = 500;
const ROBOTS_MS = 5000;
const TOKEN_HEADER = "X-Dashboard-Token"; // the server's token, required on the page's POSTs
// viridis, 0 → 1: the colour of a rollout from the first to the last of the scale
const VIRIDIS = ["#440154", "#482878", "#3e4989", "#31688e", "#26828e",
  "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"];
let robot = null; // null: the dashboard's own robot
let frameVersion = 0;
let sceneVersion = 0;
let token = null; // from the header of the server's answers
let confirming = false; // a Confirm POST in flight
let confirmed = null; // "robot request" last confirmed here: its button stays off

function el(name, attrs, parent) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}

function cm(metres) {
  return (100 * metres).toFixed(1) + " cm";
}

function signed(value) {
  return (value >= 0 ? "+" : "−") + Math.abs(value).toFixed(1);
}

// Round ticks from lo to hi: steps of 1, 2 or 5 × 10^k (at least `minStep`), about `count`.
function niceTicks(lo, hi, count, minStep = 0) {
  if (!(hi > lo)) return [lo];
  const raw = Math.max((hi - lo) / Math.max(count, 1), minStep);
  const power = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
  const ticks = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + 1e-9 * step; v += step) {
    ticks.push(Number(v.toPrecision(12)));
  }
  return ticks;
}

// The smallest round number (1, 2 or 5 × 10^k) at or above `value`.
function niceCeil(value) {
  const power = Math.pow(10, Math.floor(Math.log10(value)));
  return [1, 2, 5, 10].map((m) => m * power).find((s) => s >= value - 1e-9);
}

function viridis(t) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const i = Math.min(Math.floor(x), VIRIDIS.length - 2);
  const [a, b] = [VIRIDIS[i], VIRIDIS[i + 1]].map((h) => [1, 3, 5].map((k) => parseInt(h.substr(k, 2), 16)));
  const mix = a.map((c, k) => Math.round(c + (b[k] - c) * (x - i)));
  return `rgb(${mix.join(", ")})`;
}

// The rollout numbers the colour scale spans: 1 to the session's budget (or the newest).
function colourScale(state) {
  const last = state.rollouts.length ? state.rollouts[state.rollouts.length - 1].index : 1;
  const top = Math.max(state.learner.budget || 0, last, 2);
  return { lo: 1, hi: top, colour: (index) => viridis((index - 1) / (top - 1)) };
}

function drawFace(state, scale) {
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
  const dot = extent / 40; // cm: a marker's radius, the same on screen whatever the extent
  done.forEach((r, k) => {
    const last = k === done.length - 1;
    const marker = el("circle", {
      cx: points[k][0], cy: points[k][1], r: (r.hit ? 1.5 : 1) * dot,
      fill: scale.colour(r.index),
      stroke: last ? "#000" : "#fff", "stroke-width": (last ? 0.4 : 0.15) * dot,
      class: "impact", "data-index": r.index,
    }, svg); // in rollout order: the newest on top
    el("title", {}, marker).textContent = `rollout ${r.index}: ${cm(r.distance_m)}${r.hit ? " (hit)" : ""}`;
  });
}

function drawColourbar(scale) {
  const svg = document.getElementById("colourbar");
  svg.replaceChildren();
  const top = 12, bottom = 288, x = 4, w = 14;
  const defs = el("defs", {}, svg);
  const gradient = el("linearGradient", { id: "rollout-gradient", x1: 0, y1: 1, x2: 0, y2: 0 }, defs);
  VIRIDIS.forEach((colour, k) => {
    el("stop", { offset: k / (VIRIDIS.length - 1), "stop-color": colour }, gradient);
  });
  el("rect", { x, y: top, width: w, height: bottom - top, fill: "url(#rollout-gradient)",
    stroke: "#555", "stroke-width": 0.5, class: "colourbar" }, svg);
  const y = (index) => bottom - ((index - scale.lo) * (bottom - top)) / (scale.hi - scale.lo);
  for (const tick of niceTicks(scale.lo, scale.hi, 5, 1)) {
    if (tick < scale.lo) continue;
    el("line", { x1: x + w, y1: y(tick), x2: x + w + 4, y2: y(tick), stroke: "#444" }, svg);
    el("text", { x: x + w + 6, y: y(tick) + 4, "font-size": 11, class: "colour-tick" }, svg)
      .textContent = tick;
  }
  el("text", { x: 58, y: (top + bottom) / 2, "font-size": 11, "text-anchor": "middle",
    transform: `rotate(90 58 ${(top + bottom) / 2})` }, svg).textContent = "rollout";
}

function drawCurve(state, scale) {
  const svg = document.getElementById("curve");
  svg.replaceChildren();
  // the plot area; every label sits in the margins around it, never over the data
  const W = 960, H = 300, L = 56, R = 84, T = 12, B = 44;
  const done = state.rollouts.filter((r) => r.distance_m !== null);
  const ys = done.map((r) => 100 * r.distance_m);
  const ymax = niceCeil(Math.max(100 * state.hit_radius_m * 2, ...ys) * 1.05);
  const first = done.length ? Math.min(1, done[0].index) : 1;
  const lastIndex = done.length ? done[done.length - 1].index : 10;
  const xmax = Math.max(lastIndex, first + 4);
  const x = (index) => L + ((index - first) * (W - L - R)) / (xmax - first);
  const y = (v) => T + (H - T - B) * (1 - v / ymax);
  el("rect", { x: L, y: T, width: W - L - R, height: H - T - B, fill: "none",
    class: "plot-area" }, svg);
  for (const v of niceTicks(0, ymax, 5)) {
    el("line", { x1: L, y1: y(v), x2: W - R, y2: y(v), stroke: "#e0e0e0" }, svg);
    el("line", { x1: L - 4, y1: y(v), x2: L, y2: y(v), stroke: "#444" }, svg);
    el("text", { x: L - 7, y: y(v) + 4, "text-anchor": "end", "font-size": 12,
      class: "y-tick" }, svg).textContent = v;
  }
  for (const v of niceTicks(first, xmax, 8, 1)) { // rollouts are whole
    if (v < first) continue;
    el("line", { x1: x(v), y1: H - B, x2: x(v), y2: H - B + 4, stroke: "#444" }, svg);
    el("text", { x: x(v), y: H - B + 17, "text-anchor": "middle", "font-size": 12,
      class: "x-tick" }, svg).textContent = v;
  }
  el("line", { x1: L, y1: H - B, x2: W - R, y2: H - B, stroke: "#444" }, svg);
  el("line", { x1: L, y1: T, x2: L, y2: H - B, stroke: "#444" }, svg);
  el("text", { x: 14, y: T + (H - T - B) / 2, "font-size": 12, "text-anchor": "middle",
    transform: `rotate(-90 14 ${T + (H - T - B) / 2})`, class: "axis-label" }, svg)
    .textContent = "distance (cm)";
  el("text", { x: L + (W - L - R) / 2, y: H - 6, "font-size": 12, "text-anchor": "middle",
    class: "axis-label" }, svg).textContent = "rollout";
  const hy = y(100 * state.hit_radius_m);
  el("line", { x1: L, y1: hy, x2: W - R, y2: hy, stroke: "#c62828", "stroke-dasharray": "5 4",
    class: "hit-line" }, svg);
  el("text", { x: W - R + 6, y: hy + 4, "text-anchor": "start", "font-size": 12,
    fill: "#c62828", class: "hit-label" }, svg)
    .textContent = `${(100 * state.hit_radius_m).toFixed(0)} cm ring`;
  if (done.length > 1) {
    el("polyline", { points: done.map((r, k) => `${x(r.index)},${y(ys[k])}`).join(" "),
      fill: "none", stroke: "#90a4ae", "stroke-width": 1.5, class: "distance-line" }, svg);
  }
  done.forEach((r, k) => {
    const point = el("circle", { cx: x(r.index), cy: y(ys[k]), r: r.hit ? 5 : 3.5,
      fill: scale.colour(r.index), stroke: r.hit ? "#2e7d32" : "#fff",
      "stroke-width": r.hit ? 2 : 0.8, class: "distance-point" }, svg);
    el("title", {}, point).textContent = `rollout ${r.index}: ${ys[k].toFixed(1)} cm`;
  });
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

function query(extra) {
  const params = new URLSearchParams(extra || {});
  if (robot) params.set("robot", robot);
  const text = params.toString();
  return text ? `?${text}` : "";
}

function caption(row) {
  const figure = document.getElementById("frame-caption");
  figure.replaceChildren();
  const theta = row.theta.map((v) => (100 * v).toFixed(1)).join(", ");
  const parts = [`rollout ${row.index}`, `θ (${theta}) cm`];
  if (row.r_m) {
    parts.push(`r (${signed(100 * row.r_m[0])}, ${signed(100 * row.r_m[1])}) cm`);
    parts.push(`‖r‖ ${cm(row.distance_m)}`);
  } else {
    parts.push(`aborted: ${row.cause || row.status}`);
  }
  figure.append(parts.join(" · "));
  if (row.hit) {
    const hit = document.createElement("span");
    hit.className = "hit";
    hit.textContent = " · HIT";
    figure.append(hit);
  }
  figure.hidden = false;
}

function showFrame(state) {
  const note = document.getElementById("frame-note");
  const img = document.getElementById("frame");
  if (state.frame.version !== frameVersion && state.frame.version > 0) {
    frameVersion = state.frame.version;
    img.src = `/api/frame.png${query({ v: frameVersion })}`;
    img.alt = `detector frame ${frameVersion}`;
    const row = state.rollouts.find((r) => r.index === state.frame.rollout);
    img.dataset.rollout = row ? row.index : "";
    if (row) caption(row);
    else document.getElementById("frame-caption").hidden = true;
  }
  note.textContent = frameVersion
    ? (img.dataset.rollout ? `the detector's frame of rollout ${img.dataset.rollout}` : "the detector's last frame")
    : state.frame.error || "no frame measured yet";
}

function sceneOpen() {
  return document.getElementById("scene-details").open;
}

function showScene(state) {
  const note = document.getElementById("scene-note");
  const scene = state.scene;
  if (!sceneOpen()) return;
  if (scene.version !== sceneVersion && scene.version > 0) {
    sceneVersion = scene.version;
    const img = document.getElementById("scene");
    img.src = `/api/scene.jpg${query({ v: sceneVersion })}`;
    img.alt = `the robot, scene view ${sceneVersion}`;
  }
  if (scene.status === "unavailable") note.textContent = `no scene view: ${scene.error}`;
  else if (!sceneVersion) note.textContent = "the camera is building the scene view…";
  else {
    const at = scene.sim_time === null || scene.sim_time === undefined ? "" : ` at ${scene.sim_time.toFixed(2)} s`;
    note.textContent = `side camera, rendered by the camera service${at}`;
  }
}

function clock(epochS) {
  const t = new Date(epochS * 1000);
  return [t.getHours(), t.getMinutes(), t.getSeconds()]
    .map((v) => String(v).padStart(2, "0")).join(":");
}

// The operator's request the session waits for, with the Confirm button on an operator's
// dashboard; the button keeps the robot and the request number it shows.
function showOperator(state) {
  const panel = document.getElementById("operator-panel");
  const button = document.getElementById("confirm");
  const ask = state.learner.operator;
  if (!ask) {
    panel.hidden = true;
    return;
  }
  const shown = `${state.robot} ${ask.request}`;
  if (panel.dataset.shown !== shown) document.getElementById("operator-note").textContent = "";
  panel.dataset.shown = shown;
  document.getElementById("operator-request").textContent =
    `The session waits for the operator: ${ask.message} (request ${ask.request}, ` +
    `since ${clock(ask.since)}, waits up to ${ask.limit} s)`;
  button.hidden = !state.operator;
  button.dataset.robot = state.robot;
  button.dataset.request = ask.request;
  button.textContent = `Confirm request ${ask.request}: done`;
  button.disabled = confirming || confirmed === shown;
  panel.hidden = false;
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
  const scale = colourScale(state);
  drawFace(state, scale);
  drawColourbar(scale);
  drawCurve(state, scale);
  showServices(state);
  showRates(state);
  showFrame(state);
  showScene(state);
  showOperator(state);
}

// A GET of the dashboard's: the token the server sends with every answer is kept for POSTs.
async function get(path) {
  const response = await fetch(path, { cache: "no-store" });
  token = response.headers.get(TOKEN_HEADER) || token;
  return response;
}

// A POST of the page's own (`/api/watch`, `/api/scene`: for the chosen robot; `/api/confirm`:
// with its `params`), with the token.
async function post(path, params) {
  if (!token) await get("/api/robots");
  return fetch(params ? `${path}?${new URLSearchParams(params)}` : `${path}${query()}`,
    { method: "POST", cache: "no-store", headers: { [TOKEN_HEADER]: token || "" } });
}

async function poll() {
  const connection = document.getElementById("connection");
  try {
    if (sceneOpen()) await post("/api/scene"); // the camera renders it while the panel is open
    let response = await get(`/api/state${query()}`);
    if (response.status === 404 && robot) { // a robot chosen but not followed (yet, or any more)
      const watch = await post("/api/watch");
      if (!watch.ok) throw new Error(`robot ${robot}: ${(await watch.text()).trim()}`);
      response = await get(`/api/state${query()}`);
    }
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

async function listRobots() {
  try {
    const response = await get("/api/robots");
    if (response.ok) {
      const { default: own, robots } = await response.json();
      const select = document.getElementById("robot-select");
      const chosen = robot || own;
      const names = robots.includes(chosen) ? robots : [...robots, chosen].sort();
      if ([...select.options].map((o) => o.value).join() !== names.join()) {
        select.replaceChildren(...names.map((name) => new Option(name, name)));
      }
      select.value = chosen;
      document.getElementById("robot-choice").dataset.robots = names.length;
    }
  } catch (err) {
    // the state poll reports the connection
  }
  setTimeout(listRobots, ROBOTS_MS);
}

document.getElementById("robot-select").addEventListener("change", (event) => {
  robot = event.target.value;
  frameVersion = 0;
  sceneVersion = 0;
  for (const id of ["frame", "scene"]) document.getElementById(id).removeAttribute("src");
  document.getElementById("frame-caption").hidden = true;
  document.getElementById("operator-panel").hidden = true; // until this robot's state comes
  post("/api/watch").catch(() => {}); // the state poll reports a failure
});

document.getElementById("confirm").addEventListener("click", async (event) => {
  const button = event.currentTarget;
  const note = document.getElementById("operator-note");
  const { robot: shownRobot, request } = button.dataset;
  confirming = true;
  button.disabled = true;
  note.textContent = `confirming request ${request}…`;
  try {
    const response = await post("/api/confirm", { robot: shownRobot, request });
    if (response.ok) {
      confirmed = `${shownRobot} ${request}`;
      note.textContent = `request ${request} confirmed`;
    } else {
      note.textContent = `not confirmed: ${(await response.text()).trim()}`;
    }
  } catch (err) {
    note.textContent = `not confirmed: ${err.message}`;
  } finally {
    confirming = false;
    button.disabled = confirmed === `${shownRobot} ${request}`;
  }
});

listRobots();
poll();
