// PolyDDA result viewer: blocks in 3-D from GET /jobs/{id}/results/frames (service/frames.py).
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";
import { attachSection } from "polydda/section.js";

const cfg = JSON.parse(document.getElementById("viewer-config").textContent);
const $ = (id) => document.getElementById(id);
const state = {
  blockCount: 0, frame: 0, frameCount: 0, picked: null, ready: false, loadMs: null,
  status: "loading", error: null,
};
window.polydda = state;

const TYPED = { float32: Float32Array, float64: Float64Array, uint32: Uint32Array,
                int32: Int32Array, int8: Int8Array, uint8: Uint8Array };

function decode(buf) {
  const size = new DataView(buf).getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, size)));
  const arrays = {};
  for (const [name, spec] of Object.entries(head.arrays)) {
    const n = spec.shape.reduce((a, b) => a * b, 1);
    arrays[name] = new TYPED[spec.dtype](buf, 4 + size + spec.offset, n);
  }
  return { head, arrays };
}

async function getFrames(params, early = null) {
  const url = `${cfg.frames}?${new URLSearchParams(params)}`;
  const r = await (early || fetch(url, { credentials: "same-origin" }));
  if (!r.ok) {
    let detail = r.statusText;
    try { detail = (await r.json()).detail; } catch (e) { /* not a problem document */ }
    const err = new Error(detail);
    err.status = r.status;
    throw err;
  }
  return decode(await r.arrayBuffer());
}

// ------------------------------------------------------------------ growing frame store
class Series {
  constructor(width) { this.width = width; this.data = new Float32Array(0); this.length = 0; }
  append(values) {
    const need = this.length * this.width + values.length;
    if (need > this.data.length) {
      const grown = new Float32Array(Math.max(need, 2 * this.data.length));
      grown.set(this.data.subarray(0, this.length * this.width));
      this.data = grown;
    }
    this.data.set(values, this.length * this.width);
    this.length += values.length / this.width;
  }
  row(k) { return this.data.subarray(k * this.width, (k + 1) * this.width); }
}

const VIRIDIS = [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
  [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37]];
function viridis(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const f = x - i;
  return VIRIDIS[i].map((c, j) => (c + f * (VIRIDIS[i + 1][j] - c)) / 255);
}

// ------------------------------------------------------------------ scene
let g = null;  // geometry, motion and three.js objects
const renderer = new THREE.WebGLRenderer({ canvas: $("view"), antialias: true,
                                           preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf4f5f7);
const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1e6);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(0.4, -0.6, 1.0);
scene.add(sun);
let dirty = true;
controls.addEventListener("change", () => { dirty = true; updateOverlays(); });

function resize() {
  const el = renderer.domElement;
  const w = el.clientWidth, h = el.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(1, h);
  camera.updateProjectionMatrix();
  dirty = true;
  updateOverlays();
}
window.addEventListener("resize", resize);
// the stage also changes size when the controls bar below it wraps to another line
if (window.ResizeObserver) new ResizeObserver(() => resize()).observe(renderer.domElement);

// ------------------------------------------------------------------ triad, north, scale bar
const AXES = [["E", [1, 0, 0], "#d62728"], ["N", [0, 1, 0], "#2ca02c"], ["Up", [0, 0, 1], "#1f77b4"]];
const SVG_NS = "http://www.w3.org/2000/svg";

function screenDirection(v) {
  // a world direction as seen on the page: (right, down) components of its projection on
  // the view plane (length 1 when it lies in the view plane, 0 when along the view)
  camera.updateMatrixWorld();
  const d = new THREE.Vector3(...v).transformDirection(camera.matrixWorldInverse);
  return [d.x, -d.y, d.z];
}

