// The viewer page: streamed frames on a canvas, navigation, quality, stats, picking and
// measuring, parts, section planes, the accuracy readout and design reviews. It draws
// what the protocol gives it (docs/PROTOCOL.md); the server renders everything.

import { Api, ApiError } from "./api.js";
import { Camera, frameBounds } from "./camera.js";
import { Controls } from "./controls.js";
import { Overlay } from "./overlay.js";
import { Panels } from "./panels.js";
import { Stream } from "./stream.js";
import { add, dot, length, lerp, normalize, sub } from "./vec.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
// The credential: an API key (as `vastray serve` prints it) or a viewing/review token
// (`vt_…`). A key is kept for the tab, so the page still works at a URL without it (after
// leaving a review); a token stays in the URL it came with.
const fromUrl = params.get("key") ?? params.get("token");
const isToken = (c) => c.startsWith("vt_");
if (fromUrl && !isToken(fromUrl)) sessionStorage.setItem("vastray.key", fromUrl);
const credential = fromUrl ?? sessionStorage.getItem("vastray.key") ?? "";
const hasKey = credential !== "" && !isToken(credential);
// The join link of a review this tab started rides in the fragment of the presenter's
// link (a fragment never reaches the server); it is kept for the tab.
{
  const hash = new URLSearchParams(location.hash.slice(1));
  if (params.get("review") && hash.get("join")) {
    sessionStorage.setItem(`vastray.join.${params.get("review")}`, hash.get("join"));
    history.replaceState(null, "", location.pathname + location.search);
  }
}

class App {
  constructor() {
    this.api = new Api(location.origin, credential);
    this.canvas = $("view");
    this.ctx = this.canvas.getContext("2d");
    this.overlay = new Overlay($("overlay"));
    this.panels = new Panels(this);
    this.stream = null;
    this.model = null; // model info
    this.modelId = params.get("model");
    this.reviewId = params.get("review");
    this.camera = null; // the Camera the page drives
    this.seq = 0;
    this.sent = new Map(); // camera seq -> { camera, at }: what each frame shows, and when it was asked for
    this.shown = null; // { header, camera, rect }: the frame on the canvas
    this.bitmap = null; // its pixels, to draw again when the canvas changes size
    this.decoding = Promise.resolve();
    this.lastDrawn = 0; // the newest frame drawn: its number on its connection ...
    this.drawnGeneration = 0; // ... and that connection (Stream.generation)
    this.drawn = 0; // frames drawn since the page loaded
    this.welcomed = false;
    this.picking = new Map(); // pick id -> { mode, at }
    this.frameTimes = [];
    this.bytes = [];
    this.latency = null;
    this.pendingMax = 0;
    this.cameraQueued = false;
    this.viewport = { width: 960, height: 540 };
    this.limits = { max_pixels: 3840 * 2160 };
    this.picks = []; // measured points [{ position, hit }]
    this.following = true;
    this.role = "solo";
    this.controls = new Controls(this.canvas, {
      camera: () => this.#driveCamera(),
      onChange: () => this.cameraChanged(),
      onClick: (p) => this.#click(p),
      onDoubleClick: (p) => {
        this.#undoClick(); // (its first press was a click)
        this.#click(p, "focus");
      },
      onFrameAll: (name) => this.frameAll(name),
      onToggleProjection: () => this.toggleProjection(),
      flySpeed: () => (this.model ? 0.25 * length(sub(this.model.bounds[1], this.model.bounds[0])) : 1),
    });
    new ResizeObserver(() => this.#resize()).observe($("stage"));
  }

  async start() {
    this.panels.access({ hasKey, review: !!this.reviewId, storedKey: sessionStorage.getItem("vastray.key") });
    try {
      if (this.reviewId && !this.modelId) {
        const review = await this.api.review(this.reviewId);
        this.modelId = review.model;
      }
      await this.refreshModels();
    } catch (e) {
      this.banner(this.#explain(e), "error");
      const retry = !(e instanceof ApiError) || e.status === 0;
      this.#status(retry ? { state: "reconnecting", delay: 2000, quiet: true } : { state: "failed", quiet: true });
      if (retry) setTimeout(() => this.start(), 2000);
      return;
    }
    if (this.modelId) this.open(this.modelId);
  }

  #explain(e) {
    if (!(e instanceof ApiError)) return String(e);
    if (e.status === 0) return "The server cannot be reached; retrying…";
    if (e.status === 401) return `Access refused: ${e.message}. Open the URL the server printed (it carries the key) or a review link.`;
    if (e.status === 404) return `Not found: ${e.message}`;
    return e.message;
  }

  async refreshModels() {
    const models = await this.api.models();
    const select = $("model-select");
    select.replaceChildren(...models.map((m) => {
      const o = document.createElement("option");
      o.value = m.id;
      o.textContent = m.state === "ready" ? `${m.name} (${(m.triangles ?? 0).toLocaleString()} △)` : `${m.name} (building…)`;
      return o;
    }));
    if (!this.modelId && models.length) this.modelId = (models.find((m) => m.state === "ready") ?? models[0]).id;
    // A review token lists no models (the welcome names it); a model not listed is gone.
    if (this.modelId) {
      this.#selectModel({ id: this.modelId, name: this.reviewId ? this.modelId : `${this.modelId} (not found)` });
    }
    if (!models.length && !this.reviewId) {
      this.banner(hasKey ? "No models yet: drop a mesh on the page to upload and build one."
        : "No models to show with this link. Open the URL the server printed (it carries the key).");
    }
    return models;
  }

  // Shows `model` as the one chosen in the model picker (adding it when the list lacks it).
  #selectModel(model) {
    const select = $("model-select");
    let option = [...select.options].find((o) => o.value === model.id);
    if (!option) {
      option = document.createElement("option");
      option.value = model.id;
      select.appendChild(option);
    }
    if (model.triangles != null) option.textContent = `${model.name} (${model.triangles.toLocaleString()} △)`;
    else if (!option.textContent) option.textContent = model.name;
    select.value = model.id;
  }

