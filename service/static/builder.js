// PolyDDA scene builder. The page's state is the scene's JSON itself: every field of the
// form reads and writes one path of it (data-path), so "Download scene" gives exactly what
// the form shows and "Open scene" loads any scene back (fields the form has no input for
// are kept as they are). No rule is written here: the scene as it stands goes to
// POST /builder/validate as it changes, and its problems (the API's messages) are shown at
// their fields. Preview: POST /builder/preview; Run: POST /jobs, followed by its events.
import { BlockPreview } from "polydda/preview3d.js";

const cfg = JSON.parse(document.getElementById("builder-config").textContent);
const $ = (id) => document.getElementById(id);
const api = (p) => `${cfg.root}${p}`;

// ------------------------------------------------------------------ the scene and its paths
let scene = {
  name: "new scene",
  domain: { box: { min: [0, 0, 0], max: [10, 10, 10] } },
  analysis: { duration: 1.0, time_step: 0.001, record_interval: 10 },
};
const state = { validation: null, preview: null, job: null, previewMs: null, problems: [] };
window.builder = { scene: () => JSON.parse(JSON.stringify(scene)), state, setScene: (s) => setScene(s) };

const split = (path) => path.split(".").map((k) => (/^\d+$/.test(k) ? +k : k));

function getPath(obj, path) {
  let o = obj;
  for (const k of split(path)) { if (o == null) return undefined; o = o[k]; }
  return o;
}

function setPath(obj, path, value) {
  const keys = split(path);
  let o = obj;
  for (let i = 0; i < keys.length - 1; i++) {
    if (o[keys[i]] == null || typeof o[keys[i]] !== "object") o[keys[i]] = typeof keys[i + 1] === "number" ? [] : {};
    o = o[keys[i]];
  }
  const last = keys[keys.length - 1];
  if (value === undefined) {
    if (Array.isArray(o) && typeof last === "number") o[last] = null; else delete o[last];
  } else o[last] = value;
}

function key() {
  const m = document.cookie.match(/(?:^|; )polydda_key=([^;]*)/);
  return m ? decodeURIComponent(m[1]) : null;
}

function headers(type = "application/json") {
  const h = { "Content-Type": type, Accept: "application/json" };
  if (key()) h["X-API-Key"] = key();
  return h;
}

// a text field's value as JSON: a number when it reads as one, else the text (the API says
// what is wrong with it), nothing when empty (the schema's default applies)
function parseValue(text, type) {
  if (type === "text") return text === "" ? undefined : text;
  if (type === "list") {
    const items = text.split(",").map((t) => t.trim()).filter(Boolean);
    return items.length ? items : undefined;
  }
  const t = text.trim();
  if (t === "") return undefined;
  const n = Number(t);
  return Number.isFinite(n) && /^[-+]?(\d|\.\d)/.test(t) ? n : t;
}

function showValue(v, type) {
  if (v === undefined || v === null) return "";
  if (type === "list") return Array.isArray(v) ? v.join(", ") : String(v);
  return typeof v === "object" ? JSON.stringify(v) : String(v);
}

// ------------------------------------------------------------------ schema help
let schema = null;
function schemaAt(path) {
  // the JSON Schema of a scene path (its description and bounds), following $refs
  if (!schema) return null;
  const deref = (s) => {
    while (s && s.$ref) s = schema.$defs[s.$ref.split("/").pop()];
    if (s && (s.anyOf || s.oneOf)) return deref((s.anyOf || s.oneOf).find((x) => x.type !== "null") || s);
    return s;
  };
  let s = deref(schema);
  for (const k of split(path)) {
    if (!s) return null;
    if (typeof k === "number") s = deref(s.items || (s.prefixItems || [])[k]);
    else if (s.properties && s.properties[k]) s = deref(s.properties[k]);
    else if (s.additionalProperties) s = deref(s.additionalProperties);
    else return null;
  }
  return s;
}

// ------------------------------------------------------------------ form building blocks
function h(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  e.append(...children.filter((c) => c !== null && c !== undefined));
  return e;
}

