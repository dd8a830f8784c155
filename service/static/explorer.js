// NEMSim process explorer: controls -> rollout -> 3-D surfaces over time, cross-section, metric curves,
// mechanisms, A/B comparison and surrogate-vs-simulator jobs. Plain ES module, three.js vendored.
import * as THREE from '/static/vendor/three/three.module.min.js';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#ff7f0e', '#8c564b', '#17becf'];
const state = {
  model: null, specs: [], inputs: {}, run: null, step: 0, slices: null,
  a: null, sim: null, playing: null, recipe: [], fit: {},
};
window.explorer = state; // for tests and the console (explorer.setStep(k) is set below)

// --- API --------------------------------------------------------------------------------------------
// The page asks the server only for what it shows and answers its limits: a 429 or 503 is waited out
// (Retry-After, capped) and tried again, never shown as an empty result.
const RETRY_CAP_S = 10;
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const busy = (status) => status === 429 || status === 503;
function retryDelayS(r, tries) {
  const given = r ? Number(r.headers.get('Retry-After')) : NaN;
  return Math.min(RETRY_CAP_S, Number.isFinite(given) && given > 0 ? given : 0.5 * 2 ** tries);
}
async function fetchPatiently(path, opts = {}, tries = 5) {
  for (let i = 0; ; i++) {
    const r = await fetch(path, opts);
    if (!busy(r.status) || i >= tries) return r;
    await sleep(1000 * retryDelayS(r, i));
  }
}
async function api(method, path, body) {
  const opts = { method, headers: {} };
  if (body !== undefined) { opts.body = JSON.stringify(body); opts.headers['Content-Type'] = 'application/json'; }
  const r = await fetchPatiently(path, opts);
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (e) { data = null; }
  if (!r.ok) {
    const msg = (data && data.message) || `${method} ${path} answered HTTP ${r.status}`;
    const err = new Error(msg); err.status = r.status; throw err;
  }
  return { data, headers: r.headers };
}
function showError(msg) { const e = $('error'); e.textContent = msg; e.hidden = !msg; }

// --- controls ---------------------------------------------------------------------------------------
const fwd = (s, v) => (s.kind === 'log' ? Math.log10(Math.max(v, 1e-30)) : v);
const inv = (s, x) => (s.kind === 'log' ? 10 ** x : x);
function fmt(v) { return Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(3) : +v.toPrecision(5); }

function buildControls() {
  const box = $('controls'); box.innerHTML = '';
  for (const s of state.specs) {
    const lo = fwd(s, s.train_min), hi = fwd(s, s.train_max), pad = 0.25 * (hi - lo);
    const div = document.createElement('div'); div.className = 'ctl'; div.dataset.name = s.name;
    div.innerHTML = `<div class="row"><label for="c-${s.name}">${s.name}</label>
      <input type="number" id="c-${s.name}" step="any"> <span>${s.unit}</span></div>
      <input type="range" min="${lo - pad}" max="${hi + pad}" step="${s.kind === 'int' ? 1 : (hi - lo) / 200}">
      <div class="meaning">${s.description || s.label} · trained ${fmt(s.train_min)}…${fmt(s.train_max)} ${s.unit}</div>`;
    const num = div.querySelector('input[type=number]'), rng = div.querySelector('input[type=range]');
    num.addEventListener('input', () => { rng.value = fwd(s, +num.value); markRange(s); });
    rng.addEventListener('input', () => {
      let v = inv(s, +rng.value); if (s.kind === 'int') v = Math.round(v);
      state.inputs[s.name].exact = v; num.value = fmt(v); markRange(s);
    });
    state.inputs[s.name] = { num, rng, div, exact: undefined };
    box.appendChild(div);
  }
  setControls(Object.fromEntries(state.specs.map((s) => [s.name, s.default])));
}
function setControls(values) {
  for (const s of state.specs) {
    const inp = state.inputs[s.name];
    inp.exact = values[s.name]; inp.num.value = fmt(values[s.name]); inp.rng.value = fwd(s, values[s.name]); markRange(s);
  }
}
function markRange(s) {
  const { num, div } = state.inputs[s.name]; const v = +num.value;
  div.classList.toggle('out', num.value !== '' && (v < s.train_min || v > s.train_max));
}
function readControls() {
  const out = {};
  for (const s of state.specs) {
    // the text shows a rounded value: while it is unedited, the exact value behind it is meant
    const { num, exact } = state.inputs[s.name], raw = num.value.trim();
    out[s.name] = exact !== undefined && raw === String(fmt(exact)) ? exact : raw === '' ? NaN : Number(raw);
  }
  return out;
}