  open(modelId) {
    if (this.stream) this.stream.close();
    this.modelId = modelId;
    this.model = null;
    this.camera = null;
    this.shown = null;
    this.bitmap?.close();
    this.bitmap = null;
    this.welcomed = false;
    this.sent.clear();
    this.picks = [];
    this.picking.clear();
    this.overlay.clear();
    this.panels.pickResult(null);
    const query = new URLSearchParams(location.search);
    query.set("model", modelId);
    history.replaceState(null, "", `?${query}`);
    const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/stream`;
    this.stream = new Stream({
      url: wsUrl, token: credential, model: modelId, review: this.reviewId, viewport: this.viewport,
      quality: this.panels.quality(), name: sessionStorage.getItem("vastray.name"),
    });
    const s = this.stream;
    s.addEventListener("status", (e) => this.#status(e.detail));
    s.addEventListener("welcome", (e) => this.#welcome(e.detail));
    s.addEventListener("frame", (e) => this.#frame(e.detail));
    s.addEventListener("stats", (e) => this.panels.serverStats(e.detail));
    s.addEventListener("error", (e) => this.#serverError(e.detail));
    s.addEventListener("pick_result", (e) => this.#picked(e.detail));
    s.addEventListener("job", (e) => this.panels.job(e.detail));
    s.addEventListener("accuracy", (e) => this.panels.accuracy(e.detail));
    s.addEventListener("closing", (e) => {
      this.lostReason = e.detail.reason; // said again while the page tries to reconnect
      this.banner(`The server is closing the connection: ${e.detail.reason}`);
    });
    s.addEventListener("message", (e) => this.panels.reviewMessage(e.detail));
    s.open();
  }

  #welcome(w) {
    const reconnected = this.welcomed;
    this.welcomed = true;
    this.model = w.model;
    this.limits = w.limits;
    this.role = w.review?.role ?? "solo";
    this.camera = new Camera(w.camera);
    this.showProjection(this.camera);
    this.seq = Math.max(this.seq, w.camera.seq);
    this.#selectModel(w.model);
    this.panels.welcome(w, { reconnected });
    this.banner(null);
    $("job").hidden = true;
  }

  #status({ state, reason, code, delay, resumed, quiet = false }) {
    const badge = $("status");
    badge.dataset.state = state;
    const text = {
      connecting: "connecting…",
      connected: resumed ? "connected (resumed)" : "connected",
      reconnecting: `reconnecting in ${((delay ?? 0) / 1000).toFixed(1)} s…`,
      failed: "disconnected",
    }[state];
    badge.textContent = text;
    // The picture stays, dimmed, while it is not live.
    $("stage").dataset.live = String(state === "connected");
    if (state === "connected") this.lostReason = null;
    if (quiet) return; // the caller says why in the banner
    if (state === "reconnecting") {
      this.lostReason = reason || this.lostReason;
      this.banner(`Connection lost${this.lostReason ? ` (${this.lostReason})` : ""}; reconnecting by itself…`);
    }
    if (state === "failed") this.banner(this.#closeReason(code, reason), "error");
  }

  #closeReason(code, reason) {
    if (code === 4401) return `Access refused: ${reason}. Open the URL the server printed, or ask for a new link.`;
    if (code === 4403) return `This link does not give access to this model: ${reason}`;
    if (code === 4404) return `The model is gone: ${reason}. Pick another one.`;
    return `The server refused the view: ${reason}`;
  }

  #serverError(e) {
    if (e.fatal) this.banner(e.message, "error");
    else this.notice(e.message);
  }

  // The banner says what holds until it changes (a lost connection, an error; null:
  // nothing); a notice shows for a few seconds over it, then the banner is back.
  banner(text, kind = "warn") {
    this.lasting = text ? { text, kind } : null;
    this.#showBanner();
  }

  notice(text) {
    this.noticeText = text;
    this.#showBanner();
    clearTimeout(this.noticeTimer);
    this.noticeTimer = setTimeout(() => {
      this.noticeText = null;
      this.#showBanner();
    }, 4000);
  }

  #showBanner() {
    const shown = this.noticeText ? { text: this.noticeText, kind: "notice" } : this.lasting;
    const b = $("banner");
    b.hidden = !shown;
    b.textContent = shown?.text ?? "";
    b.dataset.kind = shown?.kind ?? "warn";
  }

  // -- camera ---------------------------------------------------------------------------

  #driveCamera() {
    if (this.reviewId && this.following && this.role !== "presenter") {
      // Taking the controls as a follower: go free, from where the presenter is.
      this.panels.setFollow(false);
    }
    return this.camera ?? new Camera({ eye: [1, 1, 1], target: [0, 0, 0] });
  }

  cameraChanged() {
    if (!this.camera || this.cameraQueued) return;
    this.cameraQueued = true;
    requestAnimationFrame(() => {
      this.cameraQueued = false;
      this.seq += 1;
      this.sent.set(this.seq, { camera: this.camera.clone(), at: performance.now() });
      if (this.sent.size > 600) this.sent.delete(this.sent.keys().next().value);
      this.stream?.send({ type: "camera", ...this.camera.toMessage(this.seq) });
    });
    this.showProjection(this.camera);
  }

  // A handover says where the shared view is: this page's next camera must be newer
  // than it, even before a frame of the shared view has arrived.
  takeSharedCamera(message) {
    if (!message) return;
    this.camera = new Camera(message);
    this.seq = Math.max(this.seq, message.seq);
    this.showProjection(this.camera);
  }

  setCamera(message) {
    this.camera = new Camera(message);
    this.cameraChanged();
  }

  // The whole model from a standard view (iso: the three-quarter one), upright about its
  // up. Navigation: a follower goes free, as when it drags.
  frameAll(name = "iso") {
    if (!this.model) return;
    this.#driveCamera();
    const [lo, hi] = this.model.bounds;
    this.camera = frameBounds(lo, hi, this.camera?.fov ?? 45, this.viewport.width / this.viewport.height,
      this.model.up ?? [0, 1, 0], name, this.camera?.projection);
    this.cameraChanged();
  }

  // Perspective or orthographic (parallel) projection, keeping what the view shows at the
  // target: the target's scale stays, the rest of the model stops shrinking with depth.
  setProjection(projection) {
    if (!this.model) return;
    const camera = this.#driveCamera().clone();
    camera.projection = projection;
    this.camera = camera;
    this.cameraChanged();
  }

  toggleProjection() {
    this.setProjection(this.camera?.orthographic ? "perspective" : "orthographic");
  }

  // Turns the view to a point (a double click), so that orbits and zooms go about it, as
  // CAD viewers focus: in perspective the eye stays and the view turns, in 0.3 s; an
  // orthographic view keeps its direction and slides over, since its rays start behind
  // the model and the point may lie behind the eye. Any other move of the camera stops
  // the turn where it is.
  focus(point) {
    if (!this.model) return;
    const camera = this.#driveCamera();
    const from = [...camera.target];
    const offset = sub(camera.eye, camera.target);
    const start = performance.now();
    let expected = [camera.eye, camera.target]; // (moves give the camera new arrays)
    const step = () => {
      if (this.camera !== camera || camera.eye !== expected[0] || camera.target !== expected[1]) return;
      const t = Math.min(1, (performance.now() - start) / 300);
      const eased = t * t * (3 - 2 * t);
      camera.target = lerp(from, point, eased);
      if (camera.orthographic) camera.eye = add(camera.target, offset);
      expected = [camera.eye, camera.target];
      this.cameraChanged();
      if (t < 1) requestAnimationFrame(step);
    };
    step();
  }

  // The projection button says which projection the view (or the picture shown) has.
  showProjection(camera) {
    const b = $("projection");
    const ortho = Boolean(camera?.orthographic);
    b.setAttribute("aria-pressed", String(ortho));
    b.textContent = ortho ? "Ortho" : "Persp";
  }

  // Which way is up in the model: the view is framed upright about it at once, and with
  // the API key it is saved with the model, so everyone's next view of it starts upright.
  async setUp(up) {
    if (!this.model) return;
    const model = this.model;
    model.up = up;
    this.frameAll();
    const saved = await this.#saveWithModel(model, { up }, "Up is");
    if (!saved) return;
    model.up = saved.up;
    this.notice(`Saved with ${saved.name}: views of it start with this side up.`);
  }

  // The length unit of the model's coordinates ("" for none): measurements are given in
  // it, and with the API key it is saved with the model for everyone's next view.
  async setUnits(units) {
    if (!this.model) return;
    const model = this.model;
    model.units = units || null;
    this.panels.unitsChanged();
    this.redrawOverlay();
    const saved = await this.#saveWithModel(model, { units }, "Units are");
    if (!saved) return;
    model.units = saved.units;
    this.notice(saved.units ? `Saved with ${saved.name}: its lengths are in ${saved.units}.`
      : `Saved with ${saved.name}: its units are not said.`);
  }

  // A model setting saved with the model (PATCH), which needs the API key: the saved
  // model, or null when it holds on this page only (and a notice says why).
  async #saveWithModel(model, changes, what) {
    if (!hasKey) {
      this.notice(`${what} changed on this page only: saving with the model needs the API key.`);
      return null;
    }
    try {
      return await this.api.updateModel(model.id, changes);
    } catch (e) {
      this.notice(`${what} changed on this page only: ${e.message}`);
      return null;
    }
  }

  // -- frames ---------------------------------------------------------------------------

  #frame(header) {
    // Decode in order, draw only what is newer than what is shown (frame numbers start
    // again on every connection), acknowledge after drawing.
    this.decoding = this.decoding.then(async () => {
      const bitmap = await createImageBitmap(header.image);
      if (header.screenshot) {
        this.#saveScreenshot(header.image);
        bitmap.close();
        this.stream?.ack(header.frame, header.generation);
        return;
      }
      const newer = header.generation > this.drawnGeneration ||
        (header.generation === this.drawnGeneration && header.frame > this.lastDrawn);
      if (!newer) {
        bitmap.close();
        this.stream?.ack(header.frame, header.generation);
        return;
      }
      this.drawnGeneration = header.generation;
      this.lastDrawn = header.frame;
      this.bitmap?.close();
      this.bitmap = bitmap;
      // The camera this frame shows: as the server says (a follower did not send it).
      const camera = header.stats?.camera ? new Camera(header.stats.camera)
        : this.sent.get(header.cameraSeq)?.camera ?? this.shown?.camera ?? this.camera;
      const follower = this.following && this.role === "follower";
      this.shown = { header, camera, rect: this.#fit(header) };
      this.#paint();
      if (follower) this.camera = camera.clone();
      this.showProjection(this.camera);
      // The next camera this page sends must be newer than any shown (a presenter's, a
      // saved view's), or the server would take it for an old one.
      this.seq = Math.max(this.seq, header.cameraSeq);
      this.#measureClient(header, !follower);
      this.redrawOverlay();
      this.panels.frame(header);
      this.drawn += 1;
      const data = this.canvas.dataset;
      data.frames = String(this.drawn);
      data.cameraSeq = String(header.cameraSeq);
      data.moving = String(header.moving);
      data.final = String(header.final);
      data.complete = String(header.complete);
      this.stream?.ack(header.frame, header.generation);
    }).catch((e) => console.error("frame", e));
  }

  // Draws the frame shown (again, after the canvas changed size: that clears it).
  #paint() {
    const { header } = this.shown;
    const rect = this.#fit(header);
    this.shown.rect = rect;
    this.ctx.fillStyle = "#202329";
    this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    this.ctx.imageSmoothingEnabled = true;
    this.ctx.imageSmoothingQuality = header.moving ? "low" : "high";
    this.ctx.drawImage(this.bitmap, rect.x, rect.y, rect.width, rect.height);
  }

  // Where a frame goes on the canvas: as large as fits, its aspect kept (a review's
  // frames have the presenter's aspect, not this window's).
  #fit(header) {
    const fullW = header.width / header.scale, fullH = header.height / header.scale;
    const s = Math.min(this.canvas.width / fullW, this.canvas.height / fullH);
    const width = fullW * s, height = fullH * s;
    return { x: (this.canvas.width - width) / 2, y: (this.canvas.height - height) / 2, width, height, fullW, fullH };
  }

  #measureClient(header, ownCamera) {
    const now = performance.now();
    this.frameTimes.push(now);
    this.bytes.push([now, header.image.size]);
    while (this.frameTimes.length && now - this.frameTimes[0] > 2000) this.frameTimes.shift();
    while (this.bytes.length && now - this.bytes[0][0] > 2000) this.bytes.shift();
    // Input to frame: from sending a camera to drawing the first frame that shows it.
    const asked = ownCamera ? this.sent.get(header.cameraSeq) : null;
    if (asked && !asked.answered) {
      asked.answered = true;
      this.latency = now - asked.at;
    }
    const span = this.frameTimes.length > 1 ? (now - this.frameTimes[0]) / 1000 : 1;
    this.panels.clientStats({
      fps: this.frameTimes.length > 1 ? (this.frameTimes.length - 1) / span : 0,
      latency: this.latency,
      mbit: (8 * this.bytes.reduce((a, [, b]) => a + b, 0)) / Math.max(span, 0.5) / 1e6,
    });
  }

  redrawOverlay() {
    if (!this.shown) return;
    const { camera, rect } = this.shown;
    const css = this.canvas.clientWidth / this.canvas.width; // canvas pixels -> CSS pixels
    const project = (p) => {
      const q = camera.project(p, rect.fullW, rect.fullH);
      if (!q) return null;
      return { x: (rect.x + (q.x * rect.width) / rect.fullW) * css, y: (rect.y + (q.y * rect.height) / rect.fullH) * css };
    };
    // A segment in view: in perspective, the part in front of the eye (by a thousandth of
    // the target's distance), so a box the eye is in still shows its edges ahead.
    const w = normalize(sub(camera.target, camera.eye));
    const near = 1e-3 * camera.distance;
    const segment = (a, b) => {
      if (!camera.orthographic) {
        const za = dot(sub(a, camera.eye), w) - near, zb = dot(sub(b, camera.eye), w) - near;
        if (za < 0 && zb < 0) return null;
        if (za < 0) a = lerp(a, b, za / (za - zb));
        else if (zb < 0) b = lerp(a, b, za / (za - zb));
      }
      const p = project(a), q = project(b);
      return p && q ? [p, q] : null;
    };
    this.overlay.draw(project, { picks: this.picks, pointers: this.panels.pointers, notes: this.panels.annotations,
      box: this.panels.sectionBox(), segment, units: this.model?.units });
  }

  #resize() {
    const dpr = window.devicePixelRatio || 1;
    const stage = $("stage");
    let width = Math.max(16, Math.round(stage.clientWidth * dpr));
    let height = Math.max(16, Math.round(stage.clientHeight * dpr));
    const budget = this.limits.max_pixels ?? 3840 * 2160;
    if (width * height > budget) {
      const s = Math.sqrt(budget / (width * height));
      width = Math.floor(width * s);
      height = Math.floor(height * s);
    }
    this.canvas.width = width;
    this.canvas.height = height;
    this.viewport = { width, height };
    if (this.shown) {
      this.#paint();
      this.redrawOverlay();
    }
    clearTimeout(this.resizeTimer);
    this.resizeTimer = setTimeout(() => {
      this.stream?.send({ type: "viewport", width, height, device_pixel_ratio: dpr });
      if (this.stream) this.stream.viewport = { width, height };
    }, 100);
  }

  // -- picking and measuring -------------------------------------------------------------

  // A pick at a point of the canvas (CSS pixels), answered as `mode` says: "measure" or
  // "pointer" (a click, as the review panel's pointer box says), "focus" (a double click).
  #click({ x, y }, mode = this.panels.pointerMode ? "pointer" : "measure") {
    if (!this.shown || !this.stream) return;
    const { camera, rect, header } = this.shown;
    // CSS pixels -> canvas pixels -> pixels of the frame's full-size image.
    const c = this.canvas.width / this.canvas.clientWidth;
    const px = ((x * c - rect.x) * rect.fullW) / rect.width;
    const py = ((y * c - rect.y) * rect.fullH) / rect.height;
    if (px < 0 || py < 0 || px > rect.fullW || py > rect.fullH) return;
    this.pickCounter = (this.pickCounter ?? 0) + 1;
    const id = `p${this.pickCounter}`;
    // Each answer is handled as its click asked, whatever was clicked since.
    this.picking.set(id, { mode, at: performance.now() });
    // What a double click's first press undoes: the measurement as it was before.
    this.lastClick = { id, mode, picks: [...this.picks], shown: this.panels.lastPickResult };
    const sent = this.stream.send({ type: "pick", id, points: [[px, py]],
      camera: camera.toMessage(header.cameraSeq), width: Math.round(rect.fullW), height: Math.round(rect.fullH) });
    if (!sent) {
      this.picking.delete(id);
      this.notice("Not connected: pick again once the status says connected.");
    }
  }

  // Takes back the last click (the first press of a double click): its pick's answer,
  // if still to come, changes nothing, and a measurement is as it was before it.
  #undoClick() {
    const last = this.lastClick;
    this.lastClick = null;
    if (!last) return;
    this.picking.delete(last.id);
    if (last.mode !== "measure") return; // (a pointer may stay where the first press put it)
    this.picks = last.picks;
    this.panels.pickResult(...(last.shown ?? [null]));
    this.redrawOverlay();
  }

  #picked(result) {
    const asked = this.picking.get(result.id);
    if (!asked) return; // not this page's (or from before the model changed)
    this.picking.delete(result.id);
    const hit = result.hits[0];
    const elapsed = performance.now() - asked.at;
    if (asked.mode === "focus") {
      if (hit?.hit) this.focus(hit.position);
      else this.notice("Nothing there to turn to: double-click the model.");
      return;
    }
    if (asked.mode === "pointer") {
      // Pointing at nothing takes one's pointer away.
      this.stream.send({ type: "pointer", position: hit?.hit ? hit.position : null });
      return;
    }
    if (!hit?.hit) {
      this.panels.pickResult(null, elapsed, result.milliseconds);
      return;
    }
    if (this.picks.length >= 2) this.picks = [];
    this.picks.push(hit);
    const measured = this.picks.length === 2 ? this.picks : null;
    this.panels.pickResult(hit, elapsed, result.milliseconds, measured);
    this.redrawOverlay();
  }

  clearMeasure() {
    this.picks = [];
    this.panels.pickResult(null);
    this.redrawOverlay();
  }

  // -- screenshots -----------------------------------------------------------------------

  screenshot() {
    const sent = this.stream?.send({ type: "screenshot", id: `s${Date.now()}` });
    this.notice(sent ? "Screenshot: waiting for the finished view…"
      : "Not connected: take the screenshot once the status says connected.");
  }

  // The finished view, lossless as the server rendered it, with the marks drawn over it
  // (measurements, notes, pointers, a section box's edges) burnt in, as review tools'
  // snapshots have them.
  async #saveScreenshot(blob) {
    let marked = false;
    try {
      const withMarks = await this.#burnInMarks(blob);
      marked = withMarks !== blob;
      blob = withMarks;
    } catch (e) {
      console.error("screenshot marks", e); // the view without them, rather than nothing
    }
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `vastray-${this.model?.name ?? "view"}-${new Date().toISOString().replace(/[:.]/g, "-")}.png`;
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
    this.notice(marked ? "Screenshot saved, with the marks drawn over the view." : "Screenshot saved.");
  }

  async #burnInMarks(blob) {
    const marks = this.overlay.image();
    if (!marks || !this.shown) return blob;
    const view = await createImageBitmap(blob);
    const canvas = document.createElement("canvas");
    canvas.width = view.width;
    canvas.height = view.height;
    const ctx = canvas.getContext("2d");
    ctx.drawImage(view, 0, 0);
    view.close();
    const url = URL.createObjectURL(marks);
    try {
      const svg = new Image();
      svg.src = url;
      await svg.decode();
      // Overlay CSS pixels -> canvas pixels -> the image's pixels (redrawOverlay's
      // mapping, inverted).
      const { rect } = this.shown;
      const css = this.canvas.clientWidth / this.canvas.width;
      const sx = canvas.width / (rect.width * css), sy = canvas.height / (rect.height * css);
      ctx.setTransform(sx, 0, 0, sy, -rect.x * sx * css, -rect.y * sy * css);
      ctx.drawImage(svg, 0, 0, svg.width, svg.height);
    } finally {
      URL.revokeObjectURL(url);
    }
    return await new Promise((resolve) => canvas.toBlob(resolve, "image/png"));
  }

  // -- uploads ---------------------------------------------------------------------------

  async upload(file) {
    if (!hasKey) {
      this.banner("Uploading needs the API key: open the URL the server printed (it carries the key).", "error");
      return;
    }
    $("job").hidden = false;
    $("job-label").textContent = `uploading ${file.name}`;
    const bar = $("job-progress");
    // A named layout (the server's vastray/layouts.py says what each sets); "balanced",
    // the default, registers the upload as it comes.
    const layout = $("upload-layout").value;
    const options = layout === "balanced" ? null : { layout };
    try {
      const up = await this.api.upload(file, (f) => { bar.value = 100 * f; }, { register: !options });
      const created = options ? await this.api.register(up.id, options) : up.created;
      if (created?.job) {
        $("job-label").textContent = `building ${created.model.name}`;
        await this.api.followJob(created.job.id, (job) => this.panels.job(job));
      }
      await this.refreshModels();
      this.open(created.model.id);
    } catch (e) {
      this.banner(`${file.name}: ${this.#explain(e)}`, "error");
      $("job").hidden = true;
    }
  }

}

const app = new App();
window.vastray = app; // for the console and the browser tests
app.start();