function input(path, type = "number", label = null, attrs = {}) {
  // one field bound to `path` of the scene
  const value = getPath(scene, path);
  let e;
  if (type === "checkbox") {
    e = h("input", { type: "checkbox", "data-path": path, ...attrs });
    e.checked = value === true;
    e.addEventListener("change", () => { setPath(scene, path, e.checked ? true : undefined); changed(); });
  } else if (Array.isArray(type)) {
    e = h("select", { "data-path": path, ...attrs }, h("option", { value: "" }, "(default)"),
      ...type.map((o) => h("option", { value: o }, o)));
    e.value = value === undefined ? "" : String(value);
    e.addEventListener("change", () => { setPath(scene, path, e.value === "" ? undefined : e.value); changed(); });
  } else {
    e = h("input", { type: "text", "data-path": path, inputmode: type === "number" ? "decimal" : undefined,
      size: type === "number" ? 7 : 14, ...attrs });
    e.value = showValue(value, type);
    e.addEventListener("input", () => { setPath(scene, path, parseValue(e.value, type)); changed(); });
  }
  const help = schemaAt(path);
  if (help && help.description) e.title = help.description;
  return label === null ? e : h("label", {}, `${label} `, e);
}

function xyz(path, label) {
  return h("span", { class: "xyz" }, `${label} `, input(`${path}.0`, "number", null, { placeholder: "x", size: 5 }),
    input(`${path}.1`, "number", null, { placeholder: "y", size: 5 }),
    input(`${path}.2`, "number", null, { placeholder: "z", size: 5 }));
}

function section(title, id, ...content) {
  return h("fieldset", { id }, h("legend", {}, title), ...content);
}

// a table of the list at `path` (columns: [key relative to a row, label, type])
function listTable(path, columns, blank, id) {
  const rows = getPath(scene, path) || [];
  const body = rows.map((_, k) => h("tr", {}, ...columns.map(([col, , type]) =>
    h("td", {}, input(`${path}.${k}.${col}`, type || "number"))),
    h("td", {}, h("button", { type: "button", class: "remove", title: "remove this row",
      onclick: () => { rows.splice(k, 1); if (!rows.length) setPath(scene, path, undefined); render(); changed(); } }, "×"))));
  return h("div", { class: "table", id },
    h("table", {}, h("tr", {}, ...columns.map(([, label]) => h("th", {}, label)), h("th", {})), ...body),
    h("button", { type: "button", class: "add", onclick: () => {
      const list = getPath(scene, path) || [];
      list.push(typeof blank === "function" ? blank(list.length) : JSON.parse(JSON.stringify(blank)));
      setPath(scene, path, list); render(); changed();
    } }, "+ add"));
}

// a table of the object at `path` keyed by name (materials, joint materials)
function dictTable(path, columns, blank, id) {
  const obj = getPath(scene, path) || {};
  const names = Object.keys(obj);
  const rename = (old, name) => {
    if (!name || name === old || name in obj) return;
    const out = {};
    for (const k of Object.keys(obj)) out[k === old ? name : k] = obj[k];
    setPath(scene, path, out);
  };
  const body = names.map((name) => h("tr", {},
    h("td", {}, h("input", { type: "text", value: name, size: 10, "data-name-of": path,
      onchange: (e) => { rename(name, e.target.value.trim()); render(); changed(); } })),
    ...columns.map(([col, , type]) => h("td", {}, input(`${path}.${name}.${col}`, type || "number"))),
    h("td", {}, h("button", { type: "button", class: "remove", onclick: () => {
      delete obj[name]; if (!Object.keys(obj).length) setPath(scene, path, undefined); render(); changed(); } }, "×"))));
  return h("div", { class: "table", id },
    h("table", {}, h("tr", {}, h("th", {}, "name"), ...columns.map(([, label]) => h("th", {}, label)), h("th", {})), ...body),
    h("button", { type: "button", class: "add", onclick: () => {
      const o = getPath(scene, path) || {};
      let k = 1; while (`${blank.prefix}${k}` in o) k++;
      o[`${blank.prefix}${k}`] = JSON.parse(JSON.stringify(blank.value));
      setPath(scene, path, o); render(); changed();
    } }, "+ add"));
}

function optional(path, label, blank, ...content) {
  // a part of the scene that is there or not (seismic, water, slope face)
  const on = getPath(scene, path) !== undefined;
  return h("div", { class: "optional" },
    h("label", {}, h("input", { type: "checkbox", "data-toggle": path, checked: on || undefined, onchange: (e) => {
      setPath(scene, path, e.target.checked ? JSON.parse(JSON.stringify(blank)) : undefined); render(); changed(); } }), ` ${label}`),
    on ? h("div", { class: "inner" }, ...content.map((c) => (typeof c === "function" ? c() : c))) : null);
}

// ------------------------------------------------------------------ the sections
const DOMAINS = ["box", "slope", "terrain"];

