// One WebSocket to the server: hello and welcome, frames and events, acknowledgements,
// pings, and reconnection with backoff that resumes the session (docs/PROTOCOL.md).

import { PROTOCOL_VERSION, parseFrame } from "./protocol.js";

const PING_MS = 15000;
const BACKOFF_MS = [200, 500, 1000, 2000, 5000];
// Close codes after which retrying cannot help.
const FATAL = { 4400: "bad request", 4401: "not authorised", 4403: "forbidden", 4404: "not found" };
// Numbers every connection of the page (of any Stream): frame numbers start again on each.
let connections = 0;

export class Stream extends EventTarget {
  constructor({ url, token, model, review = null, viewport, camera = null, quality = null, name = null }) {
    super();
    this.url = url;
    this.token = token;
    this.model = model;
    this.review = review;
    this.name = name;
    this.viewport = viewport;
    this.camera = camera; // the last camera sent (a message object), re-sent on reconnect
    this.quality = quality;
    this.session = null;
    this.generation = 0; // this stream's current connection (see `connections`)
    this.ws = null;
    this.closed = false;
    this.attempt = 0;
    this.connected = false;
    this.pingTimer = null;
  }

  open() {
    this.closed = false;
    this.#connect();
  }

  close() {
    this.closed = true;
    clearInterval(this.pingTimer);
    if (this.ws) {
      try { this.ws.send(JSON.stringify({ type: "bye" })); } catch { /* closing anyway */ }
      this.ws.close(1000);
    }
  }

  send(message) {
    // What a reconnect's hello must carry to bring the view back as it was.
    if (message.type === "camera") {
      const { type, ...camera } = message; // the hello's camera is the state, without the type
      this.camera = camera;
    }
    if (message.type === "viewport") this.viewport = { width: message.width, height: message.height };
    if (message.type === "quality") {
      const { type, ...changes } = message;
      this.quality = { ...(this.quality ?? {}), ...changes };
    }
    if (this.ws && this.ws.readyState === WebSocket.OPEN && this.connected) {
      this.ws.send(JSON.stringify(message));
      return true;
    }
    return false;
  }

  #emit(type, detail) {
    this.dispatchEvent(new CustomEvent(type, { detail }));
  }

  #connect() {
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    this.generation = ++connections;
    this.pending = null;
    this.connected = false;
    this.#emit("status", { state: "connecting", attempt: this.attempt });
    ws.onopen = () => {
      const hello = {
        type: "hello", protocol: PROTOCOL_VERSION, model: this.model, token: this.token,
        session: this.session, viewport: this.viewport,
      };
      if (this.review) Object.assign(hello, { review: this.review, name: this.name });
      if (this.camera) hello.camera = this.camera;
      if (this.quality) hello.quality = this.quality;
      ws.send(JSON.stringify(hello));
    };
    ws.onmessage = (event) => this.#receive(event.data);
    ws.onclose = (event) => this.#closed(event);
    ws.onerror = () => { /* onclose follows and says what to do */ };
  }

  #receive(data) {
    if (data instanceof ArrayBuffer) {
      const frame = parseFrame(data);
      frame.generation = this.generation;
      // A frame is followed by its stats (the camera it shows among them): hand both out
      // together. Screenshots have none.
      if (frame.screenshot) this.#emit("frame", frame);
      else this.pending = frame;
      return;
    }
    const message = JSON.parse(data);
    if (message.type === "stats" && this.pending?.frame === message.frame) {
      const frame = this.pending;
      this.pending = null;
      frame.stats = message;
      this.#emit("frame", frame);
    }
    if (message.type === "welcome") {
      this.connected = true;
      this.attempt = 0;
      this.session = message.session;
      this.camera = message.camera;
      clearInterval(this.pingTimer);
      this.pingTimer = setInterval(() => this.send({ type: "ping", t: performance.now() }), PING_MS);
      this.#emit("status", { state: "connected", resumed: message.resumed });
    }
    this.#emit(message.type, message);
    this.#emit("message", message);
  }

  // Acknowledges a frame shown; one of an earlier connection has nobody to thank.
  ack(frame, generation = this.generation) {
    if (generation === this.generation) this.send({ type: "ack", frame });
  }

  #closed(event) {
    this.connected = false;
    clearInterval(this.pingTimer);
    if (this.closed) return;
    const fatal = FATAL[event.code];
    if (fatal) {
      this.#emit("status", { state: "failed", code: event.code, reason: event.reason || fatal });
      return;
    }
    const delay = BACKOFF_MS[Math.min(this.attempt, BACKOFF_MS.length - 1)];
    this.attempt += 1;
    this.#emit("status", { state: "reconnecting", delay, code: event.code, reason: event.reason });
    setTimeout(() => { if (!this.closed) this.#connect(); }, delay);
  }
}