function updateTriad() {
  const svg = $("triad");
  if (!svg) return;
  const c = 55, L = 40, dirs = {};
  const items = AXES.map(([name, v, colour]) => {
    const [x, y, z] = screenDirection(v);
    dirs[name] = [x, y];
    return { name, colour, x, y, z };
  }).sort((p, q) => p.z - q.z);  // the axis pointing away from the viewer first
  svg.replaceChildren();
  const el = (tag, attrs, text) => {
    const e = document.createElementNS(SVG_NS, tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text) e.textContent = text;
    svg.appendChild(e);
    return e;
  };
  el("circle", { cx: c, cy: c, r: 52, fill: "rgba(255,255,255,0.85)", stroke: "#ccd" });
  for (const a of items) {
    const tx = c + L * a.x, ty = c + L * a.y, north = a.name === "N";
    el("line", { x1: c, y1: c, x2: tx, y2: ty, stroke: a.colour, "stroke-width": north ? 3 : 2,
                 id: `triad-${a.name}` });
    const len = Math.hypot(a.x, a.y);
    if (len > 0.05) {  // an arrow head; the north arrow's filled and larger
      const ux = a.x / len, uy = a.y / len, h = north ? 11 : 7, w = north ? 6 : 4;
      el("polygon", { fill: a.colour, points: [[tx, ty], [tx - h * ux + w * uy, ty - h * uy - w * ux],
                                                 [tx - h * ux - w * uy, ty - h * uy + w * ux]]
                                                 .map((p) => p.join(",")).join(" ") });
    }
    const lx = c + (L + 9) * (len > 0.05 ? a.x / Math.max(len, 1e-9) * Math.max(len, 0.35) : 0);
    const ly = c + (L + 9) * (len > 0.05 ? a.y / Math.max(len, 1e-9) * Math.max(len, 0.35) : 0);
    el("text", { x: lx, y: ly + 4, "text-anchor": "middle", fill: a.colour,
                 "font-weight": north ? "bold" : "normal", "font-size": north ? 13 : 11 }, a.name);
  }
  state.triad = dirs;
}

function niceLength(x) {
  // the largest 1, 2 or 5 × 10^k not above x
  const k = Math.floor(Math.log10(x)), base = 10 ** k;
  for (const m of [5, 2, 1]) if (m * base <= x * (1 + 1e-9)) return m * base;
  return base;
}

function updateScaleBar() {
  const box = $("scalebar");
  if (!box || !g) return;
  // metres per CSS pixel at the centre of rotation (perspective: it depends on the depth)
  const el = renderer.domElement, h = Math.max(1, el.clientHeight);
  const dist = camera.position.distanceTo(controls.target);
  const perPixel = 2 * dist * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) / h;
  const metres = niceLength(120 * perPixel), pixels = metres / perPixel;
  box.querySelector(".bar").style.width = `${pixels.toFixed(1)}px`;
  box.querySelector(".label").textContent = `${+metres.toPrecision(3)} m`;
  state.scaleBar = { metres, pixels };
}

function updateOverlays() { updateTriad(); updateScaleBar(); }