function domainKind() {
  const d = scene.domain || {};
  return DOMAINS.find((k) => d[k] !== undefined) || (Object.keys(d).some((k) => ["polyhedron", "mesh"].includes(k)) ? "other" : "none");
}

function setDomainKind(kind) {
  const d = scene.domain || {};
  for (const k of [...DOMAINS, "polyhedron", "mesh"]) delete d[k];
  if (kind === "box") d.box = { min: [0, 0, 0], max: [10, 10, 10] };
  if (kind === "slope") d.slope = { profile: [[0, 0], [5, 0], [12.28, 20], [27.28, 20]], dip_direction: 180, width: 20, base: -5 };
  if (kind === "terrain") d.terrain = { base: -5 };
  scene.domain = d;
  render(); changed();
}

function benchProfile() {
  // the profile table from the bench table: toe platform, benches (height, face angle,
  // berm), crest platform
  const v = (id) => Number($(id).value);
  const rows = [...document.querySelectorAll("#bench-table tr[data-bench]")].map((tr) =>
    [...tr.querySelectorAll("input")].map((i) => Number(i.value)));
  let s = 0, z = v("bench-toe-z");
  const profile = [[0, z]];
  s += v("bench-toe"); profile.push([round(s), z]);
  rows.forEach(([height, angle, berm], k) => {
    s += height / Math.tan(angle * Math.PI / 180); z += height; profile.push([round(s), round(z)]);
    if (k < rows.length - 1 && berm > 0) { s += berm; profile.push([round(s), round(z)]); }
  });
  s += v("bench-crest"); profile.push([round(s), round(z)]);
  setPath(scene, "domain.slope.profile", profile);
  render(); changed();
}
const round = (x) => Math.round(x * 1e4) / 1e4;

function benchTable() {
  const row = (hgt, ang, berm) => h("tr", { "data-bench": "" },
    h("td", {}, h("input", { type: "text", size: 5, value: hgt, "aria-label": "bench height" })),
    h("td", {}, h("input", { type: "text", size: 5, value: ang, "aria-label": "face angle" })),
    h("td", {}, h("input", { type: "text", size: 5, value: berm, "aria-label": "berm" })),
    h("td", {}, h("button", { type: "button", class: "remove", onclick: (e) => e.target.closest("tr").remove() }, "×")));
  const table = h("table", { id: "bench-table" }, h("tr", {}, h("th", {}, "height m"), h("th", {}, "face angle °"), h("th", {}, "berm m"), h("th", {})), row(20, 70, 0));
  return h("details", { class: "helper", id: "bench-helper", open: true }, h("summary", {}, "Bench table → profile"),
    h("label", {}, "toe elevation ", h("input", { id: "bench-toe-z", type: "text", size: 5, value: 0 })),
    h("label", {}, " toe platform m ", h("input", { id: "bench-toe", type: "text", size: 5, value: 5 })),
    h("label", {}, " crest platform m ", h("input", { id: "bench-crest", type: "text", size: 5, value: 15 })),
    table,
    h("button", { type: "button", onclick: () => table.append(row(10, 70, 4)) }, "+ bench"), " ",
    h("button", { type: "button", id: "make-profile", onclick: benchProfile }, "Make profile"));
}

async function uploadTerrain(file) {
  const note = $("terrain-note");
  const name = file.name.toLowerCase();
  if (name.endsWith(".tif") || name.endsWith(".tiff")) {
    note.textContent = "reading the GeoTIFF…";
    const r = await fetch(api("/builder/terrain"), { method: "POST", headers: headers("application/octet-stream"), body: await file.arrayBuffer() });
    const doc = await r.json();
    if (!r.ok) { note.textContent = doc.detail || r.statusText; return; }
    const t = scene.domain.terrain; delete t.data; delete t.file; delete t.format;
    t.grid = doc.grid;
    note.textContent = `${file.name}: ${doc.nodes} nodes (inline grid)`;
  } else {
    const t = scene.domain.terrain; delete t.grid; delete t.file;
    t.data = await file.text();
    t.format = name.endsWith(".asc") ? "asc" : "csv";
    note.textContent = `${file.name} (inline ${t.format})`;
  }
  render(); changed();
}

