// The REST API (docs/API.md) from the page.

export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

export class Api {
  constructor(base, credential) {
    this.base = base;
    this.credential = credential;
  }

  headers(extra = {}) {
    return this.credential ? { Authorization: `Bearer ${this.credential}`, ...extra } : extra;
  }

  async request(method, path, body = undefined) {
    let response;
    try {
      response = await fetch(this.base + path, {
        method,
        headers: this.headers(body !== undefined ? { "Content-Type": "application/json" } : {}),
        body: body !== undefined ? JSON.stringify(body) : undefined,
      });
    } catch {
      throw new ApiError(0, "unreachable", "the server cannot be reached");
    }
    if (!response.ok) {
      let code = "http_error", message = `${response.status} ${response.statusText}`;
      try {
        const e = (await response.json()).error;
        code = e.code;
        message = e.message;
      } catch { /* not our error body */ }
      throw new ApiError(response.status, code, message);
    }
    return response.status === 204 ? null : response.json();
  }

  models() { return this.request("GET", "/api/models"); }
  model(id) { return this.request("GET", `/api/models/${id}`); }
  // Renames a model or says which way is up in it (`{ name, up }`); needs the API key.
  updateModel(id, changes) { return this.request("PATCH", `/api/models/${id}`, changes); }
  // `ids`: only the parts with these ids (e.g. the highlighted ones whose bounds the
  // page has not been sent).
  parts(id, query, limit = 500, ids = null) {
    const params = { q: query, limit };
    if (ids) params.ids = ids.join(",");
    return this.request("GET", `/api/models/${id}/parts?${new URLSearchParams(params)}`);
  }
  // Views saved with a model (`{ name, camera, sections, highlight }`); saving and
  // deleting need the API key.
  modelViews(id) { return this.request("GET", `/api/models/${id}/views`); }
  saveModelView(id, view) { return this.request("POST", `/api/models/${id}/views`, view); }
  deleteModelView(id, viewId) { return this.request("DELETE", `/api/models/${id}/views/${viewId}`); }
  review(id) { return this.request("GET", `/api/reviews/${id}`); }
  // `view`: where the shared view starts (camera, quality, sections, highlight), or null.
  createReview(model, title, view = null) {
    return this.request("POST", "/api/reviews", view ? { model, title, view } : { model, title });
  }

  // Registers an upload (a mesh starts a build with these options).
  register(upload, options) { return this.request("POST", "/api/models", { upload, options }); }

  // Streams a file to the server (XMLHttpRequest: fetch cannot report upload progress).
  // With `register`, the server registers it at once with its default build options.
  upload(file, onProgress, { register = true } = {}) {
    return new Promise((resolve, reject) => {
      const xhr = new XMLHttpRequest();
      const name = encodeURIComponent(file.name);
      xhr.open("POST", `${this.base}/api/uploads?filename=${name}&register=${register}`);
      for (const [k, v] of Object.entries(this.headers())) xhr.setRequestHeader(k, v);
      xhr.upload.onprogress = (e) => e.lengthComputable && onProgress(e.loaded / e.total);
      xhr.onload = () => {
        let body = null;
        try { body = JSON.parse(xhr.responseText); } catch { /* not JSON */ }
        if (xhr.status >= 200 && xhr.status < 300) resolve(body);
        else reject(new ApiError(xhr.status, body?.error?.code ?? "http_error", body?.error?.message ?? xhr.statusText));
      };
      xhr.onerror = () => reject(new ApiError(0, "unreachable", "the upload failed: the server cannot be reached"));
      xhr.send(file);
    });
  }

  // A build job's progress until it ends (server-sent events; the key rides in the URL
  // because EventSource cannot set headers).
  followJob(jobId, onUpdate) {
    return new Promise((resolve, reject) => {
      const source = new EventSource(`${this.base}/api/jobs/${jobId}/events?key=${encodeURIComponent(this.credential)}`);
      source.addEventListener("progress", (e) => onUpdate(JSON.parse(e.data)));
      source.addEventListener("end", (e) => {
        source.close();
        const job = JSON.parse(e.data);
        onUpdate(job);
        if (job.state === "succeeded") resolve(job);
        else reject(new ApiError(0, job.state, `the build ${job.state}: ${job.error ?? ""}`));
      });
      source.onerror = () => {
        if (source.readyState === EventSource.CLOSED) reject(new ApiError(0, "unreachable", "lost the build's progress"));
      };
    });
  }
}