function build(head, a) {
  const n = head.n_blocks, V = a.vertices.length / 3, T = a.triangles.length / 3;
  const vblock = new Uint32Array(V);
  for (let b = 0; b < n; b++) vblock.fill(b, a.vertex_offsets[b], a.vertex_offsets[b + 1]);
  const rel = new Float32Array(V * 3);
  for (let v = 0; v < V; v++) {
    const b = vblock[v];
    for (let j = 0; j < 3; j++) rel[3 * v + j] = a.vertices[3 * v + j] - a.centroid0[3 * b + j];
  }
  const pos = new THREE.BufferAttribute(new Float32Array(V * 3), 3);
  const triPos = new THREE.BufferAttribute(new Float32Array(T * 9), 3);
  const triCol = new THREE.BufferAttribute(new Float32Array(T * 9), 3);
  const mg = new THREE.BufferGeometry();
  mg.setAttribute("position", triPos);
  mg.setAttribute("color", triCol);
  const mesh = new THREE.Mesh(mg, new THREE.MeshLambertMaterial({
    vertexColors: true, side: THREE.DoubleSide, polygonOffset: true,
    polygonOffsetFactor: 1, polygonOffsetUnits: 1 }));
  const eg = new THREE.BufferGeometry();
  eg.setAttribute("position", pos);
  eg.setIndex(new THREE.BufferAttribute(a.edges, 1));
  const edges = new THREE.LineSegments(eg, new THREE.LineBasicMaterial({
    color: 0x222222, transparent: true, opacity: 0.45 }));
  scene.add(mesh, edges);
  const joints = new THREE.Group();
  for (const j of head.joints || []) {
    const p = j.polygon;
    const verts = [];
    for (let k = 1; k + 1 < p.length; k++) verts.push(...p[0], ...p[k], ...p[k + 1]);
    const jg = new THREE.BufferGeometry();
    jg.setAttribute("position", new THREE.Float32BufferAttribute(verts, 3));
    joints.add(new THREE.Mesh(jg, new THREE.MeshBasicMaterial({
      color: 0x3b82f6, transparent: true, opacity: 0.18, side: THREE.DoubleSide,
      depthWrite: false })));
  }
  joints.visible = false;
  scene.add(joints);
  // contacts drawn through the blocks (they lie on faces, the force arrows inside blocks)
  const contacts = new THREE.Group();
  contacts.add(new THREE.Points(new THREE.BufferGeometry(), new THREE.PointsMaterial({
    size: 6, sizeAttenuation: false, vertexColors: true, depthTest: false })));
  contacts.add(new THREE.LineSegments(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({
    color: 0xc2185b, depthTest: false })));
  contacts.renderOrder = 10;
  contacts.children.forEach((c) => { c.renderOrder = 10; });
  contacts.visible = false;
  scene.add(contacts);
  // camera: the bounding sphere (radius r) fills the view, seen from the south-west, above
  const ext = head.extent, r = Math.max(1e-6, Math.hypot(...ext) / 2);
  const dist = 1.05 * r / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2));
  camera.near = r / 1000; camera.far = r * 100;
  camera.position.set(-0.45, -0.8, 0.45).normalize().multiplyScalar(dist);
  controls.target.set(0, 0, 0);
  controls.update();
  // the section plane and "hide fixed blocks" (service/static/section.js)
  state.section = attachSection({
    renderer, scene, camera, controls, canvas: renderer.domElement,
    box: $("section-controls"), size: 2 * r, materials: () => [mesh.material, edges.material],
    changed: () => { dirty = true; },
    hideFixed: (on) => { state.hideFixed = on; draw(state.frame); } });
  g = { head, a, n, V, T, vblock, rel, pos, triPos, triCol, mesh, edges, joints, contacts,
        disp: new Series(3 * n), rot: new Series(4 * n), vel: new Series(3 * n),
        steps: [], times: [], index: [], scale: { displacement: 0, velocity: 0 },
        nSteps: head.n_steps, next: 0, stride: 1, contactCache: new Map() };
}

function appendMotion(head, a) {
  g.disp.append(a.displacement); g.rot.append(a.rotation); g.vel.append(a.velocity);
  g.steps.push(...head.steps); g.times.push(...head.times);
  for (let i = 0; i < head.count; i++) g.index.push(head.start + i * head.stride);
  g.nSteps = head.n_steps;
  if (head.next_start != null) g.next = head.next_start;
  else if (head.count) g.next = g.index[g.index.length - 1] + g.stride;
  for (const [key, arr, w] of [["displacement", a.displacement, 3], ["velocity", a.velocity, 3]]) {
    let m = g.scale[key];
    for (let i = 0; i < arr.length; i += w) m = Math.max(m, Math.hypot(arr[i], arr[i + 1], arr[i + 2]));
    g.scale[key] = m;
  }
  state.frameCount = g.disp.length;
  const slider = $("slider");
  const atEnd = +slider.value >= +slider.max;
  slider.max = Math.max(0, state.frameCount - 1);
  if (atEnd && $("follow").checked && state.ready) setFrame(state.frameCount - 1);
  updateLabel();
}

function blockColor(b, k, mode) {
  if (state.picked && state.picked.index === b) return [0.95, 0.25, 0.2];
  if (g.head.fixed[b]) return [0.62, 0.62, 0.62];
  if (mode === "block") {
    const h = (b * 0.618033988749895) % 1;
    return new THREE.Color().setHSL(h, 0.55, 0.6).toArray();
  }
  const src = mode === "velocity" ? g.vel : g.disp;
  const row = src.row(k);
  const m = Math.hypot(row[3 * b], row[3 * b + 1], row[3 * b + 2]);
  return viridis(g.scale[mode] > 0 ? m / g.scale[mode] : 0);
}