function domainSection() {
  const kind = domainKind();
  const radios = h("div", { class: "radios" }, ...[...DOMAINS, "other"].map((k) => h("label", {},
    h("input", { type: "radio", name: "domain-kind", value: k, id: `domain-${k}`, checked: k === kind || undefined,
      disabled: k === "other" || undefined, onchange: () => setDomainKind(k) }), ` ${k}`)));
  const parts = [radios];
  if (kind === "box") parts.push(xyz("domain.box.min", "min"), xyz("domain.box.max", "max"));
  if (kind === "slope") {
    parts.push(h("div", {}, input("domain.slope.dip_direction", "number", "faces (dip direction °)"),
      input("domain.slope.width", "number", "width m"), input("domain.slope.base", "number", "base z m"),
      h("span", {}, " origin ", input("domain.slope.origin.0", "number", null, { placeholder: "x", size: 5 }),
        input("domain.slope.origin.1", "number", null, { placeholder: "y", size: 5 }))),
    h("div", {}, h("b", {}, "profile (s into the slope, z)"), listTable("domain.slope.profile", [["0", "s m"], ["1", "z m"]], [0, 0], "profile-table")),
    benchTable());
  }
  if (kind === "terrain") {
    parts.push(h("div", {}, h("label", {}, "ground: CSV x,y,z, ESRI .asc or GeoTIFF ",
      h("input", { type: "file", id: "terrain-file", accept: ".csv,.asc,.txt,.tif,.tiff", onchange: (e) => e.target.files[0] && uploadTerrain(e.target.files[0]) })),
      h("span", { id: "terrain-note", class: "muted" }, scene.domain.terrain.grid ? "inline grid" : (scene.domain.terrain.format || ""))),
    input("domain.terrain.base", "number", "base z m"),
    h("span", {}, " footprint ", ...[0, 1, 2, 3].map((k) => input(`domain.terrain.footprint.${k}`, "number", null, { placeholder: ["x0", "y0", "x1", "y1"][k], size: 5 }))));
  }
  if (kind === "other") parts.push(h("p", { class: "muted" }, "a polyhedron or mesh domain: edit it in the scene JSON"));
  if (kind !== "none") {
    parts.push(h("div", {}, input("domain.name_prefix", "text", "block names"),
      input("domain.min_block_volume", "number", "min block volume m³"),
      input("domain.material", "text", "material")));
  }
  return section("Domain", "domain-section", ...parts);
}

function fixGround() {
  const z = Number($("ground-z").value);
  const joints = scene.joints || [];
  if (!joints.some((j) => j.name === "ground")) joints.unshift({ name: "ground", dip: 0, dip_direction: 0, point: [0, 0, z] });
  scene.joints = joints;
  const b = scene.boundary || (scene.boundary = {});
  b.fixed_blocks = (b.fixed_blocks || []).concat([{ centroid_in: { min: [-1e6, -1e6, -1e6], max: [1e6, 1e6, z] } }]);
  render(); changed();
}

function fixedSection() {
  const list = (getPath(scene, "boundary.fixed_blocks") || []);
  const rows = list.map((sel, k) => {
    const p = `boundary.fixed_blocks.${k}`;
    const body = typeof sel === "string" ? input(p, "text") : sel && sel.centroid_in
      ? h("span", {}, "centroid in ", xyz(`${p}.centroid_in.min`, "min"), xyz(`${p}.centroid_in.max`, "max"))
      : sel && sel.name !== undefined ? input(`${p}.name`, "text", "name") : h("code", {}, JSON.stringify(sel));
    return h("div", { class: "row" }, body, h("button", { type: "button", class: "remove", onclick: () => {
      list.splice(k, 1); render(); changed(); } }, "×"));
  });
  return section("Fixed blocks", "fixed-section", ...rows,
    h("div", {}, h("label", {}, "fix the rock below z = ", h("input", { id: "ground-z", type: "text", size: 5, value: 0 })),
      " ", h("button", { type: "button", id: "fix-ground", onclick: fixGround }, "Fix ground"),
      h("span", { class: "muted" }, " (a horizontal joint there, and the blocks below it fixed)")));
}

async function fitMeasurements() {
  const file = $("measurements").files[0];
  if (!file) return;
  const body = { csv: await file.text(), sets: Number($("measure-sets").value) || 2 };
  const r = await fetch(api("/builder/stereonet"), { method: "POST", headers: headers(), body: JSON.stringify(body) });
  const doc = await r.json();
  state.stereonet = r.ok ? doc : { error: doc.detail || r.statusText };
  $("measure-out").replaceChildren(...stereonetOut());
}

