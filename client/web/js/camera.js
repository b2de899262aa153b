// The camera the page drives, and the model the server renders with
// (vastray/camera.py): in perspective, pixel (x, y) of a W x H image looks along
//   normalize(w + (2x/W - 1) tan(fov/2) (W/H) u + (1 - 2y/H) tan(fov/2) v),
// w = normalize(target - eye), u = normalize(w x up), v = u x w. Orthographic: every
// pixel looks along w, over the extent the perspective view has at the target (the same
// offsets times |target - eye|), so moving the eye closer zooms in, and nothing is cut
// off by the eye (the server starts the rays behind the model).

import { add, cross, dot, length, normalize, rotate, scale, sub } from "./vec.js";

export class Camera {
  constructor({ eye, target, up = [0, 1, 0], fov = 45, projection = "perspective" }) {
    this.eye = [...eye];
    this.target = [...target];
    this.up = [...up];
    this.fov = fov;
    this.projection = projection;
  }

  get orthographic() {
    return this.projection === "orthographic";
  }

  clone() {
    return new Camera(this);
  }

  toMessage(seq) {
    return { seq, eye: this.eye, target: this.target, up: this.up, fov: this.fov, projection: this.projection };
  }

  get distance() {
    return length(sub(this.target, this.eye));
  }

  basis(width, height) {
    const w = normalize(sub(this.target, this.eye));
    const u = normalize(cross(w, this.up));
    const v = cross(u, w);
    const t = Math.tan((this.fov * Math.PI) / 360);
    return { w, u, v, right: scale(u, (t * width) / height), top: scale(v, t) };
  }

  // The point at the target's depth (on the plane through it, facing the view) that
  // image point (x, y) of a width x height image shows, in either projection.
  pointAt(x, y, width, height) {
    const { right, top } = this.basis(width, height);
    const d = this.distance;
    return add(this.target, add(scale(right, (2 * x / width - 1) * d), scale(top, (1 - 2 * y / height) * d)));
  }

  // World point -> image pixel (x, y) and depth along the view axis (null behind the eye
  // in perspective; an orthographic view sees behind the eye too).
  project(point, width, height) {
    const { w, right, top } = this.basis(width, height);
    const d = sub(point, this.eye);
    const z = dot(d, w);
    const scaleBy = this.orthographic ? this.distance : z;
    if (!this.orthographic && z <= 1e-12) return null;
    const sx = dot(d, right) / (scaleBy * dot(right, right));
    const sy = dot(d, top) / (scaleBy * dot(top, top));
    return { x: ((sx + 1) * width) / 2, y: ((1 - sy) * height) / 2, depth: z };
  }

  // Orbit the eye about the target: yaw about the up vector, pitch about the right one
  // (stopping short of the poles, where up and the view would be parallel).
  orbit(yaw, pitch) {
    const up = normalize(this.up);
    let offset = sub(this.eye, this.target);
    offset = rotate(offset, up, yaw);
    const right = normalize(cross(offset, up));
    const angle = Math.acos(Math.max(-1, Math.min(1, dot(normalize(offset), up))));
    const limit = 0.01;
    const clamped = Math.max(limit, Math.min(Math.PI - limit, angle - pitch));
    offset = rotate(offset, right, angle - clamped);
    this.eye = add(this.target, offset);
  }

  // Move eye and target together, in image-plane units of the target's distance.
  pan(dx, dy, width, height) {
    const { u, v } = this.basis(width, height);
    const t = Math.tan((this.fov * Math.PI) / 360);
    const perPixel = (2 * t * this.distance) / height;
    const move = add(scale(u, -dx * perPixel), scale(v, dy * perPixel));
    this.eye = add(this.eye, move);
    this.target = add(this.target, move);
  }