// --- recipe mode ------------------------------------------------------------------------------------
function renderRecipe() {
  const body = $('recipe-table').querySelector('tbody'); body.innerHTML = '';
  const defaults = Object.fromEntries(state.specs.map((s) => [s.name, s.default]));
  state.recipe.forEach((ph, i) => {
    const diff = state.specs.filter((s) => ph.controls[s.name] !== defaults[s.name])
      .map((s) => `${s.name}=${fmt(ph.controls[s.name])}`).join(', ') || '(defaults)';
    const tr = document.createElement('tr');
    tr.innerHTML = `<td>${i + 1}</td><td><input type="number" min="0.1" step="0.1" value="${ph.duration}" class="dur"></td>
      <td class="left">${diff}</td><td><button>✕</button></td>`;
    tr.querySelector('input').addEventListener('input', (e) => { ph.duration = +e.target.value; });
    tr.querySelector('button').addEventListener('click', () => { state.recipe.splice(i, 1); renderRecipe(); });
    body.appendChild(tr);
  });
}
function horizon() { return Math.min(state.model.horizon_steps, state.model.max_steps); }
function requestBody() {
  if (!$('recipe-mode').checked) return { controls: readControls(), steps: horizon() };
  if (!state.recipe.length) throw new Error('recipe mode: add at least one phase (set the controls, then "Add phase")');
  const rows = [];
  for (const ph of state.recipe) for (let k = 0; k < Math.round(ph.duration * 10); k++) rows.push(ph.controls);
  if (rows.length > horizon()) throw new Error(`the recipe lasts ${rows.length / 10} s; at most ${horizon() / 10} s`);
  return { recipe: rows };
}

// --- canvases fit their column ----------------------------------------------------------------------
// Each canvas is as wide as its panel (CSS) and drawn at the screen's resolution, in CSS pixels; the
// page redraws when the window changes size, so nothing is cut at 1280 x 720 or stretched at 1920 x 1080.
function fitCanvas(c, cssH) {
  const dpr = window.devicePixelRatio || 1, w = Math.max(120, Math.floor(c.clientWidth || c.parentElement.clientWidth));
  const W = Math.round(w * dpr), H = Math.round(cssH * dpr);
  if (c.width !== W) c.width = W;
  if (c.height !== H) c.height = H;
  const ctx = c.getContext('2d'); ctx.setTransform(dpr, 0, 0, dpr, 0, 0); ctx.clearRect(0, 0, w, cssH);
  ctx.font = '11px system-ui';
  return { ctx, w, h: cssH };
}
function size3d() {
  const canvas = $('canvas3d'), w = Math.max(200, Math.floor(canvas.parentElement.clientWidth));
  const h = Math.round(Math.max(220, Math.min(0.8 * w, 0.6 * window.innerHeight)));
  three.renderer.setPixelRatio(window.devicePixelRatio || 1);
  three.renderer.setSize(w, h, false);
  canvas.style.height = `${h}px`;
  three.camera.aspect = w / h; three.camera.updateProjectionMatrix();
}
let resizeQueued = false;
function redrawAll() {
  resizeQueued = false;
  if (three.renderer) { size3d(); render(); }
  if (state.run) { drawSection(state.step); drawChart(); }
  if (state.mechanisms) drawMechanisms(state.mechanisms);
  if (state.sim) drawRmse(state.sim.result);
}

// --- 3-D view ---------------------------------------------------------------------------------------
const three = {};
function init3d() {
  const canvas = $('canvas3d');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setClearColor(0xeef1f5);
  const scene = new THREE.Scene();
  const sc = state.model.scene, vx = sc.voxel_nm;
  const size = new THREE.Vector3(sc.nx * vx, sc.ny * vx, sc.nz * vx);
  const camera = new THREE.PerspectiveCamera(35, canvas.width / canvas.height, 1, 50 * size.length());
  const centre = size.clone().multiplyScalar(0.5);
  camera.up.set(0, 0, 1);
  camera.position.set(centre.x + 0.8 * size.z, centre.y - 1.25 * size.z, centre.z + 0.55 * size.z);
  const controls = new OrbitControls(camera, canvas);
  controls.target.copy(centre); controls.update();
  scene.add(new THREE.AmbientLight(0xffffff, 0.55));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6); sun.position.set(1, -2, 3); scene.add(sun);
  const back = new THREE.DirectionalLight(0xffffff, 0.5); back.position.set(-2, 1, -1); scene.add(back);
  // cutaway: the half nearer the camera (y below the hole axis) is clipped away so the hole shows
  const cut = new THREE.Plane(new THREE.Vector3(0, 1, 0), -(sc.ny * vx) / 2);
  renderer.localClippingEnabled = true;
  const clip = () => ($('cutaway').checked ? [cut] : []);
  const mat = (c) => new THREE.MeshStandardMaterial({ color: c, roughness: 0.7, side: THREE.DoubleSide, clippingPlanes: clip() });
  const mask = new THREE.Mesh(new THREE.BufferGeometry(), mat(0x8a8f99));
  const si = new THREE.Mesh(new THREE.BufferGeometry(), mat(0xe0913c));
  const err = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.MeshStandardMaterial({ vertexColors: true, side: THREE.DoubleSide, clippingPlanes: clip() }));
  $('cutaway').addEventListener('change', () => { for (const m of [mask, si, err]) { m.material.clippingPlanes = clip(); m.material.needsUpdate = true; } render(); });
  err.visible = false;
  scene.add(mask, si, err);
  Object.assign(three, { renderer, scene, camera, controls, mask, si, err });
  controls.addEventListener('change', render);
  size3d(); render();
}
function render() { three.renderer.render(three.scene, three.camera); }

