// Mouse, touch and keyboard to camera moves, the way CAD viewers do it:
//   left drag: orbit   right drag / shift+left / two fingers: pan
//   wheel: zoom towards the cursor   pinch: zoom
//   W A S D: fly, Q E: down and up (shift: faster; W S zoom an orthographic view)
//   F: frame the model
//   arrows: orbit (shift: pan)   + -: zoom
//   1-7: the standard views (iso, front, back, left, right, top, bottom)   O: projection
// A click (press and release without moving) is a pick, not a move; a double click
// turns the view to the point under it, which orbits and zooms then go about.

import { STANDARD_VIEWS } from "./camera.js";

const ORBIT_PER_PIXEL = 0.006; // radians
const CLICK_SLOP = 4; // pixels a press may move and still be a click
const WHEEL_STEP = 1.0015; // zoom factor per wheel pixel
const DOUBLE_CLICK_MS = 300;
const DOUBLE_CLICK_SLOP = 6; // pixels between the two clicks of a double click
const ORTHO_ZOOM_RATE = Math.LN2; // W in an orthographic view: half the extent per second
const VIEW_KEYS = Object.keys(STANDARD_VIEWS); // keys 1-7
// The arrow keys as drags: the direction, in pixels of an orbit (5.2 degrees) or a
// twentieth of the view's height of a pan; + and - zoom by a fifth.
const ARROW_DRAGS = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] };
const ARROW_ORBIT_PIXELS = 15;
const ARROW_PAN = 1 / 20;
const KEY_ZOOM = 0.8;

