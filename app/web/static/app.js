/* MeshMark page: embed, detect, capacity and a 3-D preview through the /v1 API of the server that
   served this page.  The watermark key and the API key live only in their password fields: never
   in a URL, a cookie or the browser's storage, and they are sent in request bodies or headers. */
"use strict";

(function () {
  const $ = id => document.getElementById(id);
  const state = { file: null, downloadUrl: null, job: null, busy: false };
  const viewer = new window.MeshMarkViewer.Viewer($("view"));

  // ---- small helpers ------------------------------------------------------------------------

  function formatBytes(n) {
    if (n < 1024) return n + " bytes";
    if (n < 1024 * 1024) return (n / 1024).toFixed(1) + " KB";
    return (n / 1024 / 1024).toFixed(1) + " MB";
  }

  const grouped = n => Number(n).toLocaleString("en-US");

  /** A relative distance (fraction of the bounding-box diagonal) as a percentage people read. */
  function percentOfSize(x) {
    if (x === 0) return "0 %";
    const p = x * 100;
    return (p >= 0.1 ? p.toPrecision(2) : p.toPrecision(1)) + " %";
  }

  function scientific(x) {
    if (x === 0) return "0";
    const e = Math.floor(Math.log10(Math.abs(x))), m = x / Math.pow(10, e);
    const sup = String(e).replace(/[-0-9]/g, c => "⁻⁰¹²³⁴⁵⁶⁷⁸⁹"["-0123456789".indexOf(c)]);
    return m.toFixed(1) + " × 10" + sup;
  }

  /** "1 in N" for a probability, N in words a non-specialist reads. */
  function oneIn(p) {
    if (p <= 0 || p < 1e-15) return "less than 1 in a million billion";
    const n = 1 / p;
    const words = [[1e12, "trillion"], [1e9, "billion"], [1e6, "million"], [1e3, "thousand"]];
    for (const [scale, word] of words) {
      if (n >= scale) return "about 1 in " + Number((n / scale).toPrecision(2)) + " " + word;
    }
    return "about 1 in " + Math.round(n);
  }

  function el(tag, attrs, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v; else e.setAttribute(k, v);
    }
    for (const c of children) e.append(c);
    return e;
  }

  function setStatus(text) { $("status").textContent = text; }

  function showError(title, detail) {
    $("error-title").textContent = title;
    $("error-detail").textContent = detail || "";
    $("error").hidden = false;
  }

  function clearMessages() {
    $("error").hidden = true;
    $("result").replaceChildren();
    setStatus("");
  }

  // ---- talking to the API ---------------------------------------------------------------------

  function headers() {
    const h = {};
    const apiKey = $("apikey").value;
    if (apiKey) h["Authorization"] = "Bearer " + apiKey;
    return h;
  }

  /** The problem of a failed answer as {title, detail}: RFC 9457 members when the server sent a
      problem, else the HTTP status in words (never the raw body). */
  async function problemOf(res) {
    let body = null;
    const type = res.headers.get("content-type") || "";
    if (type.includes("json")) {
      try { body = await res.json(); } catch (e) { body = null; }
    }
    if (res.status === 401) askForApiKey();
    if (body && typeof body.title === "string") {
      return { title: body.title, detail: typeof body.detail === "string" ? body.detail : "", status: res.status };
    }
    return { title: "The server answered " + res.status + (res.statusText ? " " + res.statusText : ""),
             detail: res.status === 400 ? "The request could not be read." : "", status: res.status };
  }

  class ProblemShown extends Error {
    constructor(problem) { super(problem.title); this.problem = problem; }
  }

  async function call(path, options) {
    let res;
    try {
      res = await fetch(path, { ...options, headers: { ...headers(), ...(options && options.headers) },
                                credentials: "same-origin", cache: "no-store" });
    } catch (e) {
      throw new ProblemShown({ title: "The server cannot be reached",
                               detail: "Check that MeshMark is still running, then try again." });
    }
    if (!res.ok) throw new ProblemShown(await problemOf(res));
    return res;
  }

  function form(fields, files) {
    const f = new FormData();
    for (const [name, blob, filename] of files) f.append(name, blob, filename);
    for (const [k, v] of Object.entries(fields)) if (v !== "" && v != null) f.append(k, v);
    return f;
  }

  function askForApiKey() {
    const section = $("apikey-section");
    if (section.hidden) {
      section.hidden = false;
    }
    $("apikey").focus();
  }

  /** Runs a job (embed or detect) with a progress bar; resolves to the result's Response. */
  async function runJob(kind, body) {
    const created = await call("/v1/jobs/" + kind, { method: "POST", body });
    const location = created.headers.get("Location");
    const bar = $("progress");
    $("progress-wrap").hidden = false;
    bar.value = 0;
    state.job = location;
    try {
      for (;;) {
        const status = await (await call(location, {})).json();
        bar.value = status.progress;
        $("progress-text").textContent = Math.round(status.progress * 100) + " %";
        if (status.state === "succeeded") break;
        if (status.state === "failed") {
          const p = status.error || {};
          throw new ProblemShown({ title: p.title || "The job failed", detail: p.detail || "" });
        }
        if (status.state === "cancelled") throw new ProblemShown({ title: "Cancelled", detail: "" });
        await new Promise(r => setTimeout(r, 300));
      }
      return await call(location + "/result", {});
    } finally {
      state.job = null;
      $("progress-wrap").hidden = true;
      call(location, { method: "DELETE" }).catch(() => {});
    }
  }

  // ---- the preview ----------------------------------------------------------------------------

  function parsePreview(buffer) {
    const view = new DataView(buffer);
    const size = view.getUint32(0, true);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, size)));
    let offset = 4 + size;
    // typed arrays use the platform's byte order: little-endian in every browser that runs WebGL
    const positions = new Float32Array(buffer, offset, head.vertices * 3);
    offset += 12 * head.vertices;
    const triangles = new Uint32Array(buffer, offset, head.triangles * 3);
    offset += 12 * head.triangles;
    const displacement = head.displacement ? new Float32Array(buffer, offset, head.vertices) : null;
    return { head, positions, triangles, displacement };
  }

  function describeModel(head) {
    let text = grouped(head.source_vertices) + " vertices, " + grouped(head.source_triangles) + " triangles (" +
      head.format.toUpperCase() + (head.parts > 1 ? ", " + head.parts + " parts" : "") + ")";
    if (head.decimated) text += "; the preview shows a simplified copy (" + grouped(head.triangles) + " triangles)";
    return text;
  }

  /** Top of the colour scale: the 99th percentile of the moves, so that one outlier does not
      wash the rest out (moves above it share the top colour, and the legend says so). */
  function scaleTop(displacement) {
    const moved = displacement.filter(x => x > 0).sort();
    if (!moved.length) return 0;
    return moved[Math.min(moved.length - 1, Math.floor(0.99 * moved.length))];
  }

  function showLegend(maxValue, largest) {
    const legend = $("legend");
    if (maxValue === null) { legend.hidden = true; return; }
    const bar = $("legend-bar");
    bar.replaceChildren();
    for (let i = 0; i <= 10; i++) {
      const stop = el("span", { class: "stop" });
      stop.style.background = window.MeshMarkViewer.rampCSS(i / 10);
      bar.append(stop);
    }
    $("legend-min").textContent = "0";
    $("legend-mid").textContent = scientific(maxValue / 2);
    const capped = largest > maxValue;
    $("legend-max").textContent = (capped ? "≥ " : "") + scientific(maxValue);
    $("legend-words").textContent = "Colour: how far each vertex moved, divided by the model's " +
      "bounding-box diagonal. Grey did not move; dark red moved " + percentOfSize(maxValue) +
      (capped ? " or more" : "") + " of the model's size" +
      (capped ? " (the largest move: " + percentOfSize(largest) + ")." : ".");
    legend.hidden = false;
  }

  async function preview(mesh, name, original, originalName) {
    const msg = $("view-msg");
    if (!viewer.ok) {
      msg.textContent = "This browser cannot draw the 3-D preview (WebGL is off or unavailable). " +
        "Marking and checking work all the same.";
      return null;
    }
    msg.textContent = "Loading the preview…";
    const files = [["mesh", mesh, name]];
    if (original) files.push(["original", original, originalName]);
    let res;
    try {
      res = await call("/v1/preview", { method: "POST", body: form({}, files) });
    } catch (e) {
      if (!(e instanceof ProblemShown)) throw e;
      if (original && e.problem.status === 413) {
        // both files in one request are over the server's limit: show the marked one alone
        const head = await preview(mesh, name);
        if (head) msg.textContent += " No heat map: the two files together are larger than one request may be.";
        return head;
      }
      msg.textContent = "No preview: " + e.problem.title + (e.problem.detail ? ". " + e.problem.detail : "");
      return null;
    }
    const p = parsePreview(await res.arrayBuffer());
    let values = null, top = null;
    if (p.displacement) {
      top = scaleTop(p.displacement);
      values = new Float32Array(p.displacement.length);
      if (top > 0) for (let i = 0; i < values.length; i++) values[i] = Math.min(p.displacement[i] / top, 1);
    }
    if (!viewer.show(p.positions, p.triangles, values, p.head.diagonal)) {
      msg.textContent = "This model is too large for this browser's 3-D preview.";
      return p.head;
    }
    showLegend(values ? top : null, p.head.max_displacement);
    msg.textContent = (values ? "Heat map of the watermark on " : "") + describeModel(p.head) +
      (original && !values && p.head.comparison ? ". No heat map: " + p.head.comparison : "") + ".";
    return p.head;
  }

  // ---- choosing a file ------------------------------------------------------------------------

  function setFile(file) {
    state.file = file;
    clearMessages();
    if (state.downloadUrl) { URL.revokeObjectURL(state.downloadUrl); state.downloadUrl = null; }
    $("marked").replaceChildren();
    $("file-info").textContent = file.name + ", " + formatBytes(file.size);
    const threshold = Number(document.body.dataset.jobThreshold || 8 * 1024 * 1024);
    $("background").checked = file.size > threshold;
    for (const b of document.querySelectorAll("button.act")) b.disabled = false;
    preview(file, file.name).catch(reportUnexpected);
  }

  $("mesh").addEventListener("change", () => { if ($("mesh").files.length) setFile($("mesh").files[0]); });

  const drop = $("drop");
  drop.addEventListener("dragover", e => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", e => {
    e.preventDefault();
    drop.classList.remove("over");
    if (e.dataTransfer.files.length) setFile(e.dataTransfer.files[0]);
  });

  // ---- the three actions ----------------------------------------------------------------------

  function needKey() {
    if ($("key").value) return true;
    showError("A watermark key is needed", "Type the secret key you mark with; the same key finds the mark.");
    $("key").focus();
    return false;
  }

  function fileNameFrom(res, fallback) {
    const m = /filename="([^"]+)"/.exec(res.headers.get("Content-Disposition") || "");
    return m ? m[1] : fallback;
  }

  async function doEmbed() {
    if (!needKey()) return;
    const file = state.file;
    const fields = { key: $("key").value, payload: $("payload").value.trim(), method: $("method").value,
                     strength: $("strength").value };
    const body = form(fields, [["mesh", file, file.name]]);
    setStatus("Marking " + file.name + "…");
    $("marked").replaceChildren();
    const res = $("background").checked ? await runJob("embed", body)
      : await call("/v1/embed", { method: "POST", body });
    const blob = await res.blob();
    const report = JSON.parse(res.headers.get("X-MeshMark-Report") || "{}");
    const name = fileNameFrom(res, "marked-" + file.name);
    if (state.downloadUrl) URL.revokeObjectURL(state.downloadUrl);
    state.downloadUrl = URL.createObjectURL(blob);
    const link = el("a", { href: state.downloadUrl, download: name, id: "download", class: "button" },
                    "Download " + name + " (" + formatBytes(blob.size) + ")");
    const payload = report.key_derived ? "the key's own " + report.payload_bits + "-bit code"
      : report.payload_bits + " bits of payload";
    $("result").replaceChildren(
      el("h3", {}, "Marked"),
      el("p", {}, "The mark (" + payload + ") is in " + grouped(report.carriers) + " vertices, " +
         Number(report.copies).toFixed(1) + " per codeword bit, with the " + report.method + " method."),
      el("p", {}, "Vertices moved: " + grouped(report.vertices_moved) + ". Typical move " +
         percentOfSize(report.rms_displacement) + " of the model's size, largest " +
         percentOfSize(report.max_displacement) + "."),
      el("p", { class: "hint" }, "Keep the key: without it nobody, you included, can find the mark."));
    $("marked").replaceChildren(link, " ", el("button", { type: "button", id: "check-marked", class: "act" },
                                                "Check the marked file"));
    $("check-marked").addEventListener("click", action(() => doDetect(new File([blob], name))));
    setStatus("Marked: " + name + " is ready to download.");
    preview(blob, name, file, file.name).catch(reportUnexpected);
  }

  function confidenceChart(conf, bits) {
    const ns = "http://www.w3.org/2000/svg";
    const n = conf.length, width = n * 10, height = 100, bw = width / n;
    const svg = document.createElementNS(ns, "svg");
    svg.setAttribute("viewBox", "0 0 " + width + " " + height);
    svg.setAttribute("preserveAspectRatio", "none");  // bars stretch to the chart's box
    svg.setAttribute("class", "chart");
    svg.setAttribute("role", "img");
    const low = Math.min(...conf), mean = conf.reduce((a, b) => a + b, 0) / n;
    const label = "Confidence of each of the " + n + " bits: lowest " + Math.round(low * 100) +
      " %, average " + Math.round(mean * 100) + " %.";
    svg.setAttribute("aria-label", label);
    const line = document.createElementNS(ns, "line");
    const middle = { x1: 0, x2: width, y1: height / 2, y2: height / 2, class: "half",
                     "vector-effect": "non-scaling-stroke" };
    for (const [k, v] of Object.entries(middle)) {
      line.setAttribute(k, v);
    }
    conf.forEach((c, i) => {
      // the bar's height: confidence from 50 % (a coin flip, no bar) to 100 % (full height)
      const h = Math.max(1, (Math.max(c, 0.5) - 0.5) * 2 * height);
      const r = document.createElementNS(ns, "rect");
      r.setAttribute("x", (i * bw + bw * 0.1).toFixed(2));
      r.setAttribute("width", (bw * 0.8).toFixed(2));
      r.setAttribute("y", (height - h).toFixed(2));
      r.setAttribute("height", h.toFixed(2));
      r.setAttribute("class", c >= 0.9 ? "sure" : c >= 0.7 ? "fair" : "weak");
      const t = document.createElementNS(ns, "title");
      t.textContent = "bit " + (i + 1) + (bits ? " = " + bits[i] : "") + ": " + (c * 100).toFixed(1) + " % sure";
      r.append(t);
      svg.append(r);
    });
    svg.append(line);
    return el("figure", {}, svg, el("figcaption", {}, label + " Bar height: 50 % (a coin flip) to 100 %; green bars are at least 90 % sure, " +
      "orange at least 70 %, red less."));
  }

  async function doDetect(file = state.file) {
    if (!needKey()) return;
    const body = form({ key: $("key").value, method: $("detect-method").value,
                        payload: $("expected").value.trim() }, [["mesh", file, file.name]]);
    setStatus("Looking for the mark in " + file.name + "…");
    const res = $("background").checked ? await runJob("detect", body)
      : await call("/v1/detect", { method: "POST", body });
    const r = await res.json();
    const out = [];
    if (r.detected) {
      out.push(el("h3", { class: "found" }, "Watermark found"));
      out.push(el("p", {}, r.key_derived
        ? "This file carries the mark of this key (the key's own code, no payload)."
        : "This file carries the mark of this key, with this payload:"));
      if (r.payload && !r.key_derived) out.push(el("p", {}, el("code", { id: "payload-found" }, r.payload)));
    } else {
      out.push(el("h3", { class: "absent" }, "No watermark found"));
      out.push(el("p", {}, "Nothing in this file matches this key. Either it was not marked with this key, or " +
        "it was changed too much for the mark to survive."));
    }
    const fp = r.false_positive_probability;
    out.push(el("p", {}, r.detected
      ? "How sure: a file without this mark would match this well by pure chance " + oneIn(fp) + "."
      : "The best match found is what chance alone gives (" + oneIn(fp).replace(/^about /, "") +
        " unmarked files would match as well)."));
    if (r.bit_errors !== null && r.bit_errors !== undefined) {
      out.push(el("p", {}, "Compared with the payload you expected: " + r.bit_errors + " bit" +
        (r.bit_errors === 1 ? "" : "s") + " differ."));
    }
    if (r.bit_confidence && r.bit_confidence.length) out.push(confidenceChart(r.bit_confidence, r.payload));
    out.push(el("p", { class: "hint" }, grouped(r.carriers) + " carrier vertices read" +
      (r.method ? " (" + r.method + " method)" : "") + "."));
    $("result").replaceChildren(...out);
    setStatus(r.detected ? "Watermark found." : "No watermark found.");
  }

  async function doCapacity() {
    const file = state.file;
    const body = form({ method: $("method").value, strength: $("strength").value }, [["mesh", file, file.name]]);
    setStatus("Measuring " + file.name + "…");
    const r = await (await call("/v1/capacity", { method: "POST", body })).json();
    $("result").replaceChildren(
      el("h3", {}, "Capacity"),
      el("p", {}, grouped(r.carriers) + " vertices can carry a bit (" + r.method + " method, strength " +
         r.strength + ")."),
      el("p", {}, r.max_payload_bits > 0 ? "Largest payload: " + r.max_payload_bits + " bits."
        : "Too few carriers for a payload; the key's own code only."),
      el("p", {}, "The key's own 32-bit code would be written " + Number(r.copies_of_default).toFixed(1) +
         " times. Expected moves: typical " + percentOfSize(r.expected_rms_displacement) + ", largest " +
         percentOfSize(r.expected_max_displacement) + " of the model's size."));
    setStatus("Capacity measured.");
  }

  function reportUnexpected(e) {
    if (e instanceof ProblemShown) showError(e.problem.title, e.problem.detail);
    else showError("Something went wrong in this page", String(e && e.message || e));
  }

  function action(fn) {
    return async event => {
      event.preventDefault();
      if (state.busy || !state.file) return;
      state.busy = true;
      clearMessages();
      for (const b of document.querySelectorAll("button.act")) b.disabled = true;
      try {
        await fn();
      } catch (e) {
        setStatus("");
        reportUnexpected(e);
      } finally {
        state.busy = false;
        for (const b of document.querySelectorAll("button.act")) b.disabled = false;
      }
    };
  }

  $("embed-form").addEventListener("submit", action(doEmbed));
  $("detect-form").addEventListener("submit", action(() => doDetect()));
  $("capacity-form").addEventListener("submit", action(doCapacity));
  $("cancel").addEventListener("click", () => {
    if (state.job) call(state.job, { method: "DELETE" }).catch(() => {});
  });

  if (!viewer.ok) {
    $("view-msg").textContent = "This browser cannot draw the 3-D preview (WebGL is off or unavailable). " +
      "Marking and checking work all the same.";
    $("view").hidden = true;
  }

  // Does this server want an API key?  Any /v1 route answers 401 before looking at the request.
  fetch("/v1/jobs/auth-check", { cache: "no-store" }).then(res => {
    if (res.status === 401) $("apikey-section").hidden = false;
  }).catch(() => {});
})();