function parseGLB(buf) {
  const dv = new DataView(buf);
  if (dv.getUint32(0, true) !== 0x46546c67) throw new Error('not a glTF binary');
  let off = 12, json = null, bin = null;
  while (off < buf.byteLength) {
    const len = dv.getUint32(off, true), type = dv.getUint32(off + 4, true);
    if (type === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, off + 8, len)));
    else if (type === 0x004e4942) bin = buf.slice(off + 8, off + 8 + len);
    off += 8 + len;
  }
  const geom = new THREE.BufferGeometry();
  const prim = json && json.meshes && json.meshes[0] && json.meshes[0].primitives[0];
  if (!prim || !bin) return geom;
  const read = (i) => {
    const a = json.accessors[i], bv = json.bufferViews[a.bufferView];
    const n = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 }[a.type];
    const T = { 5126: Float32Array, 5125: Uint32Array, 5123: Uint16Array, 5121: Uint8Array }[a.componentType];
    const start = (bv.byteOffset || 0) + (a.byteOffset || 0);
    return { arr: new T(bin.slice(start, start + a.count * n * T.BYTES_PER_ELEMENT)), n, norm: !!a.normalized };
  };
  const p = read(prim.attributes.POSITION);
  geom.setAttribute('position', new THREE.BufferAttribute(p.arr, 3));
  if (prim.attributes.COLOR_0 !== undefined) {
    const c = read(prim.attributes.COLOR_0);
    geom.setAttribute('color', new THREE.BufferAttribute(c.arr, c.n, c.arr instanceof Float32Array ? false : true));
  }
  if (prim.indices !== undefined) geom.setIndex(new THREE.BufferAttribute(read(prim.indices).arr, 1));
  geom.computeVertexNormals();
  return geom;
}
async function fetchGeometry(url) {
  const r = await fetchPatiently(url);
  if (!r.ok) return null;
  return parseGLB(await r.arrayBuffer());
}

