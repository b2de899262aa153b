// What the page draws over the streamed image, pinned to 3D points: picked points and
// the measured distance, review pointers, annotations. Positions are projected with the
// camera of the frame on the canvas, so marks stay on the picture as the camera moves.

import { distance, formatLength, lerp } from "./vec.js";

const NS = "http://www.w3.org/2000/svg";
// What the overlay's stylesheet sets on its marks (viewer.css, #overlay).
const STYLED = ["fill", "stroke", "stroke-width", "stroke-dasharray", "opacity", "font-family", "font-size",
  "font-weight", "paint-order"];

export class Overlay {
  constructor(svg) {
    this.svg = svg;
  }

  clear() {
    this.svg.replaceChildren();
  }

  // The marks as a standalone SVG image (a blob), in the overlay's CSS pixels, with the
  // page's styles written into each element, since a stylesheet does not travel with
  // it; null when there are none.
  image() {
    if (!this.svg.childElementCount) return null;
    const copy = this.svg.cloneNode(true);
    const shown = this.svg.querySelectorAll("*"), copied = copy.querySelectorAll("*");
    shown.forEach((el, i) => {
      const style = getComputedStyle(el);
      copied[i].setAttribute("style", STYLED.map((p) => `${p}:${style.getPropertyValue(p)}`).join(";"));
    });
    const { width, height } = this.svg.getBoundingClientRect();
    copy.setAttribute("xmlns", NS);
    copy.setAttribute("width", String(width));
    copy.setAttribute("height", String(height));
    copy.removeAttribute("id");
    return new Blob([new XMLSerializer().serializeToString(copy)], { type: "image/svg+xml" });
  }

  #el(name, attrs, text = null) {
    const e = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== null) e.textContent = text;
    this.svg.appendChild(e);
    return e;
  }

  // `box`: [lo, hi] of a section box, drawn as its twelve edges; `segment(a, b)`: the
  // screen points of the part of a 3D segment in view, or null.
  draw(project, { picks = [], pointers = new Map(), notes = [], box = null, segment = null, units = null }) {
    this.clear();
    if (box && segment) this.#box(box, segment);
    const points = picks.map((p) => project(p.position));
    if (points.length === 2 && points[0] && points[1]) {
      const [a, b] = points;
      this.#el("line", { x1: a.x, y1: a.y, x2: b.x, y2: b.y });
      const mid = project(lerp(picks[0].position, picks[1].position, 0.5));
      if (mid) this.#el("text", { x: mid.x + 6, y: mid.y - 6, class: "distance" },
        formatLength(distance(picks[0].position, picks[1].position)) + (units ? ` ${units}` : ""));
    }
    points.forEach((p, i) => {
      if (!p) return;
      this.#el("circle", { cx: p.x, cy: p.y, r: 5, class: "marker" });
      this.#el("text", { x: p.x + 8, y: p.y + 4 }, String.fromCharCode(65 + i));
    });
    for (const [, pointer] of pointers) {
      const p = pointer.position && project(pointer.position);
      if (!p) continue;
      this.#el("path", { d: `M${p.x} ${p.y} l -6 -14 l 12 0 z`, class: "pointer" });
      this.#el("text", { x: p.x + 8, y: p.y - 8, class: "pointer-label" }, pointer.name ?? "pointer");
    }
    for (const note of notes) {
      const p = project(note.position);
      if (!p) continue;
      this.#el("rect", { x: p.x - 5, y: p.y - 5, width: 10, height: 10, class: "note" });
      this.#el("text", { x: p.x + 8, y: p.y + 4, class: "note-label" }, note.text);
    }
  }

  #box([lo, hi], segment) {
    const corner = (i) => [0, 1, 2].map((k) => ((i >> k) & 1 ? hi[k] : lo[k]));
    let d = "";
    for (let i = 0; i < 8; i++) {
      for (const bit of [1, 2, 4]) {
        if (i & bit) continue; // each edge once: from the corner with that coordinate low
        const s = segment(corner(i), corner(i | bit));
        if (s) d += `M${s[0].x} ${s[0].y}L${s[1].x} ${s[1].y}`;
      }
    }
    if (d) this.#el("path", { d, class: "section-box" });
  }
}