function quatRotate(q, x, y, z, out) {
  const [qx, qy, qz, qw] = q;
  const tx = 2 * (qy * z - qz * y), ty = 2 * (qz * x - qx * z), tz = 2 * (qx * y - qy * x);
  out[0] = x + qw * tx + (qy * tz - qz * ty);
  out[1] = y + qw * ty + (qz * tx - qx * tz);
  out[2] = z + qw * tz + (qx * ty - qy * tx);
}

// a staged run: the blocks its stages removed by time t (drawn collapsed to a point)
function removedAt(t) {
  const gone = new Set();
  for (const st of g.head.stages || []) {
    if (st.start_time < t) for (const b of st.removed) gone.add(b);
  }
  return gone;
}

// the stage the frame at time t belongs to ("" without stages)
function stageAt(t) {
  let name = "";
  for (const st of g.head.stages || []) if (st.start_time < t || !name) name = st.name;
  return name;
}

function draw(k) {
  if (!g || !state.frameCount) return;
  const { a, n, V, T, vblock, rel } = g;
  const d = g.disp.row(k), rq = g.rot.row(k), P = g.pos.array, out = [0, 0, 0];
  const gone = removedAt(g.times[k]);
  if (state.hideFixed) for (let b = 0; b < n; b++) if (g.head.fixed[b]) gone.add(b);
  for (let v = 0; v < V; v++) {
    const b = vblock[v];
    if (gone.has(b)) {
      for (let j = 0; j < 3; j++) P[3 * v + j] = a.centroid0[3 * b + j] + d[3 * b + j];
      continue;
    }
    quatRotate([rq[4 * b], rq[4 * b + 1], rq[4 * b + 2], rq[4 * b + 3]],
               rel[3 * v], rel[3 * v + 1], rel[3 * v + 2], out);
    for (let j = 0; j < 3; j++) P[3 * v + j] = a.centroid0[3 * b + j] + d[3 * b + j] + out[j];
  }
  const mode = $("colour").value;
  const colours = new Array(n);
  for (let b = 0; b < n; b++) colours[b] = blockColor(b, k, mode);
  const TP = g.triPos.array, TC = g.triCol.array, tri = a.triangles;
  for (let t = 0; t < T; t++) {
    const c = colours[a.triangle_block[t]];
    for (let i = 0; i < 3; i++) {
      const v = tri[3 * t + i], o = 9 * t + 3 * i;
      TP[o] = P[3 * v]; TP[o + 1] = P[3 * v + 1]; TP[o + 2] = P[3 * v + 2];
      TC[o] = c[0]; TC[o + 1] = c[1]; TC[o + 2] = c[2];
    }
  }
  g.pos.needsUpdate = true; g.triPos.needsUpdate = true; g.triCol.needsUpdate = true;
  g.mesh.geometry.computeVertexNormals();
  g.mesh.geometry.computeBoundingSphere();
  g.edges.geometry.computeBoundingSphere();
  drawContacts(k);
  updateColourBar(mode);
  dirty = true;
}

const MODE_NAMES = ["open", "locked", "sliding"];
const MODE_RGB = [[0.55, 0.55, 0.55], [0.15, 0.4, 0.95], [0.95, 0.45, 0.1]];

