// PolyDDA section plane and "hide fixed blocks", shared by the viewer and the builder's
// preview: see inside a rock mass (a tunnel behind its fixed rock, a slope's interior).
// The plane is set by its dip and dip direction (degrees, as joints are) and its offset
// (m, along its normal from the model's centre); drag with Shift to move it, with Alt to
// turn it. What lies above the plane (on the side its upward normal points to) is cut
// away; "flip" keeps that side instead.
import * as THREE from "three";

const RAD = Math.PI / 180;

export function planeNormal(dip, dipDirection) {
  // the upward unit normal of a plane of this dip / dip direction (x East, y North, z Up)
  const d = dip * RAD, a = dipDirection * RAD;
  return new THREE.Vector3(Math.sin(d) * Math.sin(a), Math.sin(d) * Math.cos(a), Math.cos(d));
}

function el(tag, attrs = {}, text = "") {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text) e.textContent = text;
  return e;
}

function field(label, input) {
  const l = el("label");
  l.append(label, " ", input);
  return l;
}

// attach the section controls to `box` (an element of the page) for a three.js view:
// `materials()` gives the materials to clip, `size` the model's diagonal (m); `changed()`
// redraws, `hideFixed(on)` hides or shows the fixed blocks
export function attachSection({ renderer, scene, camera, controls, canvas, box, size,
                                materials, changed, hideFixed }) {
  renderer.localClippingEnabled = true;
  let drag = null;
  const state = { on: false, dip: 90, dipDirection: 180, offset: 0, flip: false,
                  hideFixed: false };
  const plane = new THREE.Plane(new THREE.Vector3(0, 0, -1), 0);
  const half = Math.max(1e-6, size / 2);
  const helper = new THREE.Mesh(new THREE.PlaneGeometry(2 * half, 2 * half),
    new THREE.MeshBasicMaterial({ color: 0xf59e0b, transparent: true, opacity: 0.12,
                                  side: THREE.DoubleSide, depthWrite: false }));
  helper.visible = false;
  scene.add(helper);

  const on = el("input", { type: "checkbox", id: "section-on" });
  const dip = el("input", { type: "number", id: "section-dip", min: 0, max: 90, step: 1,
                            value: state.dip, style: "width:4em" });
  const ddir = el("input", { type: "number", id: "section-dip-direction", min: 0, max: 360,
                             step: 1, value: state.dipDirection, style: "width:4.5em" });
  const offset = el("input", { type: "range", id: "section-offset", min: -half, max: half,
                               step: size / 500, value: 0, style: "width:9em" });
  const flip = el("input", { type: "checkbox", id: "section-flip" });
  const fixed = el("input", { type: "checkbox", id: "hide-fixed" });
  const note = el("span", { class: "muted", id: "section-note" });
  const sectionLabel = el("label", { title: "cut the view by a plane: Shift-drag moves it, "
                                            + "Alt-drag turns it" });
  sectionLabel.append(on, " section");
  const fixedLabel = el("label");
  fixedLabel.append(fixed, " hide fixed blocks");
  const flipLabel = el("label");
  flipLabel.append(flip, " flip");
  box.replaceChildren(sectionLabel, field("dip", dip), field("dip dir.", ddir),
                      field("offset", offset), flipLabel, note, fixedLabel);

  function apply() {
    const n = planeNormal(state.dip, state.dipDirection);
    const s = state.flip ? 1 : -1;  // keep n·p <= offset (below the plane) unless flipped
    plane.normal.copy(n).multiplyScalar(s);
    plane.constant = -s * state.offset;
    const clip = state.on ? [plane] : [];
    for (const m of materials()) { m.clippingPlanes = clip; m.needsUpdate = true; }
    helper.visible = state.on && drag !== null;  // shown while it is dragged
    helper.position.copy(n).multiplyScalar(state.offset);
    helper.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), n);
    note.textContent = state.on ? `${Math.round(state.dip)}/${String(Math.round(
      ((state.dipDirection % 360) + 360) % 360)).padStart(3, "0")}, ${state.offset.toFixed(2)} m`
      : "";
    changed();
  }
  const read = () => {
    state.on = on.checked; state.flip = flip.checked;
    state.dip = Math.min(90, Math.max(0, +dip.value || 0));
    state.dipDirection = +ddir.value || 0;
    state.offset = +offset.value;
    apply();
  };
  for (const input of [on, dip, ddir, offset, flip]) input.addEventListener("input", read);
  fixed.addEventListener("change", () => { state.hideFixed = fixed.checked; hideFixed(fixed.checked); });

  // dragging: Shift moves the plane along its normal, Alt turns it
  canvas.addEventListener("pointerdown", (e) => {
    if (!state.on || !(e.shiftKey || e.altKey)) return;
    drag = { x: e.clientX, y: e.clientY, turn: e.altKey };
    controls.enabled = false;
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.turn) {
      state.dipDirection = (((state.dipDirection + 0.5 * dx) % 360) + 360) % 360;
      state.dip = Math.min(90, Math.max(0, state.dip + 0.3 * dy));
    } else {
      // the normal as seen on the page: moving the pointer along it moves the plane
      camera.updateMatrixWorld();
      const n = planeNormal(state.dip, state.dipDirection).transformDirection(camera.matrixWorldInverse);
      const len = Math.hypot(n.x, n.y) || 1;
      const h = Math.max(1, canvas.clientHeight);
      const perPixel = 2 * camera.position.distanceTo(controls.target)
        * Math.tan(camera.fov * RAD / 2) / h;
      state.offset = Math.min(half, Math.max(-half, state.offset
        + (dx * n.x - dy * n.y) / len * perPixel));
    }
    dip.value = state.dip.toFixed(1); ddir.value = state.dipDirection.toFixed(1);
    offset.value = state.offset;
    apply();
  });
  const end = () => { if (drag) { drag = null; controls.enabled = true; apply(); } };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);

  return {
    state,
    // set from code (tests, links): any of on, dip, dipDirection, offset, flip
    set(values) {
      Object.assign(state, values);
      on.checked = state.on; flip.checked = state.flip;
      dip.value = state.dip; ddir.value = state.dipDirection; offset.value = state.offset;
      apply();
    },
    setHideFixed(v) { fixed.checked = !!v; state.hideFixed = !!v; hideFixed(!!v); },
    refresh: apply,
    dispose() { scene.remove(helper); helper.geometry.dispose(); },
  };
}