function stereonetOut() {
  // the fitted sets (state.stereonet): the stereonet, the sets' table, "Add as joint sets"
  const doc = state.stereonet;
  if (!doc) return [];
  if (doc.error) return [h("p", { class: "bad" }, doc.error)];
  return [h("img", { src: doc.stereonet, alt: "stereonet of the measured poles", id: "stereonet", width: 360 }),
    h("table", {}, h("tr", {}, ...["set", "dip/dip dir.", "κ", "poles", "α95"].map((t) => h("th", {}, t))),
      ...doc.sets.map((s) => h("tr", {}, h("td", {}, s.name), h("td", {}, `${s.dip.toFixed(1)}/${s.dip_direction.toFixed(1)}`),
        h("td", {}, s.kappa.toFixed(1)), h("td", {}, s.count), h("td", {}, `${s.cone_95.toFixed(1)}°`)))),
    h("button", { type: "button", id: "add-sets", onclick: () => {
      const spacing = parseValue($("measure-spacing").value, "number");
      const joints = scene.joints || (scene.joints = []);
      for (const s of doc.sets) {
        const j = { name: s.name, dip: round(s.dip), dip_direction: round(s.dip_direction % 360), point: [0, 0, 0] };
        if (spacing !== undefined) j.spacing = spacing;
        joints.push(j);
      }
      render(); changed();
    } }, "Add as joint sets")];
}

function jointSection() {
  const cols = [["name", "name", "text"], ["dip", "dip °"], ["dip_direction", "dip dir. °"], ["spacing", "spacing m"],
    ["point.0", "x"], ["point.1", "y"], ["point.2", "z"], ["extent.disc.radius", "persistence: disc radius m (blank: persistent)"],
    ["joint_material", "joint material", "text"]];
  return section("Joints and joint sets", "joint-section",
    listTable("joints", cols, (k) => ({ name: `J${k + 1}`, dip: 60, dip_direction: 180, point: [0, 0, 0], spacing: 4 }), "joint-table"),
    h("details", { class: "helper", open: state.stereonet ? true : undefined },
      h("summary", {}, "Fit sets to measurements (CSV of dip, dip_direction)"),
      h("input", { type: "file", id: "measurements", accept: ".csv,.txt" }),
      h("label", {}, " sets ", h("input", { id: "measure-sets", type: "text", size: 3, value: 2 })),
      h("label", {}, " spacing m ", h("input", { id: "measure-spacing", type: "text", size: 4, value: 4 })),
      " ", h("button", { type: "button", id: "fit-sets", onclick: fitMeasurements }, "Fit sets"),
      h("div", { id: "measure-out" }, ...stereonetOut())));
}

function materialSection() {
  return section("Materials", "material-section",
    dictTable("materials", [["density", "density kg/m³"], ["young_modulus", "E Pa"], ["poisson_ratio", "ν"]],
      { prefix: "rock", value: { density: 2600 } }, "material-table"),
    input("default_material", "text", "default material"),
    h("b", {}, "Joint strength"),
    dictTable("joint_materials", [["friction_angle", "φ °"], ["cohesion", "c Pa"], ["tensile_strength", "tension Pa"]],
      { prefix: "joint", value: { friction_angle: 35 } }, "joint-material-table"),
    input("default_joint_material", "text", "default joint material"));
}

function loadsSection() {
  return section("Water, seismic, bolts", "loads-section",
    optional("water", "water", { phreatic_surface: { point: [0, 0, 0] } },
      () => optional("water.phreatic_surface", "phreatic surface", { point: [0, 0, 0] },
        xyz("water.phreatic_surface.point", "point"), input("water.phreatic_surface.dip", "number", "dip °"),
        input("water.phreatic_surface.dip_direction", "number", "dip dir. °")),
      h("b", {}, "joint water pressure"),
      () => listTable("water.joint_pressures", [["joint_material", "joint material", "text"], ["pressure", "pressure Pa"]],
        { joint_material: "joint", pressure: 10000 }, "pressure-table"),
      input("water.unit_weight", "number", "γw N/m³")),
    optional("seismic", "seismic (pseudo-static)", { kh: 0.1 },
      input("seismic.kh", "number", "kh"), input("seismic.kv", "number", "kv"), input("seismic.azimuth", "number", "towards °")),
    h("b", {}, "Bolts"),
    listTable("bolts", [["name", "name", "text"], ["head.0", "head x"], ["head.1", "y"], ["head.2", "z"],
      ["anchor.0", "anchor x"], ["anchor.1", "y"], ["anchor.2", "z"], ["pretension", "pretension N"], ["capacity", "capacity N"]],
    (k) => ({ name: `bolt${k + 1}`, head: [0, 0, 0], anchor: [0, 0, -3] }), "bolt-table"),
    h("b", {}, "Bolt patterns"),
    listTable("bolt_patterns", [["name_prefix", "names", "text"], ["origin.0", "origin x"], ["origin.1", "y"], ["origin.2", "z"],
      ["face_normal.0", "face normal x"], ["face_normal.1", "y"], ["face_normal.2", "z"],
      ["row_direction.0", "row dir. x"], ["row_direction.1", "y"], ["row_direction.2", "z"],
      ["spacing", "spacing m"], ["rows", "rows"], ["columns", "columns"], ["length", "length m"],
      ["trend", "trend °"], ["plunge", "plunge °"], ["pretension", "pretension N"]],
    (k) => ({ name_prefix: `P${k + 1}-`, origin: [0, 0, 0], face_normal: [0, -1, 0], row_direction: [1, 0, 0],
      spacing: 2, rows: 2, columns: 2, length: 4, trend: 0, plunge: 0 }), "pattern-table"));
}

