// services.web: the live view's page logic, no libraries (it works offline).
//
// The server sends a `snapshot` event (everything known) when the stream opens, an `update`
// event per message after it and a `final` event when a run ended (docs/protocol.md#the-
// browser-view-http-routes-and-sse-events). The page keeps a small model per robot (latest
// event per topic, trajectory, metric history), marks what changed and redraws that once per
// animation frame. Maps are painted one canvas pixel per cell (row 0 on top, as
// services.watch draws them); the overlay is a second canvas on top, sized to the displayed
// map so lines, dots and the scale bar stay sharp. Test hooks (data-* attributes, listed in
// docs/protocol.md): every canvas carries data-run, data-robot and data-kind (observed,
// overlay, mean, variance, metrics); the robot's section and its observed canvas carry data-t,
// the latest step applied for that robot; the metrics canvas what the values line shows and
// how many points and segments each curve has; the overlay the scale bar's length and the
// frontier dots' radius; the run's section and #connection how the run ended.

"use strict";

const MAP_KIND_OF_TOPIC = {
  observed_map: "observed",
  "prediction/mean": "mean",
  "prediction/variance": "variance",
};
const OVERLAY_TOPICS = ["observed_map", "pose", "path", "goal", "frontiers", "teammates", "resize"];
const OBSERVED_GREY = [255, 128, 0]; // codes 0 free, 1 unknown, 2 occupied (mapex/grid.py)
const BAD_CODE_RGB = [255, 0, 255]; // an observed code outside 0..2 (never sent by a planner)
const MAGMA_STOPS = [ // matplotlib's magma at 0, 1/4, 1/2, 3/4, 1 (variance, as services.watch)
  [0, 0, 4], [81, 18, 124], [183, 55, 121], [252, 137, 97], [252, 253, 191],
];
const COLOURS = {
  pose: "#1f77b4", trajectory: "rgba(31, 119, 180, 0.55)", path: "#d62728", goal: "#ff7f0e",
  coverage: "#1f77b4", iou: "#ff7f0e", tu: "#2ca02c", outline: "#ffffff", ink: "#1d2330",
  grid: "#e3e7ee", unscored: "#7f7f7f",
};
const TEAMMATE_COLOURS = ["#9467bd", "#2ca02c", "#8c564b", "#e377c2", "#bcbd22"];
const FRONTIER_HUE_LOW_DEG = 240; // lowest score blue, highest red (hue 0)
const LINE_CSS_PX = { trajectory: 1.5, path: 2, goal: 7, pose: 5, teammate: 4 };
const FRONTIER_RADIUS = { minCssPx: 5, ofShownWidth: 0.007, outlineCssPx: 1.5 };
const SCALE_BAR = { // bottom left of the map, at most maxFraction of its width
  maxFraction: 0.25, marginCssPx: 10, paddingCssPx: 5, thickCssPx: 4, tickCssPx: 5,
  fontCssPx: 12, background: "rgba(255, 255, 255, 0.85)",
};
const NICE_MULTIPLES = [1, 2, 5]; // round lengths and axis steps: 1, 2, 5 times a power of 10
const METRICS_CANVAS_PX = [480, 400];
const METRICS_PAD_PX = { left: 38, right: 12, top: 24, bottom: 30 };
const METRIC_POINT_PX = 3; // the marks of a sparse curve (TU is computed only now and then)
const METRIC_SERIES = [ // [field, label, marked]
  ["coverage", "coverage", false], ["iou", "IoU", false], ["tu", "TU", true],
];
const MAX_TRAJECTORY_POINTS = 20000; // as WebConfig.max_trajectory_points
const MAX_METRIC_POINTS = 5000; // as WebConfig.max_metric_points
const DRAW_FALLBACK_MS = 250; // draw even when animation frames are paused (hidden tab)
const RECONNECT_MS = 2000; // after a stream the browser gave up on

