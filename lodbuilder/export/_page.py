"""The HTML, CSS and JavaScript of the standalone web page (:mod:`lodbuilder.export.web`).

One file, no outside resource: WebGL 1 draws the points (``gl.POINTS``, squares about 1.5 rho
wide, the viewer's rule); the data follows the script in base64 chunks, each followed by an
inline call that uploads it, so the browser draws the coarse prefix while it still parses the
rest. A Content-Security-Policy of ``default-src 'none'`` makes the browser refuse any request the
page could make (fetch, images, fonts...), so the page is offline by construction.

Placeholders filled by the writer: ``@TITLE@`` (HTML-escaped) and ``@HEADER@`` (JSON with ``<``
escaped).
"""

from __future__ import annotations

HEAD = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; img-src data:">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="lodbuilder">
<title>@TITLE@</title>
<link rel="icon" href="data:,">
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: #fff;
  font: 13px/1.4 system-ui, -apple-system, "Segoe UI", sans-serif; color: #111; }
#view { display: block; width: 100%; height: 100%; touch-action: none; }
.box { position: absolute; background: rgba(255, 255, 255, 0.88); padding: 6px 9px;
  border-radius: 4px; box-shadow: 0 0 3px rgba(0, 0, 0, 0.25); }
#panel { left: 8px; top: 8px; max-width: 46em; }
#panel label { margin-right: 10px; white-space: nowrap; }
#level { width: 16em; vertical-align: middle; }
#legend { right: 8px; top: 8px; display: none; text-align: center; }
#legend canvas { display: block; margin: 4px auto; border: 1px solid #999; }
#legendTitle { font-weight: 600; white-space: nowrap; }
#legendList { text-align: left; }
#legendList span { display: inline-block; width: 12px; height: 12px; margin-right: 6px;
  vertical-align: middle; border: 1px solid #777; }
#status { left: 8px; bottom: 8px; color: #444; }
#help { right: 8px; bottom: 8px; color: #666; font-size: 12px; }
</style>
</head>
<body>
<canvas id="view"></canvas>
<div id="panel" class="box">
  <div id="info"></div>
  <div><label>level <input id="level" type="range" min="0" max="0" value="0"></label><span id="levelText"></span></div>
  <div>
    <label>colour <select id="mode"></select></label>
    <label>point size <input id="psize" type="range" min="-2" max="2" step="0.1" value="0"></label>
    <label>up <select id="up"><option>z</option><option>y</option><option>x</option><option>-z</option><option>-y</option><option>-x</option></select></label>
  </div>