export class Controls {
  constructor(element, { camera, onChange, onClick, onDoubleClick, onFrameAll, onToggleProjection, flySpeed }) {
    // onClick(point), onDoubleClick(point): at CSS pixels of the element; a double click
    // comes after the click of its first press.
    // onFrameAll(view): the model framed from a standard view (F: "iso")
    // onToggleProjection(): perspective <-> orthographic (O)
    this.element = element;
    this.camera = camera; // () => the Camera to change
    this.onChange = onChange;
    this.onClick = onClick;
    this.onDoubleClick = onDoubleClick;
    this.lastClick = null;
    this.onFrameAll = onFrameAll;
    this.onToggleProjection = onToggleProjection;
    this.flySpeed = flySpeed; // () => world units per second
    this.pointers = new Map();
    this.keys = new Set();
    this.lastFly = 0;
    this.press = null;
    element.addEventListener("pointerdown", (e) => this.#down(e));
    element.addEventListener("pointermove", (e) => this.#move(e));
    element.addEventListener("pointerup", (e) => this.#up(e));
    element.addEventListener("pointercancel", (e) => this.#up(e));
    element.addEventListener("wheel", (e) => this.#wheel(e), { passive: false });
    element.addEventListener("contextmenu", (e) => e.preventDefault());
    window.addEventListener("keydown", (e) => this.#key(e, true));
    window.addEventListener("keyup", (e) => this.#key(e, false));
    window.addEventListener("blur", () => this.keys.clear()); // keys released elsewhere
    // Two clicks on the view with a click elsewhere between them are not a double click.
    window.addEventListener("pointerdown", (e) => {
      if (e.target !== element) this.lastClick = null;
    }, true);
  }

  size() {
    const r = this.element.getBoundingClientRect();
    return { width: r.width, height: r.height, left: r.left, top: r.top };
  }

  #down(e) {
    this.element.setPointerCapture(e.pointerId);
    this.pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    this.press = this.pointers.size === 1 ? { x: e.clientX, y: e.clientY, button: e.button, moved: false } : null;
  }

  #move(e) {
    const last = this.pointers.get(e.pointerId);
    if (!last) return;
    const dx = e.clientX - last.x, dy = e.clientY - last.y;
    this.pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    if (this.press && Math.hypot(e.clientX - this.press.x, e.clientY - this.press.y) > CLICK_SLOP) {
      this.press.moved = true;
    }
    if (this.press && !this.press.moved) return;
    const camera = this.camera();
    const { width, height } = this.size();
    if (this.pointers.size >= 2) {
      this.#pinch(e.pointerId, dx, dy);
    } else if (e.buttons & 2 || e.buttons & 4 || e.shiftKey) {
      camera.pan(dx, dy, width, height);
    } else if (e.buttons & 1 || e.pointerType === "touch") {
      camera.orbit(-dx * ORBIT_PER_PIXEL, -dy * ORBIT_PER_PIXEL);
    } else {
      return;
    }
    this.onChange();
  }

  #pinch(id, dx, dy) {
    const camera = this.camera();
    const [a, b] = [...this.pointers.values()];
    const { width, height } = this.size();
    const spread = Math.hypot(a.x - b.x, a.y - b.y);
    const before = this.spread ?? spread;
    this.spread = spread;
    camera.pan(dx / 2, dy / 2, width, height);
    if (before > 0 && spread > 0) camera.zoom(before / spread);
  }

  #up(e) {
    this.pointers.delete(e.pointerId);
    if (this.pointers.size < 2) this.spread = undefined;
    const press = this.press;
    this.press = null;
    // A click of the main button (or a tap) picks; a right click is the start of a pan.
    if (press && !press.moved && press.button === 0 && e.type === "pointerup") {
      const { left, top } = this.size();
      this.#clicked({ x: e.clientX - left, y: e.clientY - top, button: press.button, shift: e.shiftKey });
    }
  }

  // A click is a click at once (a pick's answer within the 0.25 s that selection
  // feedback has); a second one close by in time and place makes it a double click,
  // which takes the first one's place (onDoubleClick undoes what it did).
  #clicked(at) {
    const first = this.lastClick;
    const now = performance.now();
    if (this.onDoubleClick && first && now - first.time < DOUBLE_CLICK_MS &&
        Math.hypot(at.x - first.at.x, at.y - first.at.y) <= DOUBLE_CLICK_SLOP) {
      this.lastClick = null;
      this.onDoubleClick(at);
      return;
    }
    this.lastClick = { at, time: now };
    this.onClick(at);
  }

  // Zooms towards the cursor, as CAD viewers do: about the point at the target's depth
  // under it, which stays under the cursor (the target moves towards it too, so orbits
  // then go about what one zoomed in on).
  #wheel(e) {
    e.preventDefault();
    const delta = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaY;
    const camera = this.camera();
    const { width, height, left, top } = this.size();
    const towards = width > 0 && height > 0 ? camera.pointAt(e.clientX - left, e.clientY - top, width, height) : null;
    camera.zoom(Math.pow(WHEEL_STEP, delta), towards);
    this.onChange();
  }

  #key(e, down) {
    const t = e.target;
    if (t instanceof HTMLInputElement || t instanceof HTMLTextAreaElement || t instanceof HTMLSelectElement ||
        t?.isContentEditable) return; // typing, not flying
    if (down && e.key in ARROW_DRAGS && (t === this.element || t === document.body)) {
      // The arrow keys do what a short drag does (shift: pan), so the view can be turned
      // without a mouse; on the view or the page itself, not in a panel they scroll.
      e.preventDefault();
      const [dx, dy] = ARROW_DRAGS[e.key];
      const camera = this.camera();
      if (e.shiftKey) {
        const { width, height } = this.size();
        camera.pan(dx * ARROW_PAN * height, dy * ARROW_PAN * height, width, height);
      } else {
        camera.orbit(-dx * ARROW_ORBIT_PIXELS * ORBIT_PER_PIXEL, -dy * ARROW_ORBIT_PIXELS * ORBIT_PER_PIXEL);
      }
      this.onChange();
      return;
    }
    const k = e.key.toLowerCase();
    if (k.length !== 1) return;
    if (down && (e.ctrlKey || e.metaKey || e.altKey)) return; // the browser's shortcuts (Ctrl+F, Ctrl+S, ...)
    if (down && (k === "+" || k === "=" || k === "-")) {
      this.camera().zoom(k === "-" ? 1 / KEY_ZOOM : KEY_ZOOM);
      this.onChange();
      return;
    }
    if (down && k === "f") {
      if (!e.repeat) this.onFrameAll("iso");
      return;
    }
    if (down && k >= "1" && k <= "7") {
      if (!e.repeat) this.onFrameAll(VIEW_KEYS[Number(k) - 1]);
      return;
    }
    if (down && k === "o") {
      if (!e.repeat) this.onToggleProjection();
      return;
    }
    if (!"wasdqe".includes(k)) return;
    if (down) this.keys.add(k);
    else this.keys.delete(k);
    this.shift = e.shiftKey;
    // One fly loop while keys are held, however many keys and key repeats there are.
    if (down && !this.flying) {
      this.flying = true;
      this.lastFly = performance.now();
      requestAnimationFrame(() => this.#fly());
    }
  }

  #fly() {
    if (this.keys.size === 0) {
      this.flying = false;
      return;
    }
    const now = performance.now();
    const dt = Math.min(0.1, (now - this.lastFly) / 1000);
    this.lastFly = now;
    const k = this.keys;
    const forward = (k.has("w") ? 1 : 0) - (k.has("s") ? 1 : 0);
    const sideways = (k.has("d") ? 1 : 0) - (k.has("a") ? 1 : 0);
    const upwards = (k.has("e") ? 1 : 0) - (k.has("q") ? 1 : 0);
    const faster = this.shift ? 4 : 1;
    const camera = this.camera();
    if (camera.orthographic && forward) {
      // Flying along parallel rays would show nothing new: W and S zoom instead, as in
      // CAD viewers, at a rate that is the same at every scale.
      camera.zoom(Math.exp(-forward * ORTHO_ZOOM_RATE * dt * faster));
    }
    camera.fly(camera.orthographic ? 0 : forward, sideways, upwards, this.flySpeed() * dt * faster);
    this.onChange();
    requestAnimationFrame(() => this.#fly());
  }
}