// --- meshes: fetched as shown -------------------------------------------------------------------------
// Only the step on screen is asked for (and, while playing, a few steps ahead), at most MESH_IN_FLIGHT
// requests at once and MESH_RATE per second (bursts of MESH_BURST): well inside the server's default
// limits. Until a step's surfaces arrive the nearest step that has them is shown. An entry's status:
// loading | ok | none (the server found no surface there: 422) | retry (busy: asked again at retryAt,
// while still wanted) | failed (another error, shown once).
const MESH_IN_FLIGHT = 3, MESH_RATE = 10, MESH_BURST = 20, LOOK_AHEAD = 6, CHANNELS = ['mask', 'si'];
const meshes = { entries: new Map(), inFlight: 0, tokens: MESH_BURST, last: 0, timer: null, waiters: [], requests: 0 };
const meshKey = (id, step, ch) => `${id}|${step}|${ch}`;
const settled = (e) => !!e && (e.status === 'ok' || e.status === 'none' || e.status === 'failed');
function wantedMeshes() {
  const run = state.run; if (!run) return [];
  const out = [];
  for (const w of meshes.waiters) if (w.id === run.id) for (const ch of CHANNELS) out.push([run.id, w.step, ch]);
  const ahead = state.playing ? LOOK_AHEAD : 0;
  for (let k = state.step; k <= Math.min(run.steps, state.step + ahead); k++) for (const ch of CHANNELS) out.push([run.id, k, ch]);
  return out;
}
function pumpMeshes() {
  clearTimeout(meshes.timer); meshes.timer = null;
  const now = performance.now();
  meshes.tokens = Math.min(MESH_BURST, meshes.tokens + ((now - meshes.last) * MESH_RATE) / 1000); meshes.last = now;
  let wake = Infinity;
  for (const [id, step, ch] of wantedMeshes()) {
    if (meshes.inFlight >= MESH_IN_FLIGHT) break;
    const e = meshes.entries.get(meshKey(id, step, ch));
    if (e && e.status !== 'retry') continue;
    if (e && e.retryAt > now) { wake = Math.min(wake, e.retryAt); continue; }
    if (meshes.tokens < 1) { wake = Math.min(wake, now + ((1 - meshes.tokens) * 1000) / MESH_RATE); break; }
    meshes.tokens -= 1;
    loadMesh(id, step, ch, e ? e.tries + 1 : 0);
  }
  if (wake < Infinity) meshes.timer = setTimeout(pumpMeshes, Math.max(0, wake - now) + 5);
}
async function loadMesh(id, step, ch, tries) {
  const e = { status: 'loading', tries, geom: null, retryAt: 0 };
  meshes.entries.set(meshKey(id, step, ch), e); meshes.inFlight++; meshes.requests++;
  let r = null;
  try {
    r = await fetch(`/rollouts/${id}/mesh?step=${step}&channel=${ch}&format=glb`);
    if (r.ok) { e.geom = parseGLB(await r.arrayBuffer()); e.status = 'ok'; }
    else if (r.status === 422) e.status = 'none'; // no zero-level surface in this channel at this step
    else if (busy(r.status) || r.status >= 500) e.status = 'retry';
    else {
      e.status = 'failed';
      showError(r.status === 404 ? 'this run is no longer in the server\'s cache: press Run again to see its surfaces'
        : `the ${ch} surface at step ${step} could not be loaded (HTTP ${r.status})`);
    }
  } catch (err) { e.status = 'retry'; } // the connection failed: try again later
  if (e.status === 'retry') e.retryAt = performance.now() + 1000 * retryDelayS(r && busy(r.status) ? r : null, tries);
  meshes.inFlight--;
  if (state.run && state.run.id === id) show3d();
  meshes.waiters = meshes.waiters.filter((w) => !(w.test() && (w.resolve(), true)));
  pumpMeshes();
}
function meshesSettled(id, step) {
  const done = () => CHANNELS.every((ch) => settled(meshes.entries.get(meshKey(id, step, ch))));
  return done() ? Promise.resolve() : new Promise((resolve) => meshes.waiters.push({ id, step, test: done, resolve }));
}
function nearestSettled(id, step, ch) {
  for (let d = 0; d <= state.run.steps; d++) {
    for (const k of d ? [step - d, step + d] : [step]) {
      const e = meshes.entries.get(meshKey(id, k, ch));
      if (e && (e.status === 'ok' || e.status === 'none')) return e;
    }
  }
  return null;
}
function show3d() {
  const run = state.run; if (!run || !three.renderer) return;
  for (const [obj, ch] of [[three.mask, 'mask'], [three.si, 'si']]) {
    const e = nearestSettled(run.id, state.step, ch);
    if (!e) continue; // nothing of this run yet: keep what is drawn
    if (e.geom && obj.geometry !== e.geom) obj.geometry = e.geom;
    if (!(obj === three.si && three.err.visible)) obj.visible = e.status === 'ok' && e.geom.attributes.position !== undefined;
  }
  render();
}
function forgetMeshes(keepId) {
  for (const key of meshes.entries.keys()) if (!key.startsWith(`${keepId}|`)) meshes.entries.delete(key);
}
state.meshReady = (step) => !!state.run && CHANNELS.every((ch) => settled(meshes.entries.get(meshKey(state.run.id, step, ch))));
state.meshStats = () => {
  const n = { requests: meshes.requests };
  for (const e of meshes.entries.values()) n[e.status] = (n[e.status] || 0) + 1;
  return n;
};

// --- cross-section ----------------------------------------------------------------------------------
function drawSection(step) {
  const c = $('section'), { ctx, w, h } = fitCanvas(c, 300);
  ctx.fillStyle = '#fff'; ctx.fillRect(0, 0, w, h);
  if (!state.slices) return;
  // side by side with A when A is pinned (same time)
  const panels = [[state.slices, 'current']];
  if (state.a && state.a.slices) panels.push([state.a.slices, 'A']);
  const pw = w / panels.length;
  panels.forEach(([sl, label], p) => {
    const [n, , D, W] = sl.shape, plane = D * W, base = Math.min(step, n - 1) * 2 * plane;
    const img = new ImageData(W, D);
    for (let z = 0; z < D; z++) for (let x = 0; x < W; x++) {
      const m = sl.bytes[base + z * W + x] / 127.5 - 1, s = sl.bytes[base + plane + z * W + x] / 127.5 - 1;
      const o = ((D - 1 - z) * W + x) * 4; // depth index grows upwards
      let rgb = [238, 241, 245];
      if (s < 0) rgb = [224, 145, 60]; else if (m < 0) rgb = [138, 143, 153];
      if (Math.min(Math.abs(m), Math.abs(s)) < 0.08) rgb = [30, 36, 48];
      img.data.set([...rgb, 255], o);
    }
    const tmp = document.createElement('canvas'); tmp.width = W; tmp.height = D;
    tmp.getContext('2d').putImageData(img, 0, 0);
    const scale = Math.min((pw - 8) / W, (h - 16) / D);
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(tmp, p * pw + (pw - W * scale) / 2, 16, W * scale, D * scale);
    if (panels.length > 1) { ctx.fillStyle = '#334'; ctx.fillText(label, p * pw + 6, 12); }
  });
}

