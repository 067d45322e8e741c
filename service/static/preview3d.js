// PolyDDA builder: the preview of a scene's cut blocks (POST /builder/preview) in 3-D,
// coloured by key-block verdict, kinematic mode or block, with the section plane and
// "hide fixed blocks" of the viewer (section.js).
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";
import { attachSection } from "polydda/section.js";

export const VERDICT_COLOURS = {
  "key block": "#d62728", "potential key block": "#ff9f1c", "not removable": "#2ca02c",
  interior: "#d5d8dc", fixed: "#7f7f7f", excavated: "#9467bd",
};
export const MODE_COLOURS = {
  falling: "#d62728", "sliding on two planes": "#ff7f0e", "sliding on one plane": "#e7ba52",
  stable: "#2ca02c", interior: "#d5d8dc", fixed: "#7f7f7f", excavated: "#9467bd",
};

const TYPED = { float32: Float32Array, uint32: Uint32Array };

function decode({ dtype, data }) {
  // a base64 little-endian array of the preview document
  const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
  return new TYPED[dtype](bytes.buffer);
}

export class BlockPreview {
  constructor(canvas, legend, sectionBox) {
    this.canvas = canvas; this.legend = legend; this.sectionBox = sectionBox;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0xf4f5f7);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1e6);
    this.camera.up.set(0, 0, 1);
    this.controls = new OrbitControls(this.camera, canvas);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.6);
    sun.position.set(0.4, -0.6, 1.0);
    this.scene.add(sun);
    this.doc = null; this.mode = "verdict"; this.hideFixed = false; this.section = null;
    this.controls.addEventListener("change", () => this.render());
    if (window.ResizeObserver) new ResizeObserver(() => this.resize()).observe(canvas);
  }

  resize() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / Math.max(1, h);
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() { this.renderer.render(this.scene, this.camera); }

  colourOf(b) {
    const blk = this.doc.blocks[b];
    if (this.mode === "block") return new THREE.Color().setHSL((b * 0.618033988749895) % 1, 0.55, 0.6);
    const table = this.mode === "mode" ? MODE_COLOURS : VERDICT_COLOURS;
    return new THREE.Color(table[this.mode === "mode" ? blk.mode : blk.verdict] || "#888888");
  }

  show(doc) {
    const first = !this.doc;
    for (const [k, v] of Object.entries(doc.mesh)) doc[k] = decode(v);
    this.doc = doc;
    if (this.mesh) { this.scene.remove(this.mesh, this.edges); this.mesh.geometry.dispose(); this.edges.geometry.dispose(); }
    const vertices = doc.vertices;
    const edgeGeo = new THREE.BufferGeometry();
    edgeGeo.setAttribute("position", new THREE.BufferAttribute(vertices, 3));
    edgeGeo.setIndex(new THREE.BufferAttribute(doc.edges, 1));
    this.edges = new THREE.LineSegments(edgeGeo, new THREE.LineBasicMaterial({ color: 0x222222, transparent: true, opacity: 0.45 }));
    this.mesh = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.MeshLambertMaterial({
      vertexColors: true, side: THREE.DoubleSide, polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1 }));
    this.scene.add(this.mesh, this.edges);
    this.vblock = new Uint32Array(vertices.length / 3);
    for (let b = 0; b < doc.blocks.length; b++) this.vblock.fill(b, doc.vertex_offsets[b], doc.vertex_offsets[b + 1]);
    this.vertices = vertices;
    const size = Math.max(1e-6, Math.hypot(...doc.extent));
    if (first || this.size !== size) {
      this.size = size;
      const r = size / 2, dist = 1.05 * r / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2));
      this.camera.near = r / 1000; this.camera.far = r * 100;
      this.camera.position.set(-0.45, -0.8, 0.45).normalize().multiplyScalar(dist);
      this.controls.target.set(0, 0, 0);
      this.controls.update();
      const keep = this.section ? { ...this.section.state } : null;
      if (this.section) this.section.dispose();
      this.section = attachSection({
        renderer: this.renderer, scene: this.scene, camera: this.camera, controls: this.controls,
        canvas: this.canvas, box: this.sectionBox, size,
        materials: () => [this.mesh.material, this.edges.material], changed: () => this.render(),
        hideFixed: (on) => { this.hideFixed = on; this.paint(); } });
      if (keep) { this.section.set({ ...keep }); this.section.setHideFixed(keep.hideFixed); }
    }
    this.paint();
    this.section.refresh();
    this.resize();
  }

  setMode(mode) { this.mode = mode; if (this.doc) this.paint(); }

  paint() {
    // triangles of the blocks shown (fixed ones left out when hidden), coloured
    const d = this.doc, tri = d.triangles, tb = d.triangle_block, V = this.vertices;
    const colours = d.blocks.map((_, b) => this.colourOf(b));
    const keep = [];
    for (let t = 0; t < tb.length; t++) if (!(this.hideFixed && d.blocks[tb[t]].fixed)) keep.push(t);
    const pos = new Float32Array(keep.length * 9), col = new Float32Array(keep.length * 9);
    keep.forEach((t, i) => {
      const c = colours[tb[t]];
      for (let j = 0; j < 3; j++) {
        const v = tri[3 * t + j], o = 9 * i + 3 * j;
        pos[o] = V[3 * v]; pos[o + 1] = V[3 * v + 1]; pos[o + 2] = V[3 * v + 2];
        col[o] = c.r; col[o + 1] = c.g; col[o + 2] = c.b;
      }
    });
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(pos, 3));
    g.setAttribute("color", new THREE.BufferAttribute(col, 3));
    g.computeVertexNormals();
    this.mesh.geometry.dispose();
    this.mesh.geometry = g;
    const idx = [];
    const e = d.edges;
    for (let k = 0; k < e.length; k += 2) {
      if (this.hideFixed && (d.blocks[this.vblock[e[k]]].fixed)) continue;
      idx.push(e[k], e[k + 1]);
    }
    this.edges.geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(idx), 1));
    this.drawLegend();
    this.render();
  }

  drawLegend() {
    const d = this.doc;
    if (this.mode === "block") { this.legend.replaceChildren(); return; }
    const key = this.mode === "mode" ? "mode" : "verdict";
    const table = this.mode === "mode" ? MODE_COLOURS : VERDICT_COLOURS;
    const counts = {};
    for (const b of d.blocks) counts[b[key]] = (counts[b[key]] || 0) + 1;
    this.counts = counts;
    this.legend.replaceChildren(...Object.keys(table).filter((k) => counts[k]).map((k) => {
      const row = document.createElement("div");
      const dot = document.createElement("span");
      dot.className = "dot"; dot.style.background = table[k];
      row.append(dot, ` ${k}: ${counts[k]}`);
      row.dataset.kind = k;
      return row;
    }));
  }

  litPixels() {
    this.render();
    const gl = this.renderer.getContext(), w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let lit = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 244) + Math.abs(px[i + 1] - 245) + Math.abs(px[i + 2] - 247) > 30) lit++;
    }
    return lit;
  }
}