</div>
<div id="legend" class="box"><div id="legendTitle"></div><div id="legendScale"><div id="legendHi"></div>
<canvas id="legendBar" width="22" height="180"></canvas><div id="legendLo"></div></div><div id="legendList"></div></div>
<div id="status" class="box">loading...</div>
<div id="help" class="box">drag: turn &middot; shift/right drag: move &middot; wheel: zoom &middot; double click: reset</div>
<script id="lod-header" type="application/json">@HEADER@</script>
<script>
"use strict";
var LOD = (function () {  // (var: window.LOD, for the chunk scripts and tests)
  const H = JSON.parse(document.getElementById("lod-header").textContent);
  const N = H.n;
  // (state.history: the points drawn at each frame, coarse first while the file loads)
  const state = { loaded: 0, drawn: 0, ready: false, mode: "", error: null, history: [] };
  const $ = (id) => document.getElementById(id);
  const status = (t) => { $("status").textContent = t; };
  window.addEventListener("error", (e) => { state.error = String(e.message); status("error: " + e.message); });

  // ---- data kept on the CPU (colours are recomputed when the mode changes) ----
  const rgb = H.rgb ? new Uint8Array(3 * N) : null;
  const scalars = H.scalars.map(() => new Uint8Array(N));
  const cats = H.cats.map(() => new Uint8Array(N));
  // per category mode: 256 x rgb, listed labels in their colours, others mid grey
  const catLut = H.cats.map((c) => {
    const t = new Uint8Array(768).fill(150);
    for (const [v, , col] of c.table) { t[3 * v] = col[0]; t[3 * v + 1] = col[1]; t[3 * v + 2] = col[2]; }
    return t;
  });
  const colours = new Uint8Array(3 * N);
  const lut = H.lut;

  function b64(text) {
    if (Uint8Array.fromBase64) return Uint8Array.fromBase64(text.trim());
    const s = atob(text.trim()), out = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }

  // ---- WebGL ----
  const canvas = $("view");
  const gl = canvas.getContext("webgl", { antialias: false, preserveDrawingBuffer: true });
  if (!gl) { state.error = "no WebGL"; status("this browser has no WebGL: the points cannot be drawn"); }
  function shader(type, src) {
    const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  let prog, posBuf, colBuf, loc = {};
  if (gl) {
    prog = gl.createProgram();
    gl.attachShader(prog, shader(gl.VERTEX_SHADER,
      "attribute vec3 a_pos; attribute vec3 a_col; uniform mat4 u_mvp; uniform vec3 u_lo;" +
      "uniform vec3 u_span; uniform float u_size; varying vec3 v_col;" +
      "void main() { gl_Position = u_mvp * vec4(u_lo + a_pos * u_span, 1.0);" +
      " gl_PointSize = u_size; v_col = a_col; }"));
    gl.attachShader(prog, shader(gl.FRAGMENT_SHADER,
      "precision mediump float; varying vec3 v_col; void main() { gl_FragColor = vec4(v_col, 1.0); }"));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    for (const n of ["a_pos", "a_col"]) loc[n] = gl.getAttribLocation(prog, n);
    for (const n of ["u_mvp", "u_lo", "u_span", "u_size"]) loc[n] = gl.getUniformLocation(prog, n);
    posBuf = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, posBuf);
    gl.bufferData(gl.ARRAY_BUFFER, 6 * N, gl.STATIC_DRAW);
    colBuf = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, colBuf);
    gl.bufferData(gl.ARRAY_BUFFER, 3 * N, gl.DYNAMIC_DRAW);
  }

  // ---- colour modes ----
  const modes = [];
  if (H.rgb) modes.push({ key: "rgb", label: "RGB" });
  H.scalars.forEach((s, i) => modes.push({ key: "s" + i, label: s.label, scalar: i }));
  H.cats.forEach((c, i) => modes.push({ key: "c" + i, label: c.label, cat: i }));
  modes.push({ key: "rank", label: "rank" });
  const modeSel = $("mode");
  for (const m of modes) { const o = document.createElement("option"); o.value = m.key; o.textContent = m.label; modeSel.appendChild(o); }
  let mode = modes[0];
  state.mode = mode.key;

  function fillColours(start, end) {
    if (mode.key === "rgb") { colours.set(rgb.subarray(3 * start, 3 * end), 3 * start); return; }
    if (mode.cat !== undefined) {
      const t = catLut[mode.cat], c = cats[mode.cat];
      for (let i = start; i < end; i++) { const v = 3 * c[i]; colours[3 * i] = t[v]; colours[3 * i + 1] = t[v + 1]; colours[3 * i + 2] = t[v + 2]; }
      return;
    }
    const logN = Math.log(Math.max(H.n_total, 2));
    const remap = mode.scalar === 0 ? radiusRemap() : null;
    for (let i = start; i < end; i++) {
      let t = mode.key === "rank" ? Math.min(255, Math.floor(255 * Math.log(i + 1) / logN)) : scalars[mode.scalar][i];
      if (remap) t = remap[t];
      colours[3 * i] = lut[3 * t]; colours[3 * i + 1] = lut[3 * t + 1]; colours[3 * i + 2] = lut[3 * t + 2];
    }
  }
  // radius: its scale follows the level shown, from its rho to the rho where it had 1/64 of
  // its points (the page-wide scale drew a uniform level in one colour); finer points get the
  // lowest colour, the level's coarsest the highest
  function radiusRange() {
    const s = H.scalars[0], [k, rho] = current();
    let top = -1;
    for (const [sk, sr] of H.steps) if (sk <= Math.max(1, Math.floor(k / 64))) top = sr;
    const lo = rho > 0 ? Math.min(Math.max(rho, s.lo), s.hi) : s.lo;
    const hi = top > lo ? Math.min(top, s.hi) : s.hi;
    return [lo, hi > lo ? hi : lo * 1.000001];
  }
  function radiusRemap() {
    const s = H.scalars[0], [lo, hi] = radiusRange(), out = new Uint8Array(256);
    const a = Math.log(s.lo), b = Math.log(s.hi) - a, c = Math.log(lo), d = Math.log(hi) - c;
    for (let t = 0; t < 256; t++) {
      const v = a + (t / 255) * b;
      out[t] = Math.max(0, Math.min(255, Math.round(255 * (v - c) / (d || 1))));
    }
    return out;
  }
  function uploadColours(start, end) {
    if (!gl || end <= start) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, colBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 3 * start, colours.subarray(3 * start, 3 * end));
  }
  function fmt(v) { return Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(2) : String(+v.toPrecision(3)); }
  function legend() {
    const box = $("legend");
    const list = $("legendList");
    while (list.firstChild) list.removeChild(list.firstChild);
    if (mode.cat !== undefined) {  // named swatches (textContent only: names come from files)
      const c = H.cats[mode.cat];
      box.style.display = "block";
      $("legendScale").style.display = "none";
      $("legendTitle").textContent = c.title;
      for (const [, name, col] of c.table) {
        const row = document.createElement("div"), sw = document.createElement("span");
        sw.style.background = "rgb(" + col[0] + "," + col[1] + "," + col[2] + ")";
        row.appendChild(sw); row.appendChild(document.createTextNode(name)); list.appendChild(row);
      }
      return;
    }
    const spec = mode.key === "rank" ? H.rank : (mode.scalar !== undefined ? H.scalars[mode.scalar] : null);
    if (!spec) { box.style.display = "none"; return; }
    box.style.display = "block";
    $("legendScale").style.display = "block";
    $("legendTitle").textContent = spec.title;
    const [lo, hi] = mode.scalar === 0 ? radiusRange() : [spec.lo, spec.hi];
    $("legendHi").textContent = fmt(hi);
    $("legendLo").textContent = fmt(lo);
    const c = $("legendBar"), g = c.getContext("2d");
    for (let y = 0; y < c.height; y++) {
      const t = Math.round(255 * (1 - y / (c.height - 1)));
      g.fillStyle = "rgb(" + lut[3 * t] + "," + lut[3 * t + 1] + "," + lut[3 * t + 2] + ")";
      g.fillRect(0, y, c.width, 1);
    }
  }
  modeSel.addEventListener("change", () => {
    mode = modes.find((m) => m.key === modeSel.value); state.mode = mode.key;
    fillColours(0, state.loaded); uploadColours(0, state.loaded); legend(); redraw();
  });

  // ---- levels: the slider walks the stops of H.steps ([k, rho], k ascending) ----
  const level = $("level");
  level.max = String(H.steps.length - 1);
  level.value = level.max;
  function current() { return H.steps[+level.value]; }
  function levelText() {
    const [k, rho] = current(), shown = Math.min(k, state.loaded);
    const pct = (100 * k / H.n_total).toPrecision(3);
    // rho < 0: the next point starts a piece of its own, so no bound holds yet
    const bound = rho > 0 ? fmt(rho) + " " + H.unit : (rho < 0 ? "none yet (new pieces follow)" :
      (k >= H.n_total ? "0 (every point)" : "0"));
    $("levelText").textContent = " " + shown.toLocaleString("en") + " of " + H.n_total.toLocaleString("en") +
      " points (" + pct + " %), rho = " + bound + (shown < k ? " (loading)" : "");
    if (state.ready) status(shown.toLocaleString("en") + " of " + N.toLocaleString("en") + " points drawn" +
      (N < H.n_total ? " (the level's prefix: coarse to fine)" : ""));
  }
  level.addEventListener("input", () => {
    if (mode.scalar === 0) { fillColours(0, state.loaded); uploadColours(0, state.loaded); legend(); }
    redraw();
  });
  $("psize").addEventListener("input", redraw);

  // ---- camera: orbit around the centre of the bounding box ----
  // the first view faces the scan (lodbuilder.viewer.data.facing_camera, as yaw and pitch)
  const cam = { yaw: H.view[0], pitch: H.view[1], dist: 2.0 * H.diag, target: [0, 0, 0] };
  const upSel = $("up");
  upSel.value = H.up;
  upSel.addEventListener("change", redraw);
  function basis() {
    const u = upSel.value, s = u[0] === "-" ? -1 : 1, a = "xyz".indexOf(u[u.length - 1]);
    const U = [0, 0, 0]; U[a] = s;
    const A = [0, 0, 0]; A[(a + 1) % 3] = 1;
    const B = [0, 0, 0]; B[(a + 2) % 3] = s;
    return [U, A, B];
  }
  const add = (p, q, f) => [p[0] + f * q[0], p[1] + f * q[1], p[2] + f * q[2]];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
  function eyeFrame() {
    const [U, A, B] = basis(), cp = Math.cos(cam.pitch);
    let d = add(add([0, 0, 0], A, cp * Math.cos(cam.yaw)), B, cp * Math.sin(cam.yaw));
    d = add(d, U, Math.sin(cam.pitch));
    const eye = add(cam.target, d, cam.dist);
    const f = norm([-d[0], -d[1], -d[2]]), r = norm(cross(f, U)), up = cross(r, f);
    return { eye, f, r, up };
  }
  function matrix(aspect) {
    const { eye, f, r, up } = eyeFrame();
    const near = cam.dist / 100, far = cam.dist + 4 * H.diag, t = 1 / Math.tan(Math.PI / 12);
    const P = [t / aspect, 0, 0, 0, 0, t, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
    const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    const V = [r[0], up[0], -f[0], 0, r[1], up[1], -f[1], 0, r[2], up[2], -f[2], 0, -dot(r, eye), -dot(up, eye), dot(f, eye), 1];
    const M = new Float32Array(16);
    for (let c = 0; c < 4; c++) for (let i = 0; i < 4; i++) {
      let s = 0; for (let k = 0; k < 4; k++) s += P[k * 4 + i] * V[c * 4 + k]; M[c * 4 + i] = s;
    }
    return M;
  }
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 }; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y; drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const { r, up } = eyeFrame(), s = cam.dist * 0.0015;
      cam.target = add(add(cam.target, r, -dx * s), up, dy * s);
    } else {
      cam.yaw -= dx * 0.008;
      cam.pitch = Math.max(-1.55, Math.min(1.55, cam.pitch + dy * 0.008));
    }
    redraw();
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); cam.dist *= Math.exp(e.deltaY * 0.001); redraw(); }, { passive: false });
  canvas.addEventListener("dblclick", () => { cam.yaw = H.view[0]; cam.pitch = H.view[1]; cam.dist = 2.0 * H.diag; cam.target = [0, 0, 0]; redraw(); });

  // ---- drawing ----
  let pending = false;
  function redraw() { levelText(); if (!pending) { pending = true; requestAnimationFrame(draw); } }
  function draw() {
    pending = false;
    if (!gl) return;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, w, h);
    gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    const [k, rho] = current(), count = Math.min(k, state.loaded);
    if (count > 0) {
      gl.useProgram(prog);
      gl.uniformMatrix4fv(loc.u_mvp, false, matrix(w / h));
      gl.uniform3fv(loc.u_lo, H.lo);
      gl.uniform3fv(loc.u_span, H.span);
      const px = h / (2 * cam.dist * Math.tan(Math.PI / 12));
      const size = 1.5 * Math.max(rho, H.spacing) * px * Math.pow(2, +$("psize").value);
      gl.uniform1f(loc.u_size, Math.min(64, Math.max(1, size)));
      gl.bindBuffer(gl.ARRAY_BUFFER, posBuf);
      gl.enableVertexAttribArray(loc.a_pos);
      gl.vertexAttribPointer(loc.a_pos, 3, gl.UNSIGNED_SHORT, true, 6, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, colBuf);
      gl.enableVertexAttribArray(loc.a_col);
      gl.vertexAttribPointer(loc.a_col, 3, gl.UNSIGNED_BYTE, true, 3, 0);
      gl.drawArrays(gl.POINTS, 0, count);
    }
    state.drawn = count;
    state.history.push(count);
  }
  window.addEventListener("resize", redraw);

  // ---- data chunks, in farthest-point order: each one refines the picture ----
  function chunk(i) {
    const el = $("c" + i), [start, end] = H.chunks[i], n = end - start;
    const bytes = b64(el.textContent);
    el.remove();
    if (bytes.length !== H.bytes_per_point * n) throw new Error("chunk " + i + " has " + bytes.length + " bytes, expected " + H.bytes_per_point * n);
    if (gl) { gl.bindBuffer(gl.ARRAY_BUFFER, posBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 6 * start, bytes.subarray(0, 6 * n)); }
    let off = 6 * n;
    if (rgb) { rgb.set(bytes.subarray(off, off + 3 * n), 3 * start); off += 3 * n; }
    for (const s of scalars) { s.set(bytes.subarray(off, off + n), start); off += n; }
    for (const c of cats) { c.set(bytes.subarray(off, off + n), start); off += n; }
    fillColours(start, end); uploadColours(start, end);
    state.loaded = end;
    status("loaded " + end.toLocaleString("en") + " of " + N.toLocaleString("en") + " points...");
    redraw();
  }
  function done() {
    requestAnimationFrame(() => { draw(); state.ready = true; levelText(); });
  }
  $("info").textContent = H.info;
  legend();
  redraw();
  return { chunk, done, state };
})();
</script>
"""

TAIL = """<script>LOD.done();</script>
</body>
</html>
"""