// --- chart ------------------------------------------------------------------------------------------
function niceTicks(lo, hi, n = 5) {
  if (!(hi > lo)) hi = lo + 1;
  const raw = (hi - lo) / n, mag = 10 ** Math.floor(Math.log10(raw)), f = raw / mag;
  const step = (f <= 1 ? 1 : f <= 2 ? 2 : f <= 2.5 ? 2.5 : f <= 5 ? 5 : 10) * mag;
  const a = Math.floor(lo / step + 1e-9) * step, b = Math.ceil(hi / step - 1e-9) * step;
  let dec = 0;
  while (dec < 6 && Math.abs(Math.round(step * 10 ** dec) - step * 10 ** dec) > 1e-6) dec++;
  const ticks = [];
  for (let v = a; v <= b + step / 2; v += step) ticks.push(v);
  return { lo: a, hi: b, ticks, label: (v) => v.toFixed(dec) };
}
function drawChart() {
  const c = $('chart'), { ctx, w: cw, h: ch } = fitCanvas(c, 260);
  const run = state.run; if (!run) return;
  const names = Object.keys(run.metrics);
  const series = [[run, []], [state.a, [6, 4]], [state.sim, [2, 3]]].filter(([s]) => s);
  let ymin = 0, ymax = 1;
  for (const [s] of series) for (const n of names) for (const v of (s.metrics[n] || [])) if (v !== null) { ymin = Math.min(ymin, v); ymax = Math.max(ymax, v); }
  const tmax = Math.max(...series.map(([s]) => s.times_s[s.times_s.length - 1]));
  const yt = niceTicks(ymin, ymax), xt = niceTicks(0, tmax);
  const L = 8 + Math.max(...yt.ticks.map((v) => ctx.measureText(yt.label(v)).width));
  const R = 30 + Math.max(...names.map((n) => ctx.measureText(n).width)), T = 16, B = 32;
  const w = cw - L - R, h = ch - T - B;
  const X = (t) => L + (w * t) / xt.hi, Y = (v) => T + h * (1 - (v - yt.lo) / (yt.hi - yt.lo));
  ctx.strokeStyle = '#99a'; ctx.fillStyle = '#445'; ctx.lineWidth = 1;
  ctx.strokeRect(L, T, w, h);
  ctx.textAlign = 'right';
  for (const v of yt.ticks) ctx.fillText(yt.label(v), L - 4, Y(v) + 4);
  ctx.textAlign = 'center';
  for (const t of xt.ticks) ctx.fillText(xt.label(t), X(t), T + h + 13);
  ctx.fillText('time (s)', L + w / 2, ch - 4);
  ctx.textAlign = 'left'; ctx.fillText('nm', 2, 11);
  ctx.strokeStyle = '#eef'; ctx.beginPath();
  for (const v of yt.ticks.slice(1, -1)) { ctx.moveTo(L + 1, Y(v)); ctx.lineTo(L + w - 1, Y(v)); }
  ctx.stroke();
  names.forEach((n, i) => {
    ctx.strokeStyle = COLORS[i % COLORS.length];
    for (const [s, dash] of series) {
      const vals = s.metrics[n]; if (!vals) continue;
      ctx.setLineDash(dash); ctx.lineWidth = 1.6; ctx.beginPath(); let pen = false;
      vals.forEach((v, k) => { if (v === null) { pen = false; return; } const x = X(s.times_s[k]), y = Y(v); pen ? ctx.lineTo(x, y) : ctx.moveTo(x, y); pen = true; });
      ctx.stroke();
    }
    ctx.setLineDash([]); ctx.fillStyle = COLORS[i % COLORS.length];
    ctx.fillRect(L + w + 8, T + 6 + 15 * i, 10, 3); ctx.fillStyle = '#334'; ctx.fillText(n, L + w + 22, T + 10 + 15 * i);
  });
  ctx.setLineDash([]); ctx.strokeStyle = '#000'; ctx.lineWidth = 1; ctx.beginPath();
  const x = X(run.times_s[state.step]); ctx.moveTo(x, T); ctx.lineTo(x, T + h); ctx.stroke();
  const legendRight = L + w + 22 + Math.max(...names.map((n) => ctx.measureText(n).width));
  state.fit.chart = legendRight <= cw && T + 10 + 15 * (names.length - 1) <= ch;
}
function metricsTable() {
  const run = state.run; if (!run) return;
  const k = state.step, cols = [['current', run]];
  if (state.a) cols.push(['A', state.a]);
  if (state.sim) cols.push(['simulator', state.sim]);
  const v = (x) => (x === null || x === undefined ? '–' : x.toFixed(1));
  let html = `<table><tr><th>at t = ${run.times_s[k].toFixed(1)} s (nm)</th>${cols.map(([n]) => `<th>${n}</th>`).join('')}</tr>`;
  for (const n of Object.keys(run.metrics)) html += `<tr><td>${n}</td>${cols.map(([, s]) => `<td>${v((s.metrics[n] || [])[Math.min(k, s.metrics[n].length - 1)])}</td>`).join('')}</tr>`;
  $('final-metrics').innerHTML = html + '</table>';
}