  // Dolly towards the target (factor < 1) or away (> 1); towards a point under the
  // cursor when given, as CAD viewers zoom.
  zoom(factor, towards = null) {
    const pivot = towards ?? this.target;
    this.eye = add(pivot, scale(sub(this.eye, pivot), factor));
    if (towards) this.target = add(pivot, scale(sub(this.target, pivot), factor));
  }

  // Fly: forward/back along the view, sideways, up/down, by `step` world units.
  fly(forward, sideways, upwards, step) {
    const w = normalize(sub(this.target, this.eye));
    const u = normalize(cross(w, this.up));
    const v = normalize(this.up);
    const move = add(add(scale(w, forward * step), scale(u, sideways * step)), scale(v, upwards * step));
    this.eye = add(this.eye, move);
    this.target = add(this.target, move);
  }
}

// `d`, a direction of a y-up model, for a model whose up is `up`: turned by the shortest
// rotation that takes +y to `up` (as vastray/camera.py view_direction turns its view).
function turnFromY(d, up) {
  const u = normalize(up);
  const c = u[1];
  if (c < -1 + 1e-12) return [d[0], -d[1], -d[2]]; // upside down: half a turn about x
  const k = cross([0, 1, 0], u);
  return add(add(scale(d, c), cross(k, d)), scale(k, dot(k, d) / (1 + c)));
}

// The three-quarter view direction (from the model towards the eye), as the server's.
export function viewDirection(up = [0, 1, 0]) {
  return turnFromY([1, 0.7, 1.3], up);
}

// The standard views of CAD viewers: which way the eye lies from the model, and the
// screen's up, for a y-up model (front: +z, right: +x; the top view has the front at
// the bottom of the screen, the bottom view at the top). They turn with the model's up.
// In the order of the keys 1-7 and of vastray/camera.py's table.
export const STANDARD_VIEWS = {
  iso: { dir: [1, 0.7, 1.3], up: [0, 1, 0] },
  front: { dir: [0, 0, 1], up: [0, 1, 0] },
  back: { dir: [0, 0, -1], up: [0, 1, 0] },
  left: { dir: [-1, 0, 0], up: [0, 1, 0] },
  right: { dir: [1, 0, 0], up: [0, 1, 0] },
  top: { dir: [0, 1, 0], up: [0, 0, -1] },
  bottom: { dir: [0, -1, 0], up: [0, 0, 1] },
};

// A camera that shows the whole box from the standard view `name` (the three-quarter
// one by default) of a model whose up is `up`, as the server frames one
// (vastray/camera.py frame_bounds, step for step): the eye backs off until all eight
// corners project inside the image, with a margin of 8 % (orthographic: until the image
// spans them at every depth), as CAD viewers fit a view to the extents.
export function frameBounds(lo, hi, fov = 45, aspect = 16 / 9, up = [0, 1, 0], name = "iso",
  projection = "perspective") {
  const view = STANDARD_VIEWS[name];
  const centre = scale(add(lo, hi), 0.5);
  const dir = normalize(turnFromY(view.dir, up));
  const cameraUp = name === "iso" ? up : turnFromY(view.up, up); // (iso keeps the up as given)
  const w = scale(dir, -1);
  const u = normalize(cross(w, normalize(cameraUp)));
  const v = cross(u, w);
  const tanV = Math.tan((fov * Math.PI) / 360), tanH = tanV * aspect;
  let needed = -Infinity;
  for (let i = 0; i < 8; i++) {
    const p = sub([0, 1, 2].map((k) => ((i >> k) & 1 ? hi[k] : lo[k])), centre);
    let n = Math.max(Math.abs(dot(p, u)) / tanH, Math.abs(dot(p, v)) / tanV);
    if (projection !== "orthographic") n -= dot(p, w);
    needed = Math.max(needed, n);
  }
  const distance = Math.max(1.08 * needed, 1e-9 * Math.max(1, ...centre.map(Math.abs)), 0.5 * length(sub(hi, lo)));
  return new Camera({ eye: add(centre, scale(dir, distance)), target: centre, up: cameraUp, fov, projection });
}