const runs = new Map(); // run name -> run model
let drawScheduled = false;
let connection = "connecting"; // the event stream: connecting (first time), live or lost

// ------------------------------------------------------------------ DOM helpers

function el(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  node.append(...children);
  return node;
}

function tagged(tag, cls, run, robot, kind) {
  return el(tag, { class: cls, "data-run": run, "data-robot": robot, "data-kind": kind,
    id: `${kind}-${run}-${robot}` });
}

function insertSorted(parent, node, key, newestFirst) {
  const after = [...parent.children].find((child) => {
    const order = child.dataset.order.localeCompare(key, undefined, { numeric: true });
    return newestFirst ? order < 0 : order > 0;
  });
  node.dataset.order = key;
  parent.insertBefore(node, after || null);
}

// ------------------------------------------------------------------ model

function ensureRun(name) {
  let run = runs.get(name);
  if (run) return run;
  document.getElementById("waiting")?.remove();
  const state = el("span", { class: "state", hidden: "" });
  const title = el("h2", {}, `run ${name}`, state, el("small"));
  const robots = el("div", { class: "robots" });
  const section = el("section", { class: "run", "data-run": name, "data-state": "running" },
    title, robots);
  const list = document.getElementById("runs");
  list.insertBefore(section, list.firstChild); // the newest run on top
  run = { name, world: null, final: null, section, title, state, robotList: robots,
    robots: new Map() };
  runs.set(name, run);
  return run;
}

function ensureRobot(run, name) {
  let robot = run.robots.get(name);
  if (robot) return robot;
  const make = (kind, cls) => tagged("canvas", cls, run.name, name, kind);
  const canvases = {
    observed: make("observed", "map"), overlay: make("overlay", "overlay"),
    mean: make("mean", "map"), variance: make("variance", "map"),
    metrics: make("metrics", "metrics"),
  };
  [canvases.metrics.width, canvases.metrics.height] = METRICS_CANVAS_PX;
  const caption = () => el("figcaption");
  const text = {
    state: el("span", { class: "state" }, "waiting"), t: el("span", { class: "status-line" }),
    detail: el("p", { class: "detail" }), values: el("p", { class: "values" }),
    observed: caption(), mean: caption(), variance: caption(),
  };
  const panel = (kind, ...children) => el("figure", { class: `panel ${kind}` }, ...children);
  const section = el("section", { class: "robot", "data-run": run.name, "data-robot": name },
    el("h3", {}, `robot ${name}`, text.state, text.t), text.detail,
    el("div", { class: "row top" },
      panel("observed", el("div", { class: "map-stack" }, canvases.observed, canvases.overlay),
        text.observed),
      panel("metrics", canvases.metrics, text.values)),
    el("div", { class: "row bottom" },
      panel("mean", el("div", { class: "map-stack" }, canvases.mean), text.mean),
      panel("variance", el("div", { class: "map-stack" }, canvases.variance), text.variance)));
  insertSorted(run.robotList, section, name, false);
  robot = { run, name, t: null, latest: {}, trajectory: [], metrics: [], dirty: new Set(),
    section, canvases, text };
  run.robots.set(name, robot);
  if (run.world) sizeMapsToWorld(robot, run.world.shape);
  return robot;
}

function applyEvent(event) {
  const run = ensureRun(event.run);
  if (event.topic === "world_info") {
    run.world = event;
    for (const robot of run.robots.values()) sizeMapsToWorld(robot, event.shape);
    showWorld(run);
    return;
  }
  const robot = ensureRobot(run, event.robot);
  const known = robot.latest[event.topic];
  if (known && event.t < known.t) return; // an older message than the one shown
  robot.latest[event.topic] = event;
  robot.t = robot.t === null ? event.t : Math.max(robot.t, event.t);
  if (event.topic === "pose") {
    pushTrajectory(robot, event.pose);
    for (const other of run.robots.values()) if (other !== robot) other.dirty.add("teammates");
  }
  if (event.topic === "metrics") pushMetric(robot, event);
  robot.dirty.add(event.topic);
}