// --- time -------------------------------------------------------------------------------------------
function setStep(step) {
  state.step = step; $('time').value = step;
  $('time-label').textContent = `t = ${state.run.times_s[step].toFixed(1)} s (step ${step})`;
  three.err.visible = false;
  show3d(); pumpMeshes(); drawSection(step); drawChart(); metricsTable();
}
function togglePlay() {
  if (state.playing) { clearInterval(state.playing); state.playing = null; $('play').textContent = 'Play'; return; }
  if (state.step >= state.run.steps) setStep(0);
  $('play').textContent = 'Pause';
  state.playing = setInterval(() => {
    if (state.step >= state.run.steps) { togglePlay(); return; }
    setStep(state.step + 1);
  }, 100);
  pumpMeshes();
}

// --- run --------------------------------------------------------------------------------------------
async function run() {
  showError('');
  let body;
  try { body = requestBody(); } catch (e) { showError(e.message); return; }
  if (state.playing) togglePlay();
  $('run').disabled = true; $('run').textContent = 'Running…'; $('play').disabled = true;
  const t0 = performance.now();
  try {
    const { data } = await api('POST', '/rollout', body);
    (state.rolloutMs = state.rolloutMs || []).push(performance.now() - t0);
    state.run = data; state.body = body; state.sim = null;
    $('comparison').innerHTML = ''; $('rmse').hidden = true; $('job-status').textContent = '';
    const w = $('warnings');
    w.hidden = !data.warnings.length;
    w.innerHTML = data.warnings.map((x) => `⚠ ${x}`).join('<br>');
    for (const s of state.specs) state.inputs[s.name].div.classList.remove('api-out');
    for (const e of data.extrapolation || []) if (state.inputs[e.control]) state.inputs[e.control].div.classList.add('out', 'api-out');
    // the final state first: its surfaces are asked for while the cross-sections load
    const slider = $('time'); slider.disabled = true; slider.max = data.steps; slider.value = data.steps;
    forgetMeshes(data.id); state.step = data.steps; three.err.visible = false; pumpMeshes();
    const [sl] = await Promise.all([
      api('GET', `/rollouts/${data.id}/slices`).then((x) => x.data), meshesSettled(data.id, data.steps),
    ]);
    sl.bytes = Uint8Array.from(atob(sl.data), (ch) => ch.charCodeAt(0)); state.slices = sl;
    slider.disabled = false;
    setStep(data.steps);
    if (state.a) renderAB();
    state.firstViewMs = performance.now() - t0;
    (state.firstViews = state.firstViews || []).push(state.firstViewMs);
    document.body.dataset.runs = String((+document.body.dataset.runs || 0) + 1);
    for (const id of ['play', 'pin-a', 'verify', 'mech-run']) $(id).disabled = false;
    if (!$('recipe-mode').checked) mechanisms('for the controls of this run');
    else {
      state.mechanisms = null; fitCanvas($('mech'), 20);
      $('mech-note').textContent = 'A recipe changes the controls over time; the mechanisms are computed for one constant set: press Compute to analyse the controls set on the left.';
    }
  } catch (e) {
    showError(e.message);
  } finally { $('run').disabled = false; $('run').textContent = 'Run'; $('play').disabled = !state.run; }
}