function excavationSection() {
  const list = scene.excavations || [];
  const rows = list.map((ex, k) => {
    const p = `excavations.${k}`;
    const kind = ["tunnel", "bench", "cavern"].find((t) => ex[t] !== undefined) || "tunnel";
    const fields = kind === "tunnel"
      ? [input(`${p}.tunnel.shape`, ["circular", "horseshoe", "d_shaped"], "shape"), input(`${p}.tunnel.width`, "number", "width m"),
        input(`${p}.tunnel.height`, "number", "height m"), xyz(`${p}.tunnel.start`, "start"),
        input(`${p}.tunnel.trend`, "number", "trend °"), input(`${p}.tunnel.plunge`, "number", "plunge °"),
        input(`${p}.tunnel.length`, "number", "length m")]
      : kind === "bench"
        ? [input(`${p}.bench.dip_direction`, "number", "dip dir. °"), input(`${p}.bench.width`, "number", "width m"),
          input(`${p}.bench.origin.0`, "number", "origin x"), input(`${p}.bench.origin.1`, "number", "y"),
          h("b", {}, " section (s, z)"), listTable(`${p}.bench.section`, [["0", "s m"], ["1", "z m"]], [0, 0], null)]
        : [xyz(`${p}.cavern.center`, "centre"), xyz(`${p}.cavern.size`, "size"), input(`${p}.cavern.trend`, "number", "trend °")];
    return h("div", { class: "row excavation" }, input(`${p}.name`, "text", "name"),
      h("select", { onchange: (e) => {
        delete ex.tunnel; delete ex.bench; delete ex.cavern;
        ex[e.target.value] = e.target.value === "tunnel" ? { width: 4, start: [0, 0, 0], trend: 0, length: 10 }
          : e.target.value === "bench" ? { section: [[0, 0], [5, 0], [5, 5]], dip_direction: 180, width: 10 }
            : { center: [0, 0, 0], size: [10, 5, 5] };
        render(); changed(); } }, ...["tunnel", "bench", "cavern"].map((t) => h("option", { value: t, selected: t === kind || undefined }, t))),
      input(`${p}.cut`, ["after_joints", "before_joints"], "cut"), ...fields,
      h("button", { type: "button", class: "remove", onclick: () => { list.splice(k, 1); if (!list.length) delete scene.excavations; render(); changed(); } }, "×"));
  });
  return section("Excavations", "excavation-section", ...rows,
    h("button", { type: "button", class: "add", onclick: () => {
      (scene.excavations || (scene.excavations = [])).push({ name: `opening${list.length + 1}`,
        tunnel: { shape: "horseshoe", width: 6, start: [0, 0, 0], trend: 0, length: 10 } });
      render(); changed(); } }, "+ add"));
}

function stageSection() {
  return section("Stages", "stage-section",
    listTable("stages", [["name", "name", "text"], ["duration", "duration s"], ["excavate", "excavate", "list"],
      ["add_bolts", "add bolts", "list"], ["drain", "drain", "checkbox"], ["quiet", "quiet", "checkbox"]],
    (k) => ({ name: `stage${k + 1}`, duration: 0.5 }), "stage-table"));
}