function applyFinal(event) {
  const run = ensureRun(event.run);
  run.final = event.final;
  showFinal(run);
}

function applySnapshot(snapshot) {
  const followed = snapshot.followed_run;
  document.getElementById("followed").textContent =
    followed ? `following run ${followed}` : "following every run";
  for (const [name, record] of Object.entries(snapshot.runs)) {
    const run = ensureRun(name);
    if (record.world) applyEvent(record.world);
    applyFinal({ run: name, final: record.final });
    for (const [robotName, known] of Object.entries(record.robots)) {
      const robot = ensureRobot(run, robotName);
      robot.latest = {};
      robot.trajectory = known.trajectory.slice();
      robot.metrics = known.metrics_history.slice();
      for (const event of Object.values(known.latest)) applyEvent(event);
      for (const topic of [...Object.keys(MAP_KIND_OF_TOPIC), ...OVERLAY_TOPICS, "metrics"]) {
        robot.dirty.add(topic);
      }
    }
  }
}

function pushTrajectory(robot, pose) {
  const last = robot.trajectory[robot.trajectory.length - 1];
  if (last && last[0] === pose[0] && last[1] === pose[1]) return;
  robot.trajectory.push(pose);
  if (robot.trajectory.length > MAX_TRAJECTORY_POINTS) robot.trajectory.shift();
}

function pushMetric(robot, event) {
  const last = robot.metrics[robot.metrics.length - 1];
  if (last && event.t <= last.t) return;
  robot.metrics.push(event);
  if (robot.metrics.length > MAX_METRIC_POINTS) robot.metrics.shift();
}

// ------------------------------------------------------------------ drawing

function scheduleDraw() {
  if (drawScheduled) return;
  drawScheduled = true;
  requestAnimationFrame(drawAll);
  setTimeout(drawAll, DRAW_FALLBACK_MS);
}

function drawAll() {
  if (!drawScheduled) return;
  drawScheduled = false;
  for (const run of runs.values()) for (const robot of run.robots.values()) drawRobot(robot);
}

function drawRobot(robot) {
  const dirty = robot.dirty;
  if (!dirty.size) return;
  for (const [topic, kind] of Object.entries(MAP_KIND_OF_TOPIC)) {
    if (dirty.has(topic) && robot.latest[topic]) paintMap(robot.canvases[kind], robot.latest[topic]);
  }
  if (OVERLAY_TOPICS.some((topic) => dirty.has(topic))) drawOverlay(robot);
  if (dirty.has("metrics")) drawMetrics(robot);
  showText(robot);
  dirty.clear();
}

function sizeCanvas(canvas, width, height) {
  if (canvas.width !== width || canvas.height !== height) {
    canvas.width = width;
    canvas.height = height;
  }
}

function sizeMapsToWorld(robot, shape) {
  for (const [topic, kind] of Object.entries(MAP_KIND_OF_TOPIC)) {
    if (!robot.latest[topic]) sizeCanvas(robot.canvases[kind], shape[1], shape[0]);
  }
  robot.dirty.add("resize");
}

function decodeBytes(base64) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return bytes;
}

function packRgba([r, g, b]) {
  return ((255 << 24) | (b << 16) | (g << 8) | r) >>> 0; // little-endian RGBA in a Uint32
}

function lerpColour(stops, fraction) {
  const position = Math.min(Math.max(fraction, 0), 1) * (stops.length - 1);
  const low = Math.min(Math.floor(position), stops.length - 2);
  const f = position - low;
  return stops[low].map((channel, i) => Math.round(channel + f * (stops[low + 1][i] - channel)));
}

function maxByte(values) {
  let top = 0;
  for (let i = 0; i < values.length; i++) if (values[i] > top) top = values[i];
  return top;
}