// --- mechanisms -------------------------------------------------------------------------------------
async function mechanisms(note = 'for the controls set on the left') {
  const q = new URLSearchParams(Object.entries(readControls()).map(([k, v]) => [k, String(v)]));
  $('mech-note').textContent = 'computing…';
  try {
    state.mechanisms = (await api('GET', `/mechanisms?${q}`)).data.result;
  } catch (e) { state.mechanisms = null; fitCanvas($('mech'), 20); $('mech-note').textContent = e.message; return; }
  $('mech-note').textContent = note;
  drawMechanisms(state.mechanisms);
}
function drawMechanisms(res) {
  const bars = [];
  const tot = Object.values(res.base.M).reduce((a, b) => a + Math.abs(b || 0), 0) || 1;
  for (const f of res.families) bars.push([`share ${f}`, (100 * (res.base.M[f] || 0)) / tot, '#1f77b4']);
  for (const iv of res.interventions) bars.push([`Cl+×${iv.s_cl_plus} Cl×${iv.s_cl}: ΔR`, iv.delta_R_pct || 0, '#d62728']);
  const rowH = 16, { ctx, w } = fitCanvas($('mech'), 4 + rowH * bars.length);
  const pct = (v) => `${v.toFixed(1)}%`;
  const x0 = 6 + Math.max(...bars.map((b) => ctx.measureText(b[0]).width));
  const room = 4 + Math.max(...bars.map((b) => ctx.measureText(pct(b[1])).width)); // a value label beside its bar
  const amax = Math.max(1, ...bars.map((b) => Math.abs(b[1])));
  const half = Math.max(10, (w - x0 - 2 * room) / 2), mid = x0 + room + half;
  let right = 0;
  bars.forEach(([label, v, col], i) => {
    const y = 2 + i * rowH; ctx.fillStyle = '#334'; ctx.fillText(label, 2, y + rowH - 4);
    ctx.fillStyle = col; const len = (half * v) / amax;
    ctx.fillRect(mid + Math.min(0, len), y + 2, Math.abs(len), rowH - 4);
    ctx.fillStyle = '#334'; const t = pct(v), tw = ctx.measureText(t).width;
    const tx = len >= 0 ? mid + len + 3 : mid + len - 3 - tw; ctx.fillText(t, tx, y + rowH - 4);
    right = Math.max(right, tx + tw);
  });
  state.fit.mech = right <= w;
}

// --- A/B --------------------------------------------------------------------------------------------
function pinA() {
  state.a = { ...state.run, label: 'A', slices: state.slices };
  $('clear-a').disabled = false; $('ab-label').textContent = 'A pinned: change the controls and Run to compare';
  renderAB();
}
function renderAB() {
  const box = $('ab'); box.hidden = !state.a;
  if (!state.a || !state.run) { drawChart(); if (state.run) drawSection(state.step); return; }
  // a control's values over the run, consecutive repeats merged (one value for constant controls)
  const seq = (r, n) => (r.recipe ? r.recipe.map((c) => c[n]) : [r.controls[n]]).filter((v, i, a) => i === 0 || v !== a[i - 1]);
  const show = (vals) => vals.map(fmt).join(' → ');
  const diff = state.specs.filter((s) => show(seq(state.a, s.name)) !== show(seq(state.run, s.name)));
  let html = '<table><tr><th>control (over time)</th><th>A</th><th>current</th></tr>';
  html += diff.map((s) => `<tr><td>${s.name}</td><td>${show(seq(state.a, s.name))}</td><td>${show(seq(state.run, s.name))}</td></tr>`).join('') || '<tr><td colspan=3>same controls</td></tr>';
  html += '</table><table><tr><th>final (nm)</th><th>A</th><th>current</th><th>current − A</th></tr>';
  for (const n of Object.keys(state.run.metrics)) {
    const a = state.a.metrics[n][state.a.metrics[n].length - 1], b = state.run.metrics[n][state.run.metrics[n].length - 1];
    html += `<tr><td>${n}</td><td>${a?.toFixed(1) ?? '–'}</td><td>${b?.toFixed(1) ?? '–'}</td><td>${a !== null && b !== null ? (b - a).toFixed(1) : '–'}</td></tr>`;
  }
  box.innerHTML = html + '</table>';
  drawChart(); metricsTable(); drawSection(state.step);
}