function drawContacts(k) {
  const on = $("contacts").checked;
  const c = on ? g.contactCache.get(g.index[k]) : null;
  g.contacts.visible = !!c;
  if (!c) {
    state.contactCount = null;
    $("contact-count").textContent = on ? "contacts: loading…" : "";
    if (on) loadContacts(k);
    return;
  }
  const n = c.mode.length, col = new Float32Array(3 * n), counts = [0, 0, 0];
  for (let i = 0; i < n; i++) {
    col.set(MODE_RGB[c.mode[i]] || [0, 0, 0], 3 * i);
    if (counts[c.mode[i]] !== undefined) counts[c.mode[i]]++;
  }
  const [points, arrows] = g.contacts.children;
  const geo = new THREE.BufferGeometry();
  geo.setAttribute("position", new THREE.BufferAttribute(c.point, 3));
  geo.setAttribute("color", new THREE.BufferAttribute(col, 3));
  points.geometry.dispose();
  points.geometry = geo;
  // normal force on block i as an arrow from the contact point along the normal (j into i);
  // the largest force of the step is 15 % of the model's size long
  let fmax = 0;
  for (let i = 0; i < n; i++) fmax = Math.max(fmax, c.force[i]);
  const L = 0.15 * Math.hypot(...g.head.extent), seg = [];
  for (let i = 0; fmax > 0 && i < n; i++) {
    if (!(c.force[i] > 0)) continue;
    const p = c.point.subarray(3 * i, 3 * i + 3), nv = c.normal.subarray(3 * i, 3 * i + 3);
    const len = L * c.force[i] / fmax, tip = [0, 1, 2].map((j) => p[j] + len * nv[j]);
    // head: two strokes back from the tip, in a plane through the normal
    const u = new THREE.Vector3(...nv).cross(Math.abs(nv[2]) < 0.9 ? new THREE.Vector3(0, 0, 1)
                                                               : new THREE.Vector3(1, 0, 0)).normalize();
    seg.push(...p, ...tip);
    for (const sgn of [1, -1]) {
      seg.push(...tip, ...[0, 1, 2].map((j) => tip[j] - 0.25 * len * nv[j]
                                                + sgn * 0.12 * len * u.getComponent(j)));
    }
  }
  arrows.geometry.dispose();
  arrows.geometry = new THREE.BufferGeometry();
  arrows.geometry.setAttribute("position", new THREE.Float32BufferAttribute(seg, 3));
  arrows.visible = c.forces;
  state.contactCount = n;
  state.contactModes = Object.fromEntries(MODE_NAMES.map((m, i) => [m, counts[i]]));
  state.maxNormalForce = fmax;
  $("contact-count").textContent = `${n} contacts (${counts[0]} open, ${counts[1]} locked, `
    + `${counts[2]} sliding)` + (c.forces
      ? (fmax > 0 ? ` · arrows: normal force, longest ${fmt(fmax)} N` : " · no normal force")
      : " · normal forces not recorded");
}

async function loadContacts(k) {
  // the contacts of one recorded step, fetched when it is shown (then kept)
  const i = g.index[k];
  if (g.contactCache.has(i)) return;
  g.contactCache.set(i, null);
  let head, arrays;
  try {
    ({ head, arrays } = await getFrames({ start: i, stop: i + 1, geometry: false, contacts: true }));
  } catch (err) {
    g.contactCache.delete(i);  // asked again when the step is shown again
    $("contact-count").textContent = `contacts: ${err.message || err}`;
    return;
  }
  g.contactCache.set(i, { point: arrays.contact_point, mode: arrays.contact_mode,
                          normal: arrays.contact_normal, force: arrays.contact_force,
                          forces: !!head.contact_forces });
  state.contactsShown = (state.contactsShown || 0) + 1;
  if (state.frame === k) { drawContacts(k); dirty = true; }
}

function updateColourBar(mode) {
  const bar = $("colourbar");
  if (mode === "block") { bar.hidden = true; return; }
  bar.hidden = false;
  const unit = mode === "velocity" ? "m/s" : "m";
  $("cb-min").textContent = `0 ${unit}`;
  $("cb-max").textContent = `${fmt(g.scale[mode])} ${unit}`;
  $("cb-title").textContent = mode === "velocity" ? "|velocity|" : "|displacement|";
}

function fmt(x) { return Math.abs(x) >= 1e4 || (Math.abs(x) < 1e-3 && x !== 0) ? x.toExponential(3) : x.toPrecision(4); }

function updateLabel() {
  const k = state.frame;
  const t = g && g.times.length ? g.times[k] : 0;
  const step = g && g.steps.length ? g.steps[k] : 0;
  const stage = g && g.head.stages && g.head.stages.length ? ` · stage ${stageAt(t)}` : "";
  $("frame-label").textContent = state.frameCount
    ? `frame ${k + 1}/${state.frameCount} · step ${step} · t = ${fmt(t)} s${stage}`
    : "no steps yet";
  $("status").textContent = state.status;
}