function colourTable(kind, top) {
  const table = new Uint32Array(256);
  if (kind === "observed") {
    table.fill(packRgba(BAD_CODE_RGB));
    OBSERVED_GREY.forEach((grey, code) => { table[code] = packRgba([grey, grey, grey]); });
  } else if (kind === "variance") {
    for (let q = 0; q < 256; q++) table[q] = packRgba(lerpColour(MAGMA_STOPS, q / Math.max(1, top)));
  } else { // an occupancy probability: free white, walls black
    for (let q = 0; q < 256; q++) table[q] = packRgba([255 - q, 255 - q, 255 - q]);
  }
  return table;
}

function paintMap(canvas, event) {
  sizeCanvas(canvas, event.width, event.height);
  const values = decodeBytes(event.data);
  const context = canvas.getContext("2d");
  const image = context.createImageData(event.width, event.height);
  const pixels = new Uint32Array(image.data.buffer);
  const top = event.kind === "variance" ? maxByte(values) : 0; // variance: scaled to its max
  const table = colourTable(event.kind, top);
  for (let i = 0; i < values.length; i++) pixels[i] = table[values[i]];
  context.putImageData(image, 0, 0);
  canvas.dataset.mapT = event.t;
  canvas.dataset.max = event.kind === "variance" ? String(top / 255) : "";
}

function mapShape(robot) {
  const observed = robot.latest.observed_map;
  if (observed) return [observed.height, observed.width];
  return robot.run.world ? robot.run.world.shape : null;
}

function drawOverlay(robot) {
  const shape = mapShape(robot);
  if (!shape) return;
  const [rows, cols] = shape;
  const canvas = robot.canvases.overlay;
  const ratio = window.devicePixelRatio || 1;
  const shownPx = canvas.parentElement.clientWidth || cols;
  const width = Math.max(cols, Math.round(shownPx * ratio));
  sizeCanvas(canvas, width, Math.round((width * rows) / cols));
  const context = canvas.getContext("2d");
  context.setTransform(1, 0, 0, 1, 0, 0);
  context.clearRect(0, 0, canvas.width, canvas.height);
  context.setTransform(canvas.width / cols, 0, 0, canvas.height / rows, 0, 0);
  const cellsPerPx = cols / shownPx; // lengths below are CSS pixels, drawn in cells
  const size = (name) => LINE_CSS_PX[name] * cellsPerPx;
  drawLine(context, robot.trajectory, COLOURS.trajectory, size("trajectory"));
  if (robot.latest.path) drawLine(context, robot.latest.path.cells, COLOURS.path, size("path"));
  const frontierCssPx = Math.max(FRONTIER_RADIUS.minCssPx, FRONTIER_RADIUS.ofShownWidth * shownPx);
  canvas.dataset.frontierRadiusCssPx = frontierCssPx.toFixed(2);
  canvas.dataset.frontiers = robot.latest.frontiers ? robot.latest.frontiers.cells.length : 0;
  if (robot.latest.frontiers) {
    drawFrontiers(context, robot.latest.frontiers, frontierCssPx * cellsPerPx,
      FRONTIER_RADIUS.outlineCssPx * cellsPerPx);
  }
  const goal = robot.latest.goal?.goal;
  if (goal) drawDiamond(context, goal, size("goal"), COLOURS.goal, cellsPerPx);
  let index = 0;
  for (const other of robot.run.robots.values()) {
    if (other === robot) continue;
    const colour = TEAMMATE_COLOURS[index++ % TEAMMATE_COLOURS.length];
    const pose = other.latest.pose?.pose;
    if (pose) drawDot(context, pose, size("teammate"), colour, cellsPerPx);
  }
  const pose = robot.latest.pose?.pose;
  if (pose) drawDot(context, pose, size("pose"), COLOURS.pose, cellsPerPx);
  drawScaleBar(canvas, context, cols, shownPx, robot.run.world?.resolution_m);
}