// --- simulator jobs ---------------------------------------------------------------------------------
async function verify() {
  showError('');
  const body = { ...state.body, steps: state.run.steps };
  $('verify').disabled = true; $('job-progress').hidden = false; $('job-progress').value = 0;
  try {
    const { data } = await api('POST', '/simulations', body);
    $('job-status').textContent = `job ${data.id}: ${data.status}`;
    state.job = data; $('job-cancel').hidden = false;
    let job;
    for (;;) {
      job = (await api('GET', data.location)).data;
      $('job-progress').value = job.progress; $('job-status').textContent = `job ${job.id}: ${job.status} (${Math.round(100 * job.progress)}%)`;
      if (['done', 'failed', 'cancelled'].includes(job.status)) break;
      await sleep(300);
    }
    if (job.status === 'cancelled') { $('job-status').textContent = `job ${job.id}: cancelled`; return; }
    if (job.status !== 'done') { showError(`simulator job ${job.status}: ${job.message || ''}`); return; }
    showComparison(job.result);
  } catch (e) { showError(e.message); } finally {
    $('verify').disabled = false; $('job-progress').hidden = true; $('job-cancel').hidden = true;
  }
}
function drawRmse(res) {
  const { ctx, w: cw, h: ch } = fitCanvas($('rmse'), 140);
  const r = res.rmse_per_step.map((v) => v || 0), rmax = Math.max(...r, 1e-6), L = 44, w = cw - L - 8, h = ch - 28;
  ctx.strokeStyle = '#99a'; ctx.strokeRect(L, 6, w, h); ctx.fillStyle = '#445';
  ctx.fillText(rmax.toFixed(3), 2, 14); ctx.fillText('0', 30, 6 + h); ctx.fillText('per-step RMSE (normalized SDF) vs time', L + 4, ch - 6);
  ctx.strokeStyle = '#d62728'; ctx.beginPath();
  r.forEach((v, k) => { const x = L + (w * k) / (r.length - 1), y = 6 + h * (1 - v / rmax); k ? ctx.lineTo(x, y) : ctx.moveTo(x, y); });
  ctx.stroke();
}
function showComparison(res) {
  state.sim = { metrics: res.simulator_metrics, times_s: res.times_s, result: res };
  $('rmse').hidden = false; drawRmse(res);
  let html = `<p>avg RMSE ${res.avg_rmse.toFixed(4)} (normalized SDF), simulator ${res.simulator_s.toFixed(1)} s, seed ${res.seed}</p>`;
  html += '<table><tr><th>final</th><th>surrogate</th><th>simulator</th><th>difference</th></tr>';
  for (const [n, d] of Object.entries(res.final_differences)) {
    const s = res.surrogate_metrics[n], m = res.simulator_metrics[n];
    const f = (x) => (x === null || x === undefined ? '–' : x.toFixed(1));
    html += `<tr><td>${n}</td><td>${f(s[s.length - 1])}</td><td>${f(m[m.length - 1])}</td><td>${f(d)}</td></tr>`;
  }
  html += '</table><button id="show-err">Show the simulator\'s Si surface at this time, coloured by the surrogate\'s error</button>';
  const box = $('comparison'); box.innerHTML = html; box.dataset.done = '1';
  $('show-err').addEventListener('click', async () => {
    const g = await fetchGeometry(res.mesh.replace(/step=\d+/, `step=${Math.min(state.step, res.steps)}`));
    if (!g) return;
    three.err.geometry = g; three.err.visible = true; three.si.visible = false; render();
  });
  drawChart(); metricsTable();
}

// --- start ------------------------------------------------------------------------------------------
async function start() {
  let info;
  for (let i = 0; ; i++) {
    try { info = (await api('GET', '/model')).data; break; } catch (e) {
      if (e.status !== 503 || i > 120) { showError(e.message); return; }
      await sleep(1000);
    }
  }
  state.model = info; state.specs = info.controls;
  $('model').textContent = `${info.model_id} · scene ${info.scene.name} · ${info.n_params} parameters · extrapolation: ${info.extrapolation}`;
  buildControls(); init3d();
  $('run').disabled = false;
  $('run').addEventListener('click', run);
  $('reset').addEventListener('click', () => setControls(Object.fromEntries(state.specs.map((s) => [s.name, s.default]))));
  $('time').addEventListener('input', (e) => setStep(+e.target.value));
  $('play').addEventListener('click', togglePlay);
  $('pin-a').addEventListener('click', pinA);
  $('clear-a').addEventListener('click', () => { state.a = null; $('clear-a').disabled = true; $('ab-label').textContent = ''; renderAB(); });
  $('mech-run').addEventListener('click', () => mechanisms());
  $('verify').addEventListener('click', verify);
  $('job-cancel').addEventListener('click', () => state.job && api('DELETE', state.job.location).catch((e) => showError(e.message)));
  $('recipe-mode').addEventListener('change', (e) => { $('recipe').hidden = !e.target.checked; });
  $('add-phase').addEventListener('click', () => { state.recipe.push({ duration: 2.5, controls: readControls() }); renderRecipe(); });
  window.addEventListener('resize', () => { if (!resizeQueued) { resizeQueued = true; requestAnimationFrame(redrawAll); } });
  state.setStep = setStep;
  document.body.dataset.ready = '1';
}
start();