function setFrame(k) {
  state.frame = Math.max(0, Math.min(k, state.frameCount - 1));
  $("slider").value = state.frame;
  draw(state.frame);
  updateLabel();
  drawHistory();
}

// ------------------------------------------------------------------ picking and history
function pick(index) {
  state.picked = index == null ? null : { index, name: g.head.block_names[index] || `block ${index}` };
  const info = $("info");
  if (!state.picked) { info.hidden = true; draw(state.frame); return; }
  info.hidden = false;
  const last = g.disp.row(state.frameCount - 1);
  const [dx, dy, dz] = [last[3 * index], last[3 * index + 1], last[3 * index + 2]];
  const mag = Math.hypot(dx, dy, dz);
  const trend = (Math.atan2(dx, dy) * 180 / Math.PI + 360) % 360;
  const plunge = Math.atan2(-dz, Math.hypot(dx, dy)) * 180 / Math.PI;
  Object.assign(state.picked, { displacement: [dx, dy, dz], magnitude: mag, trend, plunge });
  $("pick-name").textContent = state.picked.name;
  $("pick-kind").textContent = g.head.fixed[index] ? "fixed" : "free";
  $("pick-disp").textContent = mag > 0
    ? `${fmt(mag)} m, trend ${trend.toFixed(1)}°, plunge ${plunge.toFixed(1)}°` : "0 m";
  $("pick-comp").textContent = `(${fmt(dx)}, ${fmt(dy)}, ${fmt(dz)}) m`;
  draw(state.frame);
  drawHistory();
}

function drawHistory() {
  const cv = $("history");
  if (!state.picked || !cv) return;
  const b = state.picked.index, K = state.frameCount, ctx = cv.getContext("2d");
  const W = cv.width, H = cv.height, pad = 28;
  ctx.clearRect(0, 0, W, H);
  const series = [[], [], [], []];
  for (let k = 0; k < K; k++) {
    const r = g.disp.row(k), x = r[3 * b], y = r[3 * b + 1], z = r[3 * b + 2];
    series[0].push(Math.hypot(x, y, z)); series[1].push(x); series[2].push(y); series[3].push(z);
  }
  const all = series.flat();
  let lo = Math.min(0, ...all), hi = Math.max(0, ...all);
  if (hi - lo < 1e-12) hi = lo + 1;
  const t0 = g.times[0] || 0, t1 = g.times[K - 1] || 1;
  const X = (t) => pad + (W - pad - 6) * (t1 > t0 ? (t - t0) / (t1 - t0) : 0);
  const Y = (v) => H - 16 - (H - 26) * (v - lo) / (hi - lo);
  ctx.strokeStyle = "#bbb"; ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(pad, Y(0)); ctx.lineTo(W - 6, Y(0)); ctx.stroke();
  const colours = ["#111", "#d62728", "#2ca02c", "#1f77b4"];
  series.forEach((s, i) => {
    ctx.strokeStyle = colours[i]; ctx.lineWidth = i ? 1 : 2; ctx.beginPath();
    s.forEach((v, k) => (k ? ctx.lineTo(X(g.times[k]), Y(v)) : ctx.moveTo(X(g.times[k]), Y(v))));
    ctx.stroke();
  });
  ctx.strokeStyle = "#f59e0b";
  ctx.beginPath(); ctx.moveTo(X(g.times[state.frame]), 4); ctx.lineTo(X(g.times[state.frame]), H - 16); ctx.stroke();
  ctx.fillStyle = "#333"; ctx.font = "10px sans-serif";
  ctx.fillText(`${fmt(hi)} m`, 2, 10); ctx.fillText(`${fmt(lo)} m`, 2, H - 18);
  ctx.fillText(`t = ${fmt(t0)}…${fmt(t1)} s`, pad, H - 3);
}

const ray = new THREE.Raycaster();
function pickAt(clientX, clientY) {
  const r = renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((clientX - r.left) / r.width) * 2 - 1,
                                -((clientY - r.top) / r.height) * 2 + 1);
  ray.setFromCamera(ndc, camera);
  const hit = ray.intersectObject(g.mesh, false)[0];
  pick(hit ? g.a.triangle_block[hit.faceIndex] : null);
}
let down = null;
renderer.domElement.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
renderer.domElement.addEventListener("pointerup", (e) => {
  if (g && down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) pickAt(e.clientX, e.clientY);
  down = null;
});