function drawScaleBar(canvas, context, cols, shownPx, resolutionM) {
  // a round length (1, 2, 5 × 10^k m) of at most SCALE_BAR.maxFraction of the map's width
  for (const name of ["scaleM", "scaleCells", "scaleCssPx"]) delete canvas.dataset[name];
  if (!(resolutionM > 0)) return;
  const lengthM = niceFloor(SCALE_BAR.maxFraction * cols * resolutionM);
  const lengthCells = lengthM / resolutionM;
  const lengthCssPx = (lengthCells * shownPx) / cols;
  const label = `${lengthM} m`;
  const { marginCssPx: margin, paddingCssPx: pad, thickCssPx: thick, tickCssPx: tick } = SCALE_BAR;
  const cssPerCanvasPx = shownPx / canvas.width;
  context.setTransform(1 / cssPerCanvasPx, 0, 0, 1 / cssPerCanvasPx, 0, 0); // CSS pixels
  context.font = `${SCALE_BAR.fontCssPx}px system-ui, sans-serif`;
  const boxW = Math.max(lengthCssPx, context.measureText(label).width) + 2 * pad;
  const boxH = SCALE_BAR.fontCssPx + thick + tick + 3 * pad;
  const left = margin;
  const top = canvas.height * cssPerCanvasPx - margin - boxH;
  context.fillStyle = SCALE_BAR.background;
  context.fillRect(left, top, boxW, boxH);
  const barY = top + boxH - pad - thick;
  context.fillStyle = COLOURS.ink;
  context.fillRect(left + pad, barY, lengthCssPx, thick);
  context.fillRect(left + pad, barY - tick, 1, tick + thick);
  context.fillRect(left + pad + lengthCssPx - 1, barY - tick, 1, tick + thick);
  context.textAlign = "left";
  context.textBaseline = "top";
  context.fillText(label, left + pad, top + pad);
  canvas.dataset.scaleM = String(lengthM);
  canvas.dataset.scaleCells = String(lengthCells);
  canvas.dataset.scaleCssPx = lengthCssPx.toFixed(1);
}

function centre([row, col]) {
  return [col + 0.5, row + 0.5];
}

function drawLine(context, cells, colour, width) {
  if (cells.length < 2) return;
  context.beginPath();
  cells.forEach((cell, i) => (i ? context.lineTo(...centre(cell)) : context.moveTo(...centre(cell))));
  context.strokeStyle = colour;
  context.lineWidth = width;
  context.lineJoin = "round";
  context.stroke();
}

function drawFrontiers(context, frontiers, radius, outline) {
  const finite = frontiers.scores.filter((s) => s !== null);
  const low = Math.min(...finite);
  const span = Math.max(...finite) - low;
  frontiers.cells.forEach((cell, i) => {
    const score = frontiers.scores[i];
    const fraction = span > 0 ? (score - low) / span : 1;
    const colour = score === null
      ? COLOURS.unscored : `hsl(${FRONTIER_HUE_LOW_DEG * (1 - fraction)}, 90%, 45%)`;
    drawDot(context, cell, radius, colour, outline, COLOURS.ink);
  });
}

function drawDot(context, cell, radius, colour, outline, outlineColour = COLOURS.outline) {
  context.beginPath();
  context.arc(...centre(cell), radius, 0, 2 * Math.PI);
  context.fillStyle = colour;
  context.fill();
  context.lineWidth = outline;
  context.strokeStyle = outlineColour;
  context.stroke();
}

function drawDiamond(context, cell, radius, colour, outline) {
  const [x, y] = centre(cell);
  context.beginPath();
  context.moveTo(x, y - radius);
  context.lineTo(x + radius, y);
  context.lineTo(x, y + radius);
  context.lineTo(x - radius, y);
  context.closePath();
  context.fillStyle = colour;
  context.fill();
  context.lineWidth = outline;
  context.strokeStyle = COLOURS.ink;
  context.stroke();
}

