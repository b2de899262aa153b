// The side panels: quality (with the live accuracy readout), stats, pick & measure,
// parts, section planes, and the review (participants, follow, pointer, annotations,
// saved views).

import { dot, formatLength, length, normalize, sub } from "./vec.js";

const $ = (id) => document.getElementById(id);

function li(text, { title = "", onClick = null, extra = null } = {}) {
  const item = document.createElement("li");
  const label = document.createElement("span");
  label.textContent = text;
  item.appendChild(label);
  if (extra) {
    const e = document.createElement("span");
    e.className = "muted";
    e.textContent = extra;
    item.appendChild(e);
  }
  if (title) item.title = title;
  if (onClick) item.addEventListener("click", onClick);
  return item;
}

function bytes(n) {
  if (!Number.isFinite(n)) return "–";
  const units = ["B", "KiB", "MiB", "GiB"];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i += 1; }
  return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
}

const MAX_SECTIONS = 6; // as the protocol's "sections" message takes (docs/PROTOCOL.md)

export class Panels {
  constructor(app) {
    this.app = app;
    this.client = {};
    this.server = {};
    this.header = null;
    this.pointers = new Map();
    this.annotations = [];
    this.views = [];
    this.sections = [];
    this.parts = [];
    this.partBounds = new Map(); // part id -> [lo, hi], of the parts the page has been sent
    this.highlight = new Set();
    this.pointerMode = false;
    this.#wireQuality();
    this.#wireTools();
    $("model-up").addEventListener("change", (e) => this.app.setUp(e.target.value.split(",").map(Number)));
    $("model-units").addEventListener("change", (e) => this.app.setUnits(e.target.value));
    for (const b of document.querySelectorAll("#standard-views button[data-view]")) {
      b.addEventListener("click", () => this.app.frameAll(b.dataset.view));
    }
    $("projection").addEventListener("click", () => this.app.toggleProjection());
  }

  // -- quality ---------------------------------------------------------------------------

  quality() {
    return {
      shading: $("shading").value,
      pixels_of_error: Number($("poe").value),
      min_scale: Number($("min-scale").value),
      jpeg_quality: Number($("jpeg").value),
      refine: $("refine").checked,
    };
  }