function analysisSection() {
  return section("Analysis", "analysis-section",
    input("analysis.type", ["simulation", "factor_of_safety", "limit_equilibrium", "critical_seismic_coefficient"], "type"),
    input("analysis.duration", "number", "duration s"), input("analysis.time_step", "number", "Δt s"),
    input("analysis.record_interval", "number", "record every (steps)"),
    input("analysis.contact_solver", ["open_close", "complementarity"], "contact solver"),
    optional("slope_face", "slope face (kinematic screening)", { dip: 70, dip_direction: 180 },
      input("slope_face.dip", "number", "dip °"), input("slope_face.dip_direction", "number", "dip dir. °")));
}

function render() {
  // the whole form from the scene (the state); focus is kept on the field being typed in
  const active = document.activeElement && document.activeElement.dataset ? document.activeElement.dataset.path : null;
  const form = $("scene-form");
  form.replaceChildren(
    section("Scene", "scene-section", input("name", "text", "name"), input("description", "text", "description", { size: 40 })),
    domainSection(), fixedSection(), jointSection(), materialSection(), loadsSection(),
    excavationSection(), stageSection(), analysisSection());
  if (active) { const e = form.querySelector(`[data-path="${active}"]`); if (e) e.focus(); }
  markProblems();
}

// ------------------------------------------------------------------ validation
let timer = null, asked = 0;
function changed() {
  $("scene-json").textContent = JSON.stringify(scene, null, 2);
  clearTimeout(timer);
  timer = setTimeout(validate, 250);
}