function niceStep(rough) { // the smallest round number (1, 2, 5 × 10^k) of at least `rough`
  const power = 10 ** Math.floor(Math.log10(rough));
  return [...NICE_MULTIPLES, 10].map((m) => m * power).find((step) => step >= rough);
}

function niceFloor(limit) { // the largest round number (1, 2, 5 × 10^k) of at most `limit`
  const power = 10 ** Math.floor(Math.log10(limit));
  const found = [...NICE_MULTIPLES].reverse().map((m) => m * power).find((v) => v <= limit) ?? power;
  return Number(found.toPrecision(1)); // 0.2, not 0.20000000000000004
}

function drawMetrics(robot) {
  const canvas = robot.canvases.metrics;
  const context = canvas.getContext("2d");
  const pad = METRICS_PAD_PX;
  const plotW = canvas.width - pad.left - pad.right;
  const plotH = canvas.height - pad.top - pad.bottom;
  const history = robot.metrics;
  const tMax = Math.max(1, history.length ? history[history.length - 1].t : 1);
  const step = niceStep(tMax / 5);
  const xMax = Math.ceil(tMax / step) * step;
  const x = (t) => pad.left + (t / xMax) * plotW;
  const y = (v) => pad.top + (1 - v) * plotH;
  context.fillStyle = "#ffffff";
  context.fillRect(0, 0, canvas.width, canvas.height);
  context.font = "11px system-ui, sans-serif";
  context.lineWidth = 1;
  context.fillStyle = COLOURS.ink;
  context.strokeStyle = COLOURS.grid;
  context.textAlign = "right";
  for (let v = 0; v <= 1.0001; v += 0.25) {
    context.beginPath();
    context.moveTo(pad.left, y(v));
    context.lineTo(pad.left + plotW, y(v));
    context.stroke();
    context.fillText(v.toFixed(2), pad.left - 4, y(v) + 4);
  }
  context.textAlign = "center";
  for (let t = 0; t <= xMax; t += step) context.fillText(String(t), x(t), pad.top + plotH + 14);
  context.fillText("t (steps)", pad.left + plotW / 2, canvas.height - 3);
  context.textAlign = "left";
  let legendX = pad.left;
  for (const [field, label, marked] of METRIC_SERIES) {
    // a line through the samples where the metric is known (null gaps skipped), marks on them
    const points = history.filter((sample) => sample[field] !== null && sample[field] !== undefined);
    context.strokeStyle = context.fillStyle = COLOURS[field];
    context.lineWidth = 2;
    context.beginPath();
    points.forEach((p, i) => (i ? context.lineTo(x(p.t), y(p[field])) : context.moveTo(x(p.t), y(p[field]))));
    context.stroke();
    if (marked) {
      for (const p of points) {
        context.beginPath();
        context.arc(x(p.t), y(p[field]), METRIC_POINT_PX, 0, 2 * Math.PI);
        context.fill();
      }
    }
    canvas.dataset[`${field}Points`] = points.length;
    canvas.dataset[`${field}Segments`] = Math.max(0, points.length - 1);
    context.fillRect(legendX, 8, 14, 3);
    context.fillText(label, legendX + 18, 14);
    legendX += 30 + context.measureText(label).width;
  }
}

// ------------------------------------------------------------------ text

function showWorld(run) {
  const world = run.world;
  const [rows, cols] = world.shape;
  run.title.querySelector("small").textContent =
    `${world.name} · ${rows} × ${cols} cells of ${world.resolution_m} m`;
}