  #wireQuality() {
    const show = () => {
      $("poe-value").textContent = $("poe").value;
      $("scale-value").textContent = $("min-scale").value;
      $("jpeg-value").textContent = $("jpeg").value;
    };
    show();
    let timer = null;
    const send = () => {
      show();
      clearTimeout(timer);
      timer = setTimeout(() => this.app.stream?.send({ type: "quality", ...this.quality() }), 60);
    };
    for (const id of ["shading", "poe", "min-scale", "jpeg", "refine"]) {
      $(id).addEventListener("input", send);
      $(id).addEventListener("change", send);
    }
    $("accuracy-button").addEventListener("click", () => {
      $("accuracy").textContent = "measuring: rendering this view at full detail…";
      this.app.stream?.send({ type: "accuracy" });
    });
    $("accuracy-auto").addEventListener("change", (e) =>
      this.app.stream?.send({ type: "quality", auto_accuracy: e.target.checked }));
  }

  // What the page can offer with its credential: uploads and starting reviews need the
  // API key (a token only views).
  access({ hasKey, review, storedKey }) {
    this.hasKey = hasKey;
    $("model-view-save-row").hidden = !hasKey; // (saving a view with the model needs the key)
    $("upload-button").hidden = !hasKey;
    $("upload-layout").hidden = !hasKey;
    $("review-start").disabled = !hasKey;
    $("review-start").title = hasKey ? "" : "Starting a review needs the API key (the URL the server printed)";
    $("model-select").disabled = review; // a review is of one model
    document.body.classList.toggle("in-review", review);
    $("review-leave").hidden = !(review && storedKey);
    this.storedKey = storedKey;
  }

  welcome(w, { reconnected = false } = {}) {
    this.#welcomeReview(w.review);
    this.showUp(w.model.up);
    $("model-units").value = w.model.units ?? "";
    const q = w.quality;
    $("shading").value = q.shading;
    $("poe").value = q.pixels_of_error;
    $("min-scale").value = q.min_scale;
    $("jpeg").value = q.jpeg_quality;
    $("refine").checked = q.refine;
    $("poe-value").textContent = q.pixels_of_error;
    $("scale-value").textContent = q.min_scale;
    $("jpeg-value").textContent = q.jpeg_quality;
    $("accuracy").textContent = "–";
    delete $("accuracy").dataset.measured;
    this.parts = w.model.parts ?? [];
    this.partBounds = new Map(this.parts.map((p) => [p.id, p.bounds]));
    // The welcome lists the first parts of a big table; searches then go to the server.
    this.partsTotal = Math.max(w.model.part_count ?? 0, this.parts.length);
    // What the view highlights now; the parts panel sends what the page wants if it differs
    // (after a restart, what the page had).
    this.lastHighlight = (w.highlight ?? []).join(",");
    if (!reconnected || w.review) this.highlight = new Set(w.highlight ?? []);
    this.#renderParts();
    if (!reconnected) this.loadModelViews();
    if (reconnected && !w.review && !w.sections?.length && this.sections.length) {
      // The server lost the planes with the connection (a restart): give them back.
      this.#sendSections();
    } else {
      this.sections = w.sections ?? [];
    }
    this.#renderSections();
  }

  // The up picker shows the model's up: one of the axes, or "other" (set over the API).
  showUp(up = [0, 1, 0]) {
    const value = up.map((v) => Math.round(v * 1e6) / 1e6).join(",");
    const axis = [...$("model-up").options].find((o) => o.value === value);
    $("model-up").value = axis ? value : "custom";
  }

  // Whether this page's settings drive what it shows: not while following a presenter.
  mayDrive() {
    return !(this.review && this.app.role === "follower" && this.app.following);
  }

  // Settings a follower cannot change are disabled (and say why) while it follows.
  #syncDriving() {
    const drive = this.mayDrive();
    const why = drive ? "" : "You follow the presenter: stop following to change this";
    const controls = "#quality-panel input, #quality-panel select, #sections-panel button, #sections-panel input, " +
      "#model-up";
    for (const el of document.querySelectorAll(controls)) {
      if (el.dataset.title === undefined) el.dataset.title = el.title;
      el.disabled = !drive;
      el.title = drive ? el.dataset.title : why;
    }
  }

  accuracy(a) {
    $("accuracy").textContent =
      `at PoE ${a.pixels_of_error}: ${(100 * a.hit_differs).toFixed(2)} % of pixels hit other geometry, ` +
      `PSNR ${Number.isFinite(a.psnr_db) ? a.psnr_db.toFixed(1) + " dB" : "∞"}\n` +
      `frame ${a.frame_ms.toFixed(0)} ms vs ${a.full_detail_ms.toFixed(0)} ms at full detail`;
    $("accuracy").dataset.measured = "true";
  }

  // -- stats -----------------------------------------------------------------------------

  frame(header) {
    this.header = header;
    this.#renderStats();
    const loading = $("loading");
    loading.hidden = header.complete;
    if (!header.complete) {
      const pending = this.server.pending_blocks ?? 0;
      this.pendingMax = Math.max(this.pendingMax ?? 0, pending);
      $("loading-bar").style.width = `${100 * (1 - pending / Math.max(1, this.pendingMax))}%`;
    } else {
      this.pendingMax = 0;
    }
  }

  serverStats(s) {
    this.server = s;
  }

  clientStats(c) {
    this.client = c;
  }

  #renderStats() {
    const h = this.header, s = this.server, c = this.client;
    const rows = [
      ["frames/s", c.fps?.toFixed(1)],
      ["input → frame", c.latency != null ? `${c.latency.toFixed(0)} ms` : "–"],
      ["bandwidth", c.mbit != null ? `${c.mbit.toFixed(1)} Mbit/s` : "–"],
      ["render + encode", h ? `${h.renderMs.toFixed(0)} + ${h.encodeMs.toFixed(0)} ms` : "–"],
      ["image", h ? `${h.width}×${h.height} (scale ${h.scale.toFixed(2)})` : "–"],
      ["pixels of error", h ? h.pixelsOfError.toFixed(2) : "–"],
      ["pass", h ? (h.moving ? "moving" : `${h.pass}${h.final ? " (final)" : ""}`) : "–"],
      ["complete", h ? (h.complete ? "yes" : `loading, ${s.pending_blocks ?? "?"} blocks pending`) : "–"],
      ["working set", bytes(s.working_set_bytes)],
      ["cache hit rate", s.cache_hit_rate != null ? `${(100 * s.cache_hit_rate).toFixed(1)} %` : "–"],
      ["voxel hits", s.voxel_hits?.toLocaleString() ?? "–"],
    ];
    $("stats").replaceChildren(...rows.map(([k, v]) => {
      const tr = document.createElement("tr");
      for (const text of [k, v ?? "–"]) {
        const td = document.createElement("td");
        td.textContent = text;
        tr.appendChild(td);
      }
      return tr;
    }));
  }

  notice(text) {
    this.app.notice(text);
  }

  job(job) {
    $("job").hidden = job.state === "succeeded";
    $("job-label").textContent = `${job.name}: ${job.phase ?? job.state}` +
      (job.eta_seconds ? ` (about ${Math.ceil(job.eta_seconds)} s left)` : "");
    $("job-progress").value = job.percent;
    if (job.state === "failed") this.app.banner(`The build failed: ${job.error}`, "error");
  }

  // -- pick & measure ----------------------------------------------------------------------

  // `measured`: the two picks A and B once there are two. As CAD viewers measure: the
  // distance, its components along the axes, and the angle between the two surfaces
  // (between their planes, 0-90°, since a triangle's normal may face either way).
  pickResult(hit, elapsedMs = 0, serverMs = 0, measured = null) {
    this.lastPickResult = [hit, elapsedMs, serverMs, measured]; // (what a double click puts back)
    const out = $("pick");
    for (const k of ["distance", "delta", "angle"]) delete out.dataset[k];
    $("pick-part-box").hidden = hit?.part_id == null;
    if (!hit) {
      out.textContent = elapsedMs ? "Nothing there (the ray missed the model)." : "Click the model to pick a point; click again to measure.";
      return;
    }
    const u = this.#unit();
    const p = hit.position.map((x) => formatLength(x)).join(", ");
    // The part, and its size along the axes when the page knows its bounds.
    const bounds = hit.part_id != null ? this.partBounds.get(hit.part_id) : null;
    const extent = bounds && [0, 1, 2].map((k) => formatLength(bounds[1][k] - bounds[0][k])).join(" × ");
    const size = bounds ? `\npart size: ${extent}${u}` : "";
    const part = hit.part != null ? `\npart: ${hit.part}${size}` : "";
    let text = `point: ${p}${u && ` (${u.trim()})`}\ndistance from the eye: ${formatLength(hit.distance)}${u}` +
      `\ntriangle: ${hit.triangle}${part}\nanswered in ${elapsedMs.toFixed(0)} ms (server ${serverMs.toFixed(0)} ms)`;
    if (measured != null) {
      const [a, b] = measured;
      const d = sub(b.position, a.position);
      const cos = Math.min(1, Math.abs(dot(normalize(a.normal), normalize(b.normal))));
      const angle = (Math.acos(cos) * 180) / Math.PI;
      text = `A → B: ${formatLength(length(d))}${u}\n` +
        `Δx ${formatLength(d[0])}${u}, Δy ${formatLength(d[1])}${u}, Δz ${formatLength(d[2])}${u}\n` +
        `angle between the surfaces: ${angle.toFixed(1)}°\n` + text;
      out.dataset.distance = String(length(d));
      out.dataset.delta = d.join(",");
      out.dataset.angle = String(angle);
    }
    out.textContent = text;
    this.lastPick = hit;
  }

  // The model's units changed: the lengths shown say them.
  unitsChanged() {
    if (this.lastPickResult) this.pickResult(...this.lastPickResult);
    this.#renderSections();
  }

  // " mm" after a length when the model says its units, else nothing.
  #unit() {
    const units = this.app.model?.units;
    return units ? ` ${units}` : "";
  }

  #wireTools() {
    $("clear-measure").addEventListener("click", () => this.app.clearMeasure());
    $("screenshot-button").addEventListener("click", () => this.app.screenshot());
    $("model-select").addEventListener("change", (e) => this.app.open(e.target.value));
    $("upload-button").addEventListener("click", () => $("upload-input").click());
    $("upload-input").addEventListener("change", (e) => {
      const file = e.target.files[0];
      e.target.value = ""; // so that choosing the same file again uploads it again
      if (file) this.app.upload(file);
    });
    const stage = $("stage");
    stage.addEventListener("dragover", (e) => { e.preventDefault(); $("drop-hint").hidden = false; });
    stage.addEventListener("dragleave", () => { $("drop-hint").hidden = true; });
    stage.addEventListener("drop", (e) => {
      e.preventDefault();
      $("drop-hint").hidden = true;
      const file = e.dataTransfer.files[0];
      if (file) this.app.upload(file);
    });
    $("parts-search").addEventListener("input", () => this.#renderParts());
    for (const button of document.querySelectorAll("#sections-panel button[data-axis]")) {
      button.addEventListener("click", () => this.addSection(Number(button.dataset.axis)));
    }
    $("section-view").addEventListener("click", () => this.addSection(null));
    $("section-box").addEventListener("click", () => this.addSectionBox());
    $("pick-part-box").addEventListener("click", () => this.boxPart(this.lastPick));
    $("model-view-save").addEventListener("click", () => this.saveModelView());
    $("model-view-name").addEventListener("keydown", (e) => e.key === "Enter" && this.saveModelView());
    $("section-clear").addEventListener("click", () => {
      this.sections = [];
      this.#renderSections();
      this.#sendSections();
    });
    $("review-start").addEventListener("click", () => this.#startReview());
    $("review-copy").addEventListener("click", () => this.#copyLink());
    const rename = () => {
      const name = $("review-name").value.trim();
      if (!name) return;
      sessionStorage.setItem("vastray.name", name); // the next hello carries it too
      if (this.app.stream) this.app.stream.name = name;
      this.app.stream?.send({ type: "rename", name });
    };
    $("review-rename").addEventListener("click", rename);
    $("review-name").addEventListener("keydown", (e) => e.key === "Enter" && rename());
    $("review-leave").addEventListener("click", () => {
      // Back to a view of one's own, with the key this tab was opened with.
      location.href = `/?${new URLSearchParams({ key: this.storedKey, model: this.app.modelId })}`;
    });
    $("follow").addEventListener("change", (e) => this.setFollow(e.target.checked));
    $("pointer-mode").addEventListener("change", (e) => { this.pointerMode = e.target.checked; });
    $("annotate").addEventListener("click", () => this.#annotate());
    $("save-view").addEventListener("click", () => {
      const name = $("view-name").value.trim() || `view ${this.views.length + 1}`;
      this.app.stream?.send({ type: "save_view", name });
      $("view-name").value = "";
    });
  }

  // -- parts -----------------------------------------------------------------------------

  #renderParts() {
    const query = $("parts-search").value.trim().toLowerCase();
    if (!this.parts.length) {
      $("parts").replaceChildren(li("this model has no part structure", {}));
      return;
    }
    if (query && this.partsTotal > this.parts.length) {
      this.#searchServer(query);
      return;
    }
    const found = this.parts.filter((p) => !query || p.name.toLowerCase().includes(query));
    this.#showParts(found.slice(0, 500), found.length, query ? found.map((p) => p.id) : null);
  }

  // A big table's search: on the server, once typing pauses; a newer search wins.
  async #searchServer(query) {
    const seq = (this.partSearch = (this.partSearch ?? 0) + 1);
    await new Promise((resolve) => setTimeout(resolve, 200));
    if (seq !== this.partSearch) return;
    let found;
    try {
      found = await this.app.api.parts(this.app.modelId, query, 500);
    } catch {
      return;  // (the connection state shows why)
    }
    if (seq !== this.partSearch) return;
    for (const p of found.parts) this.partBounds.set(p.id, p.bounds);
    this.#showParts(found.parts, found.total, found.parts.map((p) => p.id));
  }

  // `matches`: what a search highlights (null: no search, the picked parts stay).
  #showParts(shown, total, matches) {
    const list = $("parts");
    const items = shown.map((part) => {
      const item = li(part.name, {
        extra: `${part.triangles.toLocaleString()} △`,
        title: "click: frame and highlight",
        onClick: () => this.#framePart(part),
      });
      if (this.highlight.has(part.id)) item.classList.add("active");
      return item;
    });
    if (total > shown.length) items.push(li(`… ${(total - shown.length).toLocaleString()} more: refine the search`, {}));
    if (!total && matches) items.push(li("no part matches this search", {}));
    list.replaceChildren(...items);
    this.#sendHighlight(matches ?? [...this.highlight]);
  }

  #framePart(part) {
    this.highlight = new Set([part.id]);
    const [lo, hi] = part.bounds;
    const centre = lo.map((v, i) => (v + hi[i]) / 2);
    const size = Math.hypot(...lo.map((v, i) => hi[i] - v));
    const cam = this.app.camera;
    const dir = cam ? cam.eye.map((v, i) => v - cam.target[i]) : [1, 0.7, 1.3];
    const len = Math.hypot(...dir);
    const eye = centre.map((v, i) => v + (dir[i] / len) * size * 1.6);
    this.app.setCamera({ eye, target: centre, up: cam?.up ?? [0, 1, 0], fov: cam?.fov ?? 45,
      projection: cam?.projection ?? "perspective" });
    this.#renderParts();
  }

  // Highlights these parts and no others: the search is cleared, since the list would
  // highlight what a search finds instead (#showParts), and the list sends the set.
  #highlightOnly(ids) {
    this.highlight = new Set(ids);
    $("parts-search").value = "";
    this.#renderParts();
  }

  // The part ids the view highlights (as last sent).
  #highlighted() {
    return (this.lastHighlight ?? "").split(",").filter(Boolean).map(Number);
  }

  #sendHighlight(ids) {
    const key = ids.join(",");
    if (key === (this.lastHighlight ?? "") || !this.mayDrive()) return;
    this.lastHighlight = key;
    this.app.stream?.send({ type: "highlight", parts: ids.slice(0, 4096) });
  }

  // -- sections --------------------------------------------------------------------------

  // A plane keeps geometry where dot(normal, p) + offset >= 0 (docs/PROTOCOL.md). "+ X"
  // cuts away x > the model's centre; "+ view" the near side of a plane through the
  // target, facing the camera, so the cut shows.
  addSection(axis) {
    const m = this.app.model;
    if (!m || !this.app.camera) return;
    if (this.sections.length >= MAX_SECTIONS) {
      this.app.notice(`A view takes ${MAX_SECTIONS} section planes at most: remove one first.`);
      return;
    }
    const [lo, hi] = m.bounds;
    let normal, offset;
    if (axis === null) {
      const cam = this.app.camera;
      const d = cam.target.map((v, i) => v - cam.eye[i]);
      const l = Math.hypot(...d);
      normal = d.map((v) => v / l);
      offset = -normal.reduce((a, n, i) => a + n * cam.target[i], 0);
    } else {
      normal = [0, 0, 0];
      normal[axis] = -1;
      offset = (lo[axis] + hi[axis]) / 2;
    }
    this.sections.push({ normal, offset, enabled: true });
    this.#renderSections();
    this.#sendSections();
  }

  // A section box, as CAD viewers have it: six planes that keep what lies within the
  // bounds of the parts the view highlights (the whole model when it highlights none),
  // grown by a fiftieth of their diagonal on every side so the parts' own faces stay
  // whole. It replaces the planes there were (a view takes six at most); each face's
  // slider then moves that face. vastray.schemas.section_box is the same box. The bounds
  // of highlighted parts the page has not been sent (a saved view's, a review's, past
  // the welcome's list) come from the server first.
  async addSectionBox(boxes = null) {
    const m = this.app.model;
    if (!m) return;
    if (!boxes) {
      const ids = this.#highlighted();
      const unknown = ids.filter((id) => !this.partBounds.has(id));
      try {
        for (let i = 0; i < unknown.length; i += 1000) {
          const chunk = unknown.slice(i, i + 1000);
          const found = await this.app.api.parts(this.app.modelId, "", chunk.length, chunk);
          for (const p of found.parts) this.partBounds.set(p.id, p.bounds);
        }
      } catch (e) {
        this.app.notice(`The highlighted parts' bounds could not be read: ${e.message}`);
        return;
      }
      if (this.app.model !== m) return; // another model opened meanwhile
      boxes = ids.map((id) => this.partBounds.get(id)).filter(Boolean);
    }
    const lo = [0, 1, 2].map((k) => Math.min(...(boxes.length ? boxes : [m.bounds]).map((b) => b[0][k])));
    const hi = [0, 1, 2].map((k) => Math.max(...(boxes.length ? boxes : [m.bounds]).map((b) => b[1][k])));
    const margin = Math.hypot(...lo.map((v, k) => hi[k] - v)) / 50;
    this.sections = [];
    for (let k = 0; k < 3; k++) {
      const inward = [0, 0, 0];
      inward[k] = 1; // keeps p[k] >= lo[k] - margin
      this.sections.push({ normal: [...inward], offset: -(lo[k] - margin), enabled: true });
      inward[k] = -1; // keeps p[k] <= hi[k] + margin
      this.sections.push({ normal: inward, offset: hi[k] + margin, enabled: true });
    }
    this.#renderSections();
    this.#sendSections();
  }

  // The picked part, highlighted and boxed: its bounds from the part table the page has,
  // or from a search of the server's by its name.
  async boxPart(hit) {
    if (hit?.part_id == null) return;
    if (!this.mayDrive()) {
      this.app.notice("You follow the presenter: stop following to change the sections.");
      return;
    }
    let bounds = this.partBounds.get(hit.part_id);
    if (!bounds) {
      try {
        const found = await this.app.api.parts(this.app.modelId, hit.part, 500);
        for (const p of found.parts) this.partBounds.set(p.id, p.bounds);
      } catch (e) {
        this.app.notice(`The part's bounds could not be read: ${e.message}`);
        return;
      }
      bounds = this.partBounds.get(hit.part_id);
      if (!bounds) return;
    }
    this.#highlightOnly([hit.part_id]);
    this.addSectionBox([bounds]);
  }

  // [lo, hi] when the enabled planes keep a box (one facing each way along each axis,
  // whichever way they were made), else null: the overlay draws its edges.
  sectionBox() {
    const on = this.sections.filter((p) => p.enabled);
    if (on.length !== 6) return null;
    const lo = [null, null, null], hi = [null, null, null];
    for (const { normal, offset } of on) {
      const k = normal.findIndex((v) => Math.abs(v) === 1);
      if (k < 0) return null;
      if (normal[k] > 0) lo[k] = -offset; // keeps p[k] >= -offset
      else hi[k] = offset; // keeps p[k] <= offset
    }
    return lo.every((v, k) => v !== null && hi[k] !== null && v <= hi[k]) ? [lo, hi] : null;
  }

  // Whether a plane's normal points away from the camera (it then cuts the near side).
  #facesAway(normal) {
    const cam = this.app.camera;
    return !cam || normal.reduce((a, n, k) => a + n * (cam.target[k] - cam.eye[k]), 0) > 0;
  }

  #sendSections() {
    this.app.stream?.send({ type: "sections", planes: this.sections });
    this.app.redrawOverlay(); // a section box's edges move with its sliders at once
  }

  #renderSections() {
    const m = this.app.model;
    const box = $("sections");
    box.replaceChildren(...this.sections.map((plane, i) => {
      const axis = plane.normal.findIndex((v) => Math.abs(v) === 1);
      const name = axis >= 0 ? "XYZ"[axis] : "view";
      // The slider moves the plane along its axis in world units (a view plane: along its
      // normal); `offset` follows.
      const u = axis >= 0 ? plane.normal.map((_, k) => (k === axis ? 1 : 0)) : plane.normal;
      const sign = plane.normal.reduce((a, n, k) => a + n * u[k], 0); // +1 or -1
      const position = () => -plane.offset * sign;
      const div = document.createElement("div");
      div.className = "section";
      const label = document.createElement("label");
      label.className = "check";
      const on = document.createElement("input");
      on.type = "checkbox";
      on.checked = plane.enabled;
      on.setAttribute("aria-label", `${name} plane on`);
      on.addEventListener("change", () => { plane.enabled = on.checked; this.#sendSections(); });
      const readout = document.createElement("span");
      const describe = () => {
        const at = formatLength(position()) + this.#unit();
        readout.textContent = axis >= 0
          ? ` ${name} plane at ${at}: cuts ${name.toLowerCase()} ${sign < 0 ? ">" : "<"} ${at}`
          : ` view plane: cuts the ${this.#facesAway(plane.normal) ? "near" : "far"} side`;
      };
      describe();
      label.append(on, readout);
      const slider = document.createElement("input");
      slider.type = "range";
      const extent = m ? Math.hypot(...m.bounds[0].map((v, k) => m.bounds[1][k] - v)) : 1;
      const centre = m ? u.reduce((a, x, k) => a + x * (m.bounds[0][k] + m.bounds[1][k]) / 2, 0) : 0;
      slider.min = String(centre - extent / 2);
      slider.max = String(centre + extent / 2);
      slider.step = String(extent / 500);
      slider.value = String(position());
      slider.setAttribute("aria-label", `${name} plane position`);
      slider.addEventListener("input", () => {
        plane.offset = -Number(slider.value) * sign;
        describe();
        this.#sendSections();
      });
      const flip = document.createElement("button");
      flip.textContent = "flip";
      flip.title = "Cut away the other side";
      flip.addEventListener("click", () => {
        plane.normal = plane.normal.map((n) => -n);
        plane.offset = -plane.offset;
        this.#renderSections();
        this.#sendSections();
      });
      const remove = document.createElement("button");
      remove.textContent = "remove";
      remove.addEventListener("click", () => {
        this.sections.splice(i, 1);
        this.#renderSections();
        this.#sendSections();
      });
      const row = document.createElement("div");
      row.className = "row";
      row.append(flip, remove);
      div.append(label, slider, row);
      return div;
    }));
    this.#syncDriving();
  }

  // -- views saved with the model ----------------------------------------------------------

  async loadModelViews() {
    const modelId = this.app.modelId;
    let views;
    try {
      views = (await this.app.api.modelViews(modelId)).views;
    } catch (e) {
      $("model-views").replaceChildren(li(`saved views could not be read: ${e.message}`, {}));
      return;
    }
    if (modelId !== this.app.modelId) return; // another model opened meanwhile
    this.modelViews = views;
    $("model-views").replaceChildren(...(views.length ? views.map((v) => {
      const item = li(v.name, { title: "click: go to this view", onClick: () => this.showModelView(v) });
      if (this.hasKey) {
        const remove = document.createElement("button");
        remove.textContent = "×";
        remove.title = "Delete this view";
        remove.setAttribute("aria-label", `delete the view ${v.name}`);
        remove.addEventListener("click", (e) => {
          e.stopPropagation();
          this.#deleteModelView(v);
        });
        item.append(remove);
      }
      return item;
    }) : [li("no views saved with this model yet", {})]));
  }

  // Goes to a saved view: its camera, section planes and highlighted parts.
  showModelView(view) {
    if (!this.mayDrive()) {
      this.app.notice("You follow the presenter: stop following to go to a view of your own.");
      return;
    }
    this.sections = view.sections.map((p) => ({ ...p }));
    this.#renderSections();
    this.#sendSections();
    this.#highlightOnly(view.highlight);
    this.app.setCamera(view.camera);
  }

  async saveModelView() {
    const camera = this.app.camera;
    if (!camera || !this.app.modelId) return;
    const name = $("model-view-name").value.trim() || `view ${(this.modelViews?.length ?? 0) + 1}`;
    try {
      await this.app.api.saveModelView(this.app.modelId, {
        name, camera: camera.toMessage(0), sections: this.sections,
        highlight: this.#highlighted(),
      });
    } catch (e) {
      this.app.notice(`The view was not saved: ${e.message}`);
      return;
    }
    $("model-view-name").value = "";
    this.app.notice(`Saved "${name}" with the model.`);
    if (!this.app.stream?.connected) await this.loadModelViews(); // (else the model_views event lists them)
  }

  async #deleteModelView(view) {
    try {
      await this.app.api.deleteModelView(this.app.modelId, view.id);
    } catch (e) {
      this.app.notice(`The view was not deleted: ${e.message}`);
    }
    if (!this.app.stream?.connected) await this.loadModelViews(); // (else the model_views event lists them)
  }

  // -- review ----------------------------------------------------------------------------

  #welcomeReview(review) {
    if (review) $("review-name").value = review.name ?? "";
    this.review = review ?? null;
    this.pointers.clear(); // the server sends those there are now
    $("review-idle").hidden = !!review;
    $("review-active").hidden = !review;
    if (review) {
      $("review-panel").open = true;
      $("review-title").textContent = review.title ?? "";
      // Never the presenter's own link: that would make whoever opens it a presenter.
      const join = review.role === "presenter"
        ? sessionStorage.getItem(`vastray.join.${review.id}`) ?? "" : location.href;
      $("review-link").value = join;
      $("review-link").placeholder = join ? "" : "the join link came with the review (POST /api/reviews: join_url)";
      $("review-copy").disabled = !join;
      $("follow").checked = review.following ?? true;
      this.app.following = review.following ?? true;
      this.#showRole(review.role);
    }
    this.#syncDriving();
  }

  #showRole(role) {
    const presenter = this.review?.presenter;
    $("review-role").textContent = role === "presenter" ? "You present: the others see your view."
      : presenter ? "You follow the presenter's view (navigate to look on your own)."
        : "No presenter is here now: the shared view stays where it was left.";
    $("follow-label").hidden = role === "presenter"; // the presenter is who the others follow
    this.#syncDriving();
  }

  async #startReview() {
    try {
      // The review starts from what this page shows: the page reloads into it, and the
      // shared view would otherwise start from the model's overview.
      const camera = this.app.camera?.toMessage(this.app.seq);
      const view = camera
        ? { camera, quality: this.quality(), sections: this.sections, highlight: [...this.highlight] }
        : null;
      const r = await this.app.api.createReview(this.app.modelId, `${this.app.model?.name ?? "model"} review`, view);
      // The presenter joins through its own link: the page reloads into the review,
      // with the join link (to show and share) in the fragment.
      location.href = `${r.presenter_url}#${new URLSearchParams({ join: r.join_url })}`;
    } catch (e) {
      this.app.banner(`Cannot start a review: ${e.message}`, "error");
    }
  }

  async #copyLink() {
    const input = $("review-link");
    try {
      await navigator.clipboard.writeText(input.value);
      this.notice("The join link is copied: send it to the others.");
    } catch {
      input.select(); // no clipboard here (an insecure origin): the user copies it
      this.notice("Copy the selected link (Ctrl+C) and send it to the others.");
    }
  }

  setFollow(follow) {
    $("follow").checked = follow;
    this.app.following = follow;
    this.app.stream?.send({ type: "follow", follow });
    this.#syncDriving();
  }

  #annotate() {
    const text = $("annotation-text").value.trim();
    const at = this.lastPick?.position;
    if (!text || !at) {
      this.notice(at ? "Write the note first." : "Pick a point first: the note is pinned there.");
      return;
    }
    this.app.stream?.send({ type: "annotate", text, position: at });
    $("annotation-text").value = "";
  }

  reviewMessage(m) {
    switch (m.type) {
      case "participants": {
        this.participants = m.participants;
        if (this.review) {
          this.review.presenter = m.presenter;
          this.#showRole(this.review.role);
        }
        $("participants").replaceChildren(...m.participants.map((p) => {
          const item = li(`${p.name}${p.id === this.review?.participant ? " (you)" : ""}`, {
            extra: p.role === "presenter" ? "presenter" : p.following ? "following" : "looking around",
          });
          if (this.review?.role === "presenter" && p.role !== "presenter") {
            // Handing over is explicit: a button, not a click on the name.
            const give = document.createElement("button");
            give.textContent = "make presenter";
            give.setAttribute("aria-label", `hand the presenter role to ${p.name}`);
            give.addEventListener("click", () => this.app.stream?.send({ type: "handover", to: p.id }));
            item.appendChild(give);
          }
          return item;
        }));
        break;
      }
      case "role":
        if (this.review) {
          this.review.role = m.role;
          this.review.presenter = m.presenter;
          this.app.role = m.role;
          this.app.takeSharedCamera(m.camera);
          this.notice(m.role === "presenter" ? "You are the presenter now." : "You follow the presenter.");
          if (m.role !== "presenter") this.setFollow(true);
          this.#showRole(m.role);
        }
        break;
      case "pointer":
        if (m.position) this.pointers.set(m.from, { position: m.position, name: m.name });
        else this.pointers.delete(m.from);
        this.app.redrawOverlay();
        break;
      case "annotations":
        this.annotations = m.annotations;
        $("annotations").replaceChildren(...m.annotations.map((a) => li(a.text, {
          extra: a.author ?? "",
          title: "click: go there",
          onClick: () => a.camera && this.#jump({ camera: a.camera }),
        })));
        this.app.redrawOverlay();
        break;
      case "views":
        this.views = m.views;
        $("views").replaceChildren(...m.views.map((v) => li(v.name, { title: "click: go to this view", onClick: () => this.#jump(v) })));
        break;
      case "model_views": // saved or deleted (by this page or another): list them again
        if (m.model === this.app.modelId) this.loadModelViews();
        break;
      case "model": // its name, up or units changed (PATCH, by this page or another)
        if (m.model === this.app.modelId && this.app.model) {
          const renamed = m.name !== this.app.model.name;
          Object.assign(this.app.model, { name: m.name, up: m.up, units: m.units });
          if (renamed && !this.review) this.app.refreshModels().catch(() => {}); // the picker's name
          this.showUp(m.up);
          $("model-units").value = m.units ?? "";
          this.unitsChanged();
          this.app.redrawOverlay();
        }
        break;
      case "sections":
        // The presenter's own planes, echoed: re-rendering would break a drag of a slider.
        if (this.review?.role === "presenter") break;
        this.sections = m.planes;
        this.#renderSections();
        break;
      default:
        break;
    }
  }

  #jump(view) {
    if (view.id) {
      this.app.stream?.send({ type: "jump", view: view.id });
    } else {
      this.app.setCamera(view.camera);
    }
  }
}