function pathOf(loc) {
  // an API field path (`joints[2] ('J3').dip`) as the form's (`joints.2.dip`)
  return loc.replace(/ \('[^']*'\)/g, "").replace(/\[(\d+)\]/g, ".$1");
}

function markProblems() {
  document.querySelectorAll(".has-problem").forEach((e) => { e.classList.remove("has-problem"); e.removeAttribute("data-problem"); });
  for (const p of state.problems) {
    let path = pathOf(p.loc), e = null;
    while (path && !(e = document.querySelector(`[data-path="${path}"]`))) path = path.includes(".") ? path.slice(0, path.lastIndexOf(".")) : "";
    if (e) { e.classList.add("has-problem"); e.setAttribute("data-problem", p.msg); e.title = p.msg; }
  }
}

async function validate() {
  const n = ++asked;
  $("valid").textContent = "checking…";
  let r;
  try {
    r = await fetch(api("/builder/validate"), { method: "POST", headers: headers(), body: JSON.stringify(scene), credentials: "same-origin" });
  } catch (err) { $("valid").textContent = `cannot reach the service: ${err.message}`; return; }
  const doc = await r.json().catch(() => ({}));
  if (n !== asked) return;  // an older answer
  state.validation = { status: r.status, doc };
  state.problems = r.ok ? [] : (doc.errors || [{ loc: "", msg: doc.detail || r.statusText }]);
  $("valid").textContent = r.ok ? "valid" : `${state.problems.length} problem${state.problems.length === 1 ? "" : "s"}`;
  $("valid").className = r.ok ? "good" : "bad";
  $("estimate").textContent = r.ok ? `about ${doc.estimated_blocks} block${doc.estimated_blocks === 1 ? "" : "s"}` : "";
  $("problems").replaceChildren(...state.problems.map((p) => h("li", { "data-loc": p.loc }, p.loc ? `${p.loc}: ${p.msg}` : p.msg)));
  markProblems();
}

// ------------------------------------------------------------------ preview
const view = new BlockPreview($("preview-view"), $("preview-legend"), $("section-controls"));
window.builder.view = view;

async function preview() {
  const t0 = performance.now();
  $("preview").disabled = true;
  $("block-count").textContent = "cutting…";
  try {
    const r = await fetch(api("/builder/preview"), { method: "POST", headers: headers(), body: JSON.stringify(scene), credentials: "same-origin" });
    const t1 = performance.now();
    const doc = await r.json().catch(() => ({}));
    if (!r.ok) {
      state.problems = doc.errors || [{ loc: "", msg: doc.detail || r.statusText }];
      $("problems").replaceChildren(...state.problems.map((p) => h("li", {}, p.loc ? `${p.loc}: ${p.msg}` : p.msg)));
      $("block-count").textContent = `no preview (${r.status})`;
      markProblems();
      return;
    }
    const t2 = performance.now();
    view.show(doc);
    state.preview = { count: doc.count, counts: view.counts, seconds: doc.seconds, timings: doc.timings,
                      page: { answer: (t1 - t0) / 1000, read: (t2 - t1) / 1000, drawn: (performance.now() - t2) / 1000 } };
    state.previewMs = performance.now() - t0;
    $("block-count").textContent = `${doc.count} blocks`;
    $("preview-time").textContent = `cut in ${doc.seconds.toFixed(2)} s, shown in ${(state.previewMs / 1000).toFixed(2)} s`
      + (doc.warnings.length ? ` · ${doc.warnings.length} warning(s)` : "");
    $("preview-time").title = doc.warnings.join("\n");
  } finally { $("preview").disabled = false; }
}
$("preview").addEventListener("click", preview);
$("preview-colour").addEventListener("change", (e) => view.setMode(e.target.value));

// ------------------------------------------------------------------ run
async function run() {
  const process = $("run-process").value;
  $("run-links").replaceChildren();
  $("run-status").textContent = "submitting…";
  const r = await fetch(api(`/jobs?process=${encodeURIComponent(process)}`), { method: "POST", headers: headers(), body: JSON.stringify(scene), credentials: "same-origin" });
  const doc = await r.json().catch(() => ({}));
  if (r.status !== 201) {
    $("run-status").textContent = `${r.status}: ${doc.detail || r.statusText}`;
    return;
  }
  state.job = { id: doc.jobID, status: doc.status, events: 0 };
  const bar = $("run-progress");
  bar.hidden = false; bar.value = 0;
  const events = new EventSource(api(`/jobs/${doc.jobID}/events`), { withCredentials: true });
  events.addEventListener("status", (e) => {
    const s = JSON.parse(e.data);
    state.job.status = s.status; state.job.events++; state.job.message = s.message;
    bar.value = s.progress || 0;
    $("run-status").textContent = `${s.status} ${Math.round(s.progress || 0)} %${s.message ? ` · ${s.message}` : ""}`;
    if (["successful", "failed", "dismissed"].includes(s.status)) {
      events.close();
      const base = api(`/jobs/${doc.jobID}`);
      const links = [];
      if (process === "simulation") links.push(h("a", { href: `${base}/viewer`, target: "_blank", id: "open-viewer" }, "viewer"));
      links.push(h("a", { href: `${base}/report`, target: "_blank", id: "open-report" }, "report"),
        h("a", { href: `${base}/results`, target: "_blank" }, "results"));
      $("run-links").replaceChildren(...links.flatMap((a, i) => (i ? [" · ", a] : [a])));
      showConclusion(`${base}/report`).finally(() => { state.job.done = true; });
    }
  });
  events.addEventListener("gone", () => events.close());
}
async function showConclusion(url) {
  // the report's conclusion, under the run (the whole report: its link)
  try {
    const r = await fetch(url, { credentials: "same-origin" });
    const page = new DOMParser().parseFromString(await r.text(), "text/html");
    const p = page.querySelector("p.conclusion");
    $("run-conclusion").textContent = p ? p.textContent : "";
    state.job.conclusion = p ? p.textContent : null;
  } catch (err) { $("run-conclusion").textContent = `no report: ${err.message}`; }
}
if (cfg.can_run) $("run").addEventListener("click", run);

// ------------------------------------------------------------------ open and download
function setScene(s) {
  scene = s;
  state.preview = null;
  render(); changed();
}

$("open-scene").addEventListener("change", async (e) => {
  const file = e.target.files[0];
  if (!file) return;
  const text = await file.text();
  let data;
  try { data = JSON.parse(text); } catch (err) { $("valid").textContent = `${file.name} is not JSON: ${err.message}`; return; }
  setScene(data);
  e.target.value = "";
});

// The last download's object URL lives until the next download: revoked on a timer, a
// browser slow to start the download (a loaded machine) found it gone and saved nothing.
let downloadURL = null;
$("download-scene").addEventListener("click", () => {
  const text = `${JSON.stringify(scene, null, 2)}\n`;
  if (downloadURL) URL.revokeObjectURL(downloadURL);
  downloadURL = URL.createObjectURL(new Blob([text], { type: "application/json" }));
  const a = document.createElement("a");
  a.href = downloadURL;
  const name = String(scene.name || "scene").replace(/[^A-Za-z0-9_.-]+/g, "_") || "scene";
  a.download = `${name}.json`;
  a.click();
});

// ------------------------------------------------------------------ start
fetch(cfg.schema, { credentials: "same-origin" }).then((r) => r.json()).then((s) => { schema = s; render(); }).catch(() => {});
render();
changed();
state.ready = true;
