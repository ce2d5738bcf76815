// phantom-calib view: a small WebGL2 renderer of the calibrated phantom (no dependencies).
// The surrogate runs in the Python server (/api/predict); this file draws what it returns.
"use strict";
(function () {
  const $ = (id) => document.getElementById(id);
  const canvas = $("gl");
  // Multisampling on a real GPU; off on the software rasteriser (SwiftShader: headless
  // Chromium, machines without a GPU), where MSAA in software added 5-15 ms to the median
  // control-to-frame latency (benchmarks/bench_view.py --aa 0|1). ?aa=1 or ?aa=0 overrides.
  function softwareGL() {
    const probe = document.createElement("canvas").getContext("webgl2");
    if (!probe) return false;
    const ext = probe.getExtension("WEBGL_debug_renderer_info");
    const name = String(probe.getParameter(ext ? ext.UNMASKED_RENDERER_WEBGL : probe.RENDERER));
    probe.getExtension("WEBGL_lose_context")?.loseContext();
    return /swiftshader|llvmpipe|software/i.test(name);
  }
  const aaParam = new URLSearchParams(location.search).get("aa");
  const antialias = aaParam === null ? !softwareGL() : aaParam === "1";
  const gl = canvas.getContext("webgl2", { antialias });
  const V = (window.viewer = {
    ready: null, state: { gravity: [0, 0, 0], c1: null, scan: "", overlay: "none" }, antialias,
    latencies: [], frames: 0, scene: null, error: null,
  });
  const DEG = Math.PI / 180;

  // ---------- shaders ----------
  const VS = `#version 300 es
  in vec3 pos; in vec3 nrm; in float val;
  uniform mat4 mvp; uniform float psize;
  out vec3 vn; out float vv;
  void main() { gl_Position = mvp * vec4(pos, 1.0); vn = nrm; vv = val; gl_PointSize = psize; }`;
  const FS = `#version 300 es
  precision highp float;
  in vec3 vn; in float vv; out vec4 o;
  uniform vec4 color; uniform int mode; uniform float vmax; uniform vec3 light;
  vec3 cmap(float t) { // RdBu_r, 5 samples (matplotlib), linear in between: the reports' map
    vec3 c0 = vec3(0.020, 0.188, 0.380), c1 = vec3(0.421, 0.676, 0.819),
         c2 = vec3(0.969, 0.966, 0.965), c3 = vec3(0.895, 0.504, 0.400),
         c4 = vec3(0.404, 0.000, 0.122);
    t = clamp(t, 0.0, 1.0) * 4.0;
    if (t < 1.0) return mix(c0, c1, t); if (t < 2.0) return mix(c1, c2, t - 1.0);
    if (t < 3.0) return mix(c2, c3, t - 2.0); return mix(c3, c4, t - 3.0);
  }
  void main() {
    if (mode == 2) { vec2 d = gl_PointCoord - 0.5; if (dot(d, d) > 0.25) discard;
      if (color.a < 0.5 && dot(d, d) < 0.09) discard; o = vec4(color.rgb, 1.0); return; }
    if (mode == 3) { o = color; return; }
    vec3 n = normalize(vn); float l = 0.35 + 0.65 * abs(dot(n, light));
    // the signed distance, + where the scan lies outside the model (calib.report.maps)
    vec3 base = mode == 1 ? cmap(0.5 + 0.5 * vv / vmax) : color.rgb;
    o = vec4(base * l, color.a);
  }`;
  function compile(type, src) {
    const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  let prog, loc;
  function initGL() {
    prog = gl.createProgram();
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    loc = {};
    for (const a of ["pos", "nrm", "val"]) loc[a] = gl.getAttribLocation(prog, a);
    for (const u of ["mvp", "psize", "color", "mode", "vmax", "light"])
      loc[u] = gl.getUniformLocation(prog, u);
    gl.enable(gl.DEPTH_TEST);
  }

  // ---------- meshes ----------
  function makeMesh(pos, idx, val) {
    const m = { n: pos.length / 3, count: idx ? idx.length : pos.length / 3, vao: gl.createVertexArray() };
    gl.bindVertexArray(m.vao);
    m.pbuf = gl.createBuffer(); m.nbuf = gl.createBuffer(); m.vbuf = gl.createBuffer();
    for (const [buf, a, k] of [[m.pbuf, loc.pos, 3], [m.nbuf, loc.nrm, 3], [m.vbuf, loc.val, 1]]) {
      gl.bindBuffer(gl.ARRAY_BUFFER, buf);
      gl.bufferData(gl.ARRAY_BUFFER, (k * m.n) * 4, gl.DYNAMIC_DRAW);
      if (a >= 0) { gl.enableVertexAttribArray(a); gl.vertexAttribPointer(a, k, gl.FLOAT, false, 0, 0); }
    }
    if (idx) {
      m.ibuf = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, m.ibuf);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW); m.idx = idx;
    }
    gl.bindVertexArray(null);
    setPositions(m, pos);
    setValues(m, val || new Float32Array(m.n));
    return m;
  }
  function normals(pos, idx) {
    const n = new Float32Array(pos.length);
    for (let f = 0; f < idx.length; f += 3) {
      const a = 3 * idx[f], b = 3 * idx[f + 1], c = 3 * idx[f + 2];
      const ux = pos[b] - pos[a], uy = pos[b + 1] - pos[a + 1], uz = pos[b + 2] - pos[a + 2];
      const vx = pos[c] - pos[a], vy = pos[c + 1] - pos[a + 1], vz = pos[c + 2] - pos[a + 2];
      const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      for (const i of [a, b, c]) { n[i] += nx; n[i + 1] += ny; n[i + 2] += nz; }
    }
    return n;
  }
  function setPositions(m, pos) {
    gl.bindBuffer(gl.ARRAY_BUFFER, m.pbuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, pos);
    if (m.idx) { gl.bindBuffer(gl.ARRAY_BUFFER, m.nbuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, normals(pos, m.idx)); }
    m.pos = pos;
  }
  function setValues(m, val) { gl.bindBuffer(gl.ARRAY_BUFFER, m.vbuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, val); }

  // ---------- camera ----------
  const cam = { yaw: -40 * DEG, pitch: 25 * DEG, dist: 300, center: [0, 0, 0] };
  function mat4mul(a, b) {
    const o = new Float32Array(16);
    for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) {
      let s = 0; for (let k = 0; k < 4; k++) s += a[k * 4 + j] * b[i * 4 + k]; o[i * 4 + j] = s;
    }
    return o;
  }
  function viewProj() {
    const w = canvas.clientWidth, h = canvas.clientHeight, aspect = w / Math.max(h, 1);
    const f = 1 / Math.tan(22 * DEG), near = cam.dist / 50, far = cam.dist * 10;
    const P = new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1,
      0, 0, (2 * far * near) / (near - far), 0]);
    // eye on a sphere about the centre; up = -z of the phantom frame shown up (gravity "down" at prone)
    const cy = Math.cos(cam.yaw), sy = Math.sin(cam.yaw), cp = Math.cos(cam.pitch), sp = Math.sin(cam.pitch);
    const fwd = [-cp * cy, -cp * sy, sp];               // from eye to centre
    const eye = cam.center.map((c, i) => c - cam.dist * fwd[i]);
    const up0 = [0, 0, -1];
    const r = norm3(cross(fwd, up0)), u = cross(r, fwd);
    const W = new Float32Array([r[0], u[0], -fwd[0], 0, r[1], u[1], -fwd[1], 0, r[2], u[2], -fwd[2], 0,
      -dot(r, eye), -dot(u, eye), dot(fwd, eye), 1]);
    const M = mat4mul(P, W); M.fwd = fwd; M.right = r; M.up = u; return M;
  }
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm3 = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
  let drag = null;
  canvas.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; });
  window.addEventListener("mouseup", () => { drag = null; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    cam.yaw -= (e.clientX - drag[0]) * 0.01;
    cam.pitch = Math.max(-1.5, Math.min(1.5, cam.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY]; draw();
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); cam.dist *= Math.exp(e.deltaY * 0.001); draw(); },
    { passive: false });

  // ---------- scene ----------
  let model = null, overlay = null, points = null, lines = null, plate = null, vmax = 1;
  // The back plate: the plane of the clamped back nodes (the scene's plate_z_mm; the phantom
  // frame's z points from the plate into the breast), drawn as a grid of PLATE_MM squares a
  // little wider than the body (review AX: no plate, no scale).
  const PLATE_MM = 10;
  function plateGrid(lo, hi, z) {
    const pad = [0, 1].map((i) => 0.15 * (hi[i] - lo[i]));
    const a = [0, 1].map((i) => PLATE_MM * Math.floor((lo[i] - pad[i]) / PLATE_MM));
    const b = [0, 1].map((i) => PLATE_MM * Math.ceil((hi[i] + pad[i]) / PLATE_MM));
    const v = [];
    for (let x = a[0]; x <= b[0] + 1e-6; x += PLATE_MM) v.push(x, a[1], z, x, b[1], z);
    for (let y = a[1]; y <= b[1] + 1e-6; y += PLATE_MM) v.push(a[0], y, z, b[0], y, z);
    return { z, spacing_mm: PLATE_MM, x_mm: [a[0], b[0]], y_mm: [a[1], b[1]], pos: new Float32Array(v) };
  }
  const marks = { nipple: null, tumour: null, fiducials: [], mNipple: null, mTumour: null };
  // review CD-9: the phantom frame's axes as the camera turns them (the panel speaks of
  // the x-z plane and +y; the camera puts -z up, the plate above the breast)
  function drawAxes(M) {
    const L = 20, c = 34, colours = ["#c0392b", "#27ae60", "#2c6fbb"];
    let svg = "";
    for (let i = 0; i < 3; i++) {
      const e = [0, 0, 0]; e[i] = 1;
      const x = c + L * dot(M.right, e), y = c - L * dot(M.up, e);
      svg += `<line x1="${c}" y1="${c}" x2="${x.toFixed(1)}" y2="${y.toFixed(1)}" stroke="${colours[i]}" stroke-width="2"/>`;
      svg += `<text x="${(c + 1.3 * (x - c)).toFixed(1)}" y="${(c + 1.3 * (y - c) + 4).toFixed(1)}" fill="${colours[i]}" font-size="12" text-anchor="middle">${"xyz"[i]}</text>`;
    }
    $("axes").innerHTML = svg;
  }
  function draw() {
    const w = Math.round(canvas.clientWidth * devicePixelRatio), h = Math.round(canvas.clientHeight * devicePixelRatio);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.96, 0.96, 0.95, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!model && !overlay) return;
    const M = viewProj();
    drawAxes(M);
    gl.useProgram(prog);
    gl.uniformMatrix4fv(loc.mvp, false, M);
    gl.uniform3fv(loc.light, M.fwd);
    gl.uniform1f(loc.psize, 11 * devicePixelRatio);
    gl.uniform1f(loc.vmax, vmax);
    const ov = V.state.overlay;
    // a scan without the map asked for: its measured surface, not a map of zeros
    const isMap = overlay && (ov === "error_mm" || ov === "error_after_mm") && !!overlay.maps[ov];
    // error maps: the measured surface coloured alone (a model over it would tint the colours);
    // "measured": the model opaque, the measured surface translucent blue over it
    if (plate) {
      gl.uniform1i(loc.mode, 3); gl.uniform4f(loc.color, 0.62, 0.62, 0.6, 1);
      gl.bindVertexArray(plate.vao); gl.drawArrays(gl.LINES, 0, plate.n);
    }
    if (model && $("show_model").checked && !isMap) {
      gl.uniform1i(loc.mode, 0); gl.uniform4f(loc.color, 0.86, 0.72, 0.62, 1);
      gl.bindVertexArray(model.vao); gl.drawElements(gl.TRIANGLES, model.count, gl.UNSIGNED_INT, 0);
    }
    if (overlay && ov !== "none") {
      gl.uniform1i(loc.mode, isMap ? 1 : 0);
      gl.uniform4f(loc.color, 0.3, 0.5, 0.95, isMap ? 1 : 0.45);
      if (!isMap) { gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false); }
      const nc = isMap ? 3 * overlay.nScored : overlay.count;
      gl.bindVertexArray(overlay.vao); gl.drawElements(gl.TRIANGLES, nc, gl.UNSIGNED_INT, 0);
      if (nc < overlay.count) {  // faces on the back plate or a cut field of view: not scored,
        // dark grey (a light one read as the signed map's white, 0 mm, once shaded)
        gl.uniform1i(loc.mode, 0); gl.uniform4f(loc.color, 0.42, 0.42, 0.42, 1);
        gl.drawElements(gl.TRIANGLES, overlay.count - nc, gl.UNSIGNED_INT, 4 * nc);
      }
      gl.disable(gl.BLEND); gl.depthMask(true);
    }
    // markers and the gravity arrow, on top
    gl.disable(gl.DEPTH_TEST);
    const pts = [], cols = [];
    const add = (p, c) => { if (p && isFinite(p[0])) { pts.push(p); cols.push(c); } };
    add(marks.nipple, [0.85, 0.1, 0.1, 1]); add(marks.tumour, [0.8, 0.1, 0.8, 1]);
    for (const f of marks.fiducials) add(f, [0.1, 0.6, 0.2, 1]);
    if (ov !== "none") { add(marks.mNipple, [0.85, 0.1, 0.1, 0]); add(marks.mTumour, [0.8, 0.1, 0.8, 0]); }
    gl.uniform1i(loc.mode, 2);
    for (let i = 0; i < pts.length; i++) {
      setPositions(points, new Float32Array(pts[i])); gl.uniform4fv(loc.color, cols[i]);
      gl.bindVertexArray(points.vao); gl.drawArrays(gl.POINTS, 0, 1);
    }
    const g = V.state.gravity, gn = Math.hypot(g[0], g[1], g[2]);
    if (gn > 0) {
      const c = cam.center, L = cam.dist * 0.25;
      const tip = c.map((x, i) => x + (L * g[i]) / gn);
      setPositions(lines, new Float32Array([...c, ...tip]));
      gl.uniform1i(loc.mode, 3); gl.uniform4f(loc.color, 0.1, 0.2, 0.9, 1);
      gl.bindVertexArray(lines.vao); gl.drawArrays(gl.LINES, 0, 2);
      gl.uniform1i(loc.mode, 2); setPositions(points, new Float32Array(tip));
      gl.bindVertexArray(points.vao); gl.drawArrays(gl.POINTS, 0, 1);
    }
    gl.enable(gl.DEPTH_TEST);
    gl.bindVertexArray(null);
    V.frames++;
  }
  V.draw = draw;

  // Read a displayed vertex back from the GPU buffer (WebGL2 getBufferSubData), phantom frame mm.
  V.readVertex = function (i) {
    const out = new Float32Array(3);
    gl.bindBuffer(gl.ARRAY_BUFFER, model.pbuf); gl.getBufferSubData(gl.ARRAY_BUFFER, 12 * i, out);
    return Array.from(out);
  };
  V.nVertices = () => (model ? model.n : 0);

  // ---------- controls ----------
  function gravityFromAngles(a, s, g) {           // phantom frame, m/s^2
    const ca = Math.cos(a * DEG), sa = Math.sin(a * DEG), cs = Math.cos(s * DEG), ss = Math.sin(s * DEG);
    return [g * ca * cs, g * ss, g * sa * cs];
  }
  function anglesFromGravity(v) {
    const n = Math.hypot(v[0], v[1], v[2]) || 1;
    const s = Math.asin(Math.max(-1, Math.min(1, v[1] / n))) / DEG;
    let a = Math.atan2(v[2], v[0]) / DEG; if (a < 0) a += 360;
    return [a, s];
  }
  let c1Touched = false;  // until the c1 slider moves: the calibrated c1 exactly
  function c1FromSlider() {
    const r = V.scene.model.c1_range_pa, t = Number($("c1").value) / 1000;
    return r[0] === r[1] || !c1Touched ? V.scene.model.c1_pa : r[0] * Math.pow(r[1] / r[0], t);
  }
  let postureGravity = null;  // a scan's exact gravity, until a gravity slider moves
  function readControls() {
    const a = Number($("angle_a").value), s = Number($("angle_s").value);
    V.state.gravity = postureGravity ? postureGravity.slice() : gravityFromAngles(a, s, V.scene.g_m_s2);
    $("a_val").textContent = a.toFixed(1) + "°"; $("s_val").textContent = s.toFixed(1) + "°";
    if (V.scene.model) { V.state.c1 = c1FromSlider(); $("c1_val").textContent = V.state.c1.toFixed(1); }
    if (!V.scene.model && !postureGravity) {
      // review AG: without a surrogate the shape shown without a saved state is the
      // stress-free one, under no gravity
      V.state.gravity = [0, 0, 0];
      $("gvec").textContent = "the stress-free shape (no gravity)";
      // review AX: the disabled sliders' 90° read as the shape's posture
      $("a_val").textContent = "–"; $("s_val").textContent = "–";
      return;
    }
    const g = V.state.gravity;
    $("gvec").textContent = `g (phantom frame) = (${g.map((x) => x.toFixed(3)).join(", ")}) m/s²`;
  }

  // One request in flight; the newest control state wins.
  // the status line's c1 words: its trained range, or why it is fixed (c1Fixed, else "")
  let inflight = false, pending = null, trainedC1 = "", c1Fixed = "";
  const errorText = (e) => (e && e.message ? e.message : String(e));
  function onControl(ev) {
    const t0 = ev && ev.timeStamp > 0 ? ev.timeStamp : performance.now();
    readControls();
    if (!V.scene.model) return;
    pending = { g: V.state.gravity.slice(), c1: V.state.c1, t0, moved: !!ev };
    if (!inflight) pump();
  }
  async function pump() {
    inflight = true;
    try { await pumpAll(); } catch (e) {
      // review CD-7: a failed fetch left `inflight` set, and every later control change
      // was dropped without a word; review CE-9: only a failed fetch (a TypeError) is
      // the server's silence
      pending = null;
      const why = errorText(e);
      $("warn").textContent = e instanceof TypeError ? `the view's server did not answer (${why}): is phantom-calib view still running?` : `error: ${why}`;
    } finally {
      inflight = false;
      if (V._waiters) { const w = V._waiters; V._waiters = []; w.forEach((f) => f()); }
    }
  }
  async function pumpAll() {
    while (pending) {
      const q = pending; pending = null;
      const tf = performance.now();
      const r = await fetch(`/api/predict?g=${q.g.join(",")}&c1=${q.c1}`);
      if (!r.ok) { $("warn").textContent = (await r.json()).error; continue; }
      const buf = new Float32Array(await r.arrayBuffer());
      const fetchMs = performance.now() - tf;
      const n = model.n;
      const extra = r.headers.get("X-Extrapolating") === "1";
      // draw at once (into the drawing buffer) and count the frame as drawn at the next
      // animation frame, the one that composites it (benchmarks/bench_view.py)
      const td = performance.now();
      setPositions(model, buf.subarray(0, 3 * n));
      marks.nipple = Array.from(buf.subarray(3 * n, 3 * n + 3));
      marks.tumour = Array.from(buf.subarray(3 * n + 3, 3 * n + 6));
      draw();
      const drawMs = performance.now() - td;
      await new Promise((res) => requestAnimationFrame(() => {
        const dt = performance.now() - q.t0;
        V.latencies.push(dt);
        V.lastFrame = { gravity: q.g, c1: q.c1, latency_ms: dt, fetch_ms: fetchMs, draw_ms: drawMs, extrapolating: extra };
        // review CD-12: the first frame said "after the control moved" with nothing moved
        // review CE-10: a fixed c1 keeps saying why after a slider moved
        $("status").textContent = q.moved ? `surrogate prediction drawn ${dt.toFixed(0)} ms after the control moved${c1Fixed && "; " + c1Fixed}` : `surrogate ${V.scene.model.kind} prediction drawn; ${trainedC1}`;
        $("warn").textContent = [extra ? "outside the surrogate's trained range: it extrapolates" : "", overlayNote].filter(Boolean).join("; ");
        res();
      }));
    }
  }
  // Resolves once every pending control change has been drawn.
  V.settled = () => new Promise((res) => { if (!inflight && !pending) res(); else (V._waiters ||= []).push(res); });

  async function showState(name) {   // no surrogate: the saved FE states
    if (!model) return;
    if (!name) {
      setPositions(model, V.rest); marks.nipple = V.restNipple; marks.tumour = V.scene.landmarks.tumour_rest_mm;
      draw(); return;
    }
    const r = await fetch(`/api/state/${encodeURIComponent(name)}`);
    if (!r.ok) { $("warn").textContent = (await r.json()).error; return; }
    const buf = new Float32Array(await r.arrayBuffer()), n = model.n;
    setPositions(model, buf.subarray(0, 3 * n));
    marks.nipple = Array.from(buf.subarray(3 * n, 3 * n + 3)); marks.tumour = Array.from(buf.subarray(3 * n + 3, 3 * n + 6));
    $("status").textContent = `saved FE state of ${name} (calibrate, c1 = ${V.scene.c1_pa.toFixed(1)} Pa)`;
    draw();
  }
  async function loadOverlay(name) {
    overlay = null; overlayNote = ""; $("bar").style.display = "none";
    const sc = V.scene.scans.find((s) => s.name === name);
    marks.mNipple = sc ? sc.nipple_mm : null; marks.mTumour = sc ? sc.tumour_mm : null;
    if (!sc) { draw(); return; }
    const r = await fetch(`/api/overlay/${encodeURIComponent(name)}`);
    if (!r.ok) { draw(); return; }
    const lay = JSON.parse(r.headers.get("X-Layout")), buf = await r.arrayBuffer();
    const nv = lay.n_vertices, nf = lay.n_faces;
    const pos = new Float32Array(buf, 0, 3 * nv), idx = new Uint32Array(buf, 12 * nv, 3 * nf);
    const maps = {};
    lay.maps.forEach((k, j) => { maps[k] = new Float32Array(buf, 12 * nv + 12 * nf + 4 * nv * j, nv); });
    overlay = makeMesh(pos, idx, null); overlay.maps = maps;
    overlay.nScored = lay.n_scored_faces;
    overlay.scored = new Uint8Array(nv);  // the vertices of the scored faces (listed first)
    for (let i = 0; i < 3 * overlay.nScored; i++) overlay.scored[idx[i]] = 1;
    applyOverlayMode();
  }
  let overlayNote = "";  // why the overlay is not what was asked for (kept past each frame)
  function applyOverlayMode() {
    overlayNote = "";
    V.state.overlay = $("overlay").value;
    const k = V.state.overlay;
    if (overlay && (k === "error_mm" || k === "error_after_mm")) {
      const m = overlay.maps[k];
      if (!m) {
        overlayNote = (k === "error_after_mm" ? "no diagnose refit map for this scan (run `phantom-calib diagnose`)" : "no error map for this scan (no FE state: the reference, or a failed solve)") + ": its measured surface shown";
        $("warn").textContent = overlayNote; $("bar").style.display = "none";
      }
      else {
        // one scale for before and after (as diagnose's figures): the 99th percentile of
        // |error| before, over the vertices of the scored faces (the rest are 0, not compared)
        const ref = overlay.maps.error_mm || m;
        const s = Array.from(ref).filter((x, i) => overlay.scored[i]).map(Math.abs).sort((x, y) => x - y);
        vmax = s.length ? Math.max(s[Math.floor(0.99 * (s.length - 1))], 1e-6) : 1;
        setValues(overlay, m); showBar(vmax, k);
      }
    } else $("bar").style.display = "none";
    if (!overlay && k !== "none") $("warn").textContent = "choose a scan's posture to overlay its measured surface";
    draw();
  }
  function showBar(vmax, k) {
    const c = $("barc"), x = c.getContext("2d"), stops = ["#053061", "#6bacd1", "#f7f6f6", "#e48066", "#67001f"];
    const gr = x.createLinearGradient(0, c.height, 0, 0); stops.forEach((s, i) => gr.addColorStop(i / 4, s));
    x.fillStyle = gr; x.fillRect(0, 0, c.width, c.height);
    // review AG: the map is the saved FE state's, at the scan's posture; the sliders move the
    // model, not the map
    // the ticks beside the bar's top, middle and bottom
    const at = (css, text) => `<span style="position: absolute; ${css}">${text}</span>`;
    $("barticks").innerHTML = at("top: 0", `+${vmax.toFixed(2)} mm: the scan<br>outside the model`) +
      at("top: 50%; transform: translateY(-50%)", "0 mm") +
      at("bottom: 0", `−${vmax.toFixed(2)} mm: inside`);
    $("barlabel").innerHTML = `scale: p99 of this scan's |error|<br>(1 % beyond: the end colours;<br>the reports' maps share one<br>scale across the scans)<br>${k === "error_mm" ? "model vs measured" : "after diagnose's refit"}<br>at the scan's posture and c1<br>(not the sliders')<br>dark grey: not scored`;
    $("bar").style.display = "block";
  }

  async function init() {
    if (!gl) throw new Error("this browser has no WebGL2");
    initGL();
    const sc = (V.scene = await (await fetch("/api/scene")).json());
    $("workname").textContent = sc.work;
    for (const m of sc.missing) { const li = document.createElement("li"); li.textContent = m; $("missing").appendChild(li); }
    points = makeMesh(new Float32Array(3), null, null);
    lines = makeMesh(new Float32Array(6), null, null);
    if (sc.has_surface) {
      const r = await fetch("/api/surface");
      const lay = JSON.parse(r.headers.get("X-Layout")), buf = await r.arrayBuffer();
      V.rest = new Float32Array(buf, 0, 3 * lay.n_vertices).slice();
      const idx = new Uint32Array(buf, 12 * lay.n_vertices, 3 * lay.n_faces);
      model = makeMesh(V.rest.slice(), idx, null);
      const lo = [1e9, 1e9, 1e9], hi = [-1e9, -1e9, -1e9];
      for (let i = 0; i < V.rest.length; i++) { lo[i % 3] = Math.min(lo[i % 3], V.rest[i]); hi[i % 3] = Math.max(hi[i % 3], V.rest[i]); }
      if (sc.plate_z_mm != null) {  // a mesh without its back nodes: no plate drawn
        const grid = plateGrid(lo, hi, sc.plate_z_mm);
        plate = makeMesh(grid.pos, null, null);
        V.plate = { z_mm: grid.z, spacing_mm: grid.spacing_mm, x_mm: grid.x_mm, y_mm: grid.y_mm };
      }
      cam.center = lo.map((l, i) => (l + hi[i]) / 2);
      cam.dist = 1.9 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
      const nv = sc.landmarks.nipple_vertex;
      V.restNipple = nv == null ? null : Array.from(V.rest.subarray(3 * nv, 3 * nv + 3));
      marks.nipple = V.restNipple; marks.tumour = sc.landmarks.tumour_rest_mm;
      marks.fiducials = sc.landmarks.fiducials_mm || [];
    }
    for (const s of sc.scans) {
      const o = document.createElement("option"); o.value = s.name;
      o.textContent = `${s.name} (${s.role})${sc.states.includes(s.name) ? "" : " – no FE state"}`;
      $("scan").appendChild(o);
    }
    if (sc.model) {
      const r = sc.model.c1_range_pa;
      $("c1").disabled = r[0] === r[1];
      $("c1").value = r[0] === r[1] ? 500 : String(Math.round(1000 * Math.log(sc.model.c1_pa / r[0]) / Math.log(r[1] / r[0])));
      // review CD-12: a fixed c1 was a greyed slider with no reason given
      c1Fixed = r[0] === r[1] ? `c1 fixed at ${r[0].toFixed(1)} Pa (the sweep had no --c1 axis)` : "";
      trainedC1 = c1Fixed || `trained c1 ${r[0].toFixed(1)}–${r[1].toFixed(1)} Pa`;
      $("c1").title = c1Fixed;
      $("status").textContent = `surrogate ${sc.model.kind}: ${sc.model.path}; ${trainedC1}`;
    } else {
      for (const id of ["angle_a", "angle_s", "c1"]) $(id).disabled = true;
      $("status").textContent = sc.has_surface ? "no surrogate: pick a scan to see its saved FE state" : "nothing to draw";
      if (!sc.has_surface) {
        $("legend").innerHTML = "<b>Nothing to draw.</b> Missing:<br>" +
          sc.missing.map((m) => m.replace(/&/g, "&amp;").replace(/</g, "&lt;")).join("<br>");
        $("legend").style.cssText = "left:20px;top:20px;bottom:auto;font-size:14px;max-width:70%";
      }
    }
    $("c1").addEventListener("input", () => { c1Touched = true; }, true);
    for (const id of ["angle_a", "angle_s"]) $(id).addEventListener("input", () => { postureGravity = null; }, true);
    for (const id of ["angle_a", "angle_s", "c1"]) $(id).addEventListener("input", onControl);
    async function scanChanged(ev) {
      const s = sc.scans.find((x) => x.name === ev.target.value);
      const saved = s && sc.states.includes(s.name);
      // without a surrogate only a saved FE state is shown under the scan's gravity
      postureGravity = s && (sc.model || saved) ? s.gravity_phantom_m_s2.slice() : null;
      if (s) { const [a, t] = anglesFromGravity(s.gravity_phantom_m_s2); $("angle_a").value = a; $("angle_s").value = t; }
      if (s && $("overlay").value === "none") $("overlay").value = s.maps.includes("error_mm") ? "error_mm" : "measured";
      await loadOverlay(ev.target.value);
      if (sc.model) onControl(null);
      else {
        readControls();
        await showState(saved ? s.name : "");
        // review AG: the reference beside the stress-free shape, offset by its sag, unsaid
        if (s && !saved) $("status").textContent = `${s.name}: no saved FE state (the reference, or a failed solve): the stress-free shape beside its measured, loaded surface`;
      }
    }
    $("scan").addEventListener("change", scanChanged);
    $("overlay").addEventListener("change", applyOverlayMode);
    $("show_model").addEventListener("change", draw);
    window.addEventListener("resize", draw);
    readControls();
    if (sc.model) { onControl(null); await V.settled(); } else draw();
    // ?scan=NAME&overlay=MODE (phantom-calib view --scan): start at a scan's posture
    const qs = new URLSearchParams(location.search);
    if (qs.get("overlay")) $("overlay").value = qs.get("overlay");
    if (qs.get("scan")) {
      $("scan").value = qs.get("scan");
      if ($("scan").value !== qs.get("scan")) $("warn").textContent = `no scan ${qs.get("scan")} in this work folder`;
      else { await scanChanged({ target: $("scan"), timeStamp: performance.now() }); if (sc.model) await V.settled(); }
    }
  }
  // review CD-12: "error: Error: ..." said its prefix twice
  V.ready = init().catch((e) => { V.error = errorText(e); $("warn").textContent = "error: " + V.error; });
})();