// where a block's visible surface is on the page (for tests and links): a triangle facing the camera
state.screenOf = (b) => {
  const r = renderer.domElement.getBoundingClientRect(), P = g.pos.array, tri = g.a.triangles;
  let best = null;
  for (let t = 0; t < g.T; t++) {
    if (g.a.triangle_block[t] !== b) continue;
    const c = new THREE.Vector3();
    for (let i = 0; i < 3; i++) {
      const v = tri[3 * t + i];
      c.add(new THREE.Vector3(P[3 * v], P[3 * v + 1], P[3 * v + 2]));
    }
    c.divideScalar(3);
    const dist = c.distanceTo(camera.position);
    if (!best || dist < best.dist) best = { c, dist };
  }
  const p = best.c.clone().project(camera);
  return { x: r.left + (p.x + 1) / 2 * r.width, y: r.top + (1 - p.y) / 2 * r.height };
};
state.pick = (b) => pick(b);
state.removed = () => (g ? [...removedAt(g.times[state.frame])] : []);
// a point of the model (the frames' coordinates) on the page, and the camera's frame
state.project = (p) => {
  const r = renderer.domElement.getBoundingClientRect();
  const q = new THREE.Vector3(...p).project(camera);
  return { x: r.left + (q.x + 1) / 2 * r.width, y: r.top + (1 - q.y) / 2 * r.height };
};
state.camera = () => {
  camera.updateMatrixWorld();
  const e = camera.matrixWorld.elements;
  return { position: camera.position.toArray(), target: controls.target.toArray(),
           right: [e[0], e[1], e[2]], up: [e[4], e[5], e[6]] };
};
// look at the centre of rotation from a direction (x East, y North, z up), same distance
state.lookFrom = (dir) => {
  const d = camera.position.distanceTo(controls.target);
  camera.position.copy(controls.target).add(new THREE.Vector3(...dir).normalize().multiplyScalar(d));
  controls.update();
  updateOverlays();
  dirty = true;
};
state.play = (on) => setPlaying(on);
state.setFrame = (k) => setFrame(k);
state.litPixels = () => {
  renderer.render(scene, camera);
  const gl = renderer.getContext(), w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
  const px = new Uint8Array(w * h * 4);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
  let lit = 0;
  for (let i = 0; i < px.length; i += 4) {
    if (Math.abs(px[i] - 244) + Math.abs(px[i + 1] - 245) + Math.abs(px[i + 2] - 247) > 30) lit++;
  }
  return lit;
};

// ------------------------------------------------------------------ controls
let playing = false, lastTick = 0;
state.playing = false;
state.framesPlayed = 0;
function setPlaying(on) {
  playing = !!on;
  state.playing = playing;
  $("play").textContent = playing ? "Pause" : "Play";
  if (playing && state.frame >= state.frameCount - 1 && state.status !== "running") setFrame(0);
}
$("play").addEventListener("click", () => setPlaying(!playing));
$("slider").addEventListener("input", (e) => setFrame(+e.target.value));
$("colour").addEventListener("change", () => draw(state.frame));
$("joints").addEventListener("change", (e) => { if (g) { g.joints.visible = e.target.checked; dirty = true; } });
$("contacts").addEventListener("change", () => { if (g) draw(state.frame); });
$("save").addEventListener("click", () => {
  renderer.render(scene, camera);
  const a = document.createElement("a");
  a.href = renderer.domElement.toDataURL("image/png");
  a.download = `polydda-${cfg.job.split("/").pop().slice(0, 8)}-step${g ? g.steps[state.frame] : 0}.png`;
  a.click();
});

function loop(now) {
  requestAnimationFrame(loop);
  if (playing && now - lastTick > 1000 / +$("fps").value) {
    lastTick = now;
    if (state.frame < state.frameCount - 1) { setFrame(state.frame + 1); state.framesPlayed++; }
    else if (state.status !== "running") setPlaying(false);
  }
  if (dirty) { dirty = false; renderer.render(scene, camera); }
}