function showText(robot) {
  const { latest, text } = robot;
  const status = latest.status;
  text.state.textContent = status ? status.state : "waiting";
  text.state.dataset.state = status ? status.state : "waiting";
  text.t.textContent = robot.t === null ? "" : `t = ${robot.t}`;
  text.detail.textContent = status?.detail || "";
  const metrics = latest.metrics; // the latest metrics message, whatever the curve holds
  const tu = robot.metrics.findLast((sample) => sample.tu !== null); // TU is sampled less often
  text.values.replaceChildren(...(metrics ? [
    el("span", { class: "coverage" }, `coverage ${(100 * metrics.coverage).toFixed(1)} %`),
    el("span", { class: "iou" }, `IoU ${metrics.iou.toFixed(3)}`),
    el("span", {}, `(t = ${metrics.t}${metrics.degraded ? ", degraded" : ""})`),
    el("span", { class: "tu" }, tu ? `TU ${tu.tu.toFixed(3)} (t = ${tu.t})` : "TU –"),
  ] : []));
  const shown = robot.canvases.metrics.dataset;
  for (const [name, value] of [["coverage", metrics?.coverage], ["coverageT", metrics?.t],
    ["iou", metrics?.iou], ["tu", tu?.tu], ["tuT", tu?.t]]) {
    if (value === undefined) delete shown[name];
    else shown[name] = String(value);
  }
  const caption = (topic, name, extra = "") =>
    latest[topic] ? `${name} · t = ${latest[topic].t}${extra}` : `${name}: waiting`;
  text.observed.textContent = caption("observed_map", "observed map");
  text.mean.textContent = caption("prediction/mean", "prediction mean");
  const top = robot.canvases.variance.dataset.max;
  text.variance.textContent = caption("prediction/variance", "variance",
    top ? ` · max ${Number(top).toFixed(3)}` : "");
  if (robot.t !== null) {
    robot.section.dataset.t = robot.t;
    robot.canvases.observed.dataset.t = robot.t;
  }
}

function showFinal(run) {
  const final = run.final;
  run.section.dataset.state = final ? final.state : "running";
  if (final) run.section.dataset.finalT = final.t;
  else delete run.section.dataset.finalT;
  run.state.hidden = !final;
  run.state.dataset.state = final ? final.state : "";
  run.state.textContent = final ? `${final.state} · t = ${final.t}` : "";
  showConnection();
}

// ------------------------------------------------------------------ the stream

function runsEnded() {
  // "finished" or "failed" once every run shown has ended (any failed: failed); else null
  const all = [...runs.values()];
  if (!all.length || all.some((run) => !run.final)) return null;
  return all.some((run) => run.final.state === "failed") ? "failed" : "finished";
}

function showConnection() {
  // live, or how the runs ended while the server is up ("ended") or after it went
  // ("closed"); reconnecting only while a run may still go on
  const ended = runsEnded();
  let shown = ["connecting", "connecting…"];
  if (connection === "live") shown = ended ? ["ended", ended] : ["live", "live"];
  else if (ended) shown = ["closed", `${ended} (server closed)`];
  else if (connection === "lost") shown = ["reconnecting", "reconnecting…"];
  const badge = document.getElementById("connection");
  [badge.dataset.state, badge.textContent] = shown;
}

function handle(message, apply) {
  try {
    apply(JSON.parse(message.data));
  } catch (error) {
    console.warn("services.web: an event the page could not apply", error);
  }
  scheduleDraw();
}

function connect() {
  const source = new EventSource("events");
  source.addEventListener("open", () => { connection = "live"; showConnection(); });
  source.addEventListener("snapshot", (message) => handle(message, applySnapshot));
  source.addEventListener("update", (message) => handle(message, applyEvent));
  source.addEventListener("final", (message) => handle(message, applyFinal));
  source.addEventListener("error", () => { // the browser retries by itself unless CLOSED
    connection = "lost";
    showConnection();
    if (source.readyState === EventSource.CLOSED) setTimeout(connect, RECONNECT_MS);
  });
}

window.addEventListener("resize", () => {
  for (const run of runs.values()) for (const robot of run.robots.values()) robot.dirty.add("resize");
  scheduleDraw();
});
connect();