// ------------------------------------------------------------------ loading and following
async function jobStatus() {
  const r = await fetch(cfg.job, { credentials: "same-origin" });
  return r.ok ? (await r.json()).status : "unknown";
}

async function follow() {
  for (;;) {
    await new Promise((res) => setTimeout(res, cfg.poll_ms));
    try {
      if (!g) {
        await start();
        if (!g) continue;
      }
      const job = await jobStatus();
      // the next step at the chosen stride; a run that ended between two steps of the
      // stride still shows its last one
      const { head, arrays } = await getFrames({ start: Math.min(g.next, g.nSteps),
                                                 stride: g.stride, geometry: false });
      if (head.count) appendMotion(head, arrays);
      state.status = job === "running" || job === "accepted" ? "running" : `job ${job}`;
      updateLabel();
      if (state.status !== "running" && !head.count) return;
    } catch (err) {
      if (err.status !== 404) { state.error = String(err.message || err); $("status").textContent = state.error; }
    }
  }
}

function every(head, a, stride) {
  // frames 0, stride, 2 stride, ... of a payload fetched at stride 1
  const keep = [];
  for (let k = 0; k < head.count; k += stride) keep.push(k);
  const rows = (arr) => {
    const w = arr.length / Math.max(1, head.count), out = new Float32Array(keep.length * w);
    keep.forEach((k, i) => out.set(arr.subarray(k * w, (k + 1) * w), i * w));
    return out;
  };
  return [{ ...head, stride, count: keep.length, next_start: null,
            steps: keep.map((k) => head.steps[k]), times: keep.map((k) => head.times[k]) },
          { displacement: rows(a.displacement), rotation: rows(a.rotation), velocity: rows(a.velocity) }];
}

async function start() {
  const t0 = performance.now();
  let data;
  try {
    // the geometry and the first steps (all of them unless the payload would be too big)
    const early = window.polyddaFirst;  // started by the page (cfg.first) before the scripts
    window.polyddaFirst = null;
    data = await getFrames({ start: 0, stop: cfg.max_frames, geometry: true }, early);
  } catch (err) {
    state.status = err.status === 404 ? "waiting for the first step" : `error: ${err.message}`;
    state.error = err.status === 404 ? null : err.message;
    $("status").textContent = state.status;
    return;
  }
  const { head, arrays } = data;
  build(head, arrays);
  state.blockCount = head.n_blocks;
  state.status = head.status === "running" ? "running" : `result ${head.status}`;
  $("title-blocks").textContent = `${head.n_blocks} blocks`;
  $("contacts").disabled = !head.contacts_recorded;
  $("joints").disabled = !(head.joints || []).length;
  resize();
  // every recorded step, or a stride that keeps the motion within the viewer's budget
  const budget = Math.min(cfg.max_frames, Math.floor(cfg.max_bytes / (40 * Math.max(1, head.n_blocks))));
  g.stride = Math.max(1, Math.ceil(head.n_steps / Math.max(1, budget)));
  appendMotion(...(g.stride === 1 ? [head, arrays] : every(head, arrays, g.stride)));
  while (g.next < g.nSteps) {
    const part = await getFrames({ start: g.next, stride: g.stride, geometry: false });
    if (!part.head.count) break;
    appendMotion(part.head, part.arrays);
  }
  $("stride").textContent = g.stride > 1 ? `every ${g.stride}th recorded step` : "";
  // a finished run from its start: the first frame, then play (cfg.play false: stay
  // there); a live one at its newest step, followed (playing at the chosen fps would fall
  // behind a run that records faster)
  const live = state.status === "running" && $("follow").checked;
  setFrame(live ? state.frameCount - 1 : 0);
  state.startFrame = state.frame;
  updateOverlays();
  renderer.render(scene, camera);
  dirty = false;
  state.loadMs = performance.now() - t0;
  state.readyMs = performance.now();  // since the navigation started
  state.ready = true;
  $("load-time").textContent = `loaded in ${(state.loadMs / 1000).toFixed(2)} s`;
  if (cfg.play !== false && !live && state.frameCount > 1) setPlaying(true);
}

resize();
requestAnimationFrame(loop);
start().then(() => { if (!g || state.status === "running") follow(); });
