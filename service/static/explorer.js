// NEMSim process explorer: controls -> rollout -> 3-D surfaces over time, cross-section, metric curves,
// mechanisms, A/B comparison and surrogate-vs-simulator jobs. Plain ES module, three.js vendored.
import * as THREE from '/static/vendor/three/three.module.min.js';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#ff7f0e', '#8c564b', '#17becf'];
const state = {
  model: null, specs: [], inputs: {}, run: null, step: 0, slices: null, meshes: new Map(),
  fetchToken: 0, a: null, sim: null, playing: null, recipe: [],
};
window.explorer = state; // for tests and the console (explorer.setStep(k) is set below)

// --- API --------------------------------------------------------------------------------------------
async function api(method, path, body) {
  const opts = { method, headers: {} };
  if (body !== undefined) { opts.body = JSON.stringify(body); opts.headers['Content-Type'] = 'application/json'; }
  const r = await fetch(path, opts);
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
      num.value = fmt(v); markRange(s);
    });
    state.inputs[s.name] = { num, rng, div };
    box.appendChild(div);
  }
  setControls(Object.fromEntries(state.specs.map((s) => [s.name, s.default])));
}
function setControls(values) {
  for (const s of state.specs) {
    const { num, rng } = state.inputs[s.name];
    num.value = fmt(values[s.name]); rng.value = fwd(s, values[s.name]); markRange(s);
  }
}
function markRange(s) {
  const { num, div } = state.inputs[s.name]; const v = +num.value;
  div.classList.toggle('out', num.value !== '' && (v < s.train_min || v > s.train_max));
}
function readControls() {
  const out = {};
  for (const s of state.specs) {
    const raw = state.inputs[s.name].num.value.trim();
    out[s.name] = raw === '' ? NaN : Number(raw);
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
  render();
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
  const r = await fetch(url);
  if (!r.ok) return null; // e.g. a channel with no surface at this step
  return parseGLB(await r.arrayBuffer());
}
function meshPromise(id, step, channel) {
  const key = `${id}|${step}|${channel}`;
  if (!state.meshes.has(key)) {
    const p = fetchGeometry(`/rollouts/${id}/mesh?step=${step}&channel=${channel}&format=glb`).catch(() => null);
    state.meshes.set(key, p);
    p.then((g) => { p.value = g; p.ready = true; });
  }
  return state.meshes.get(key);
}
function nearestReady(id, step, channel) {
  for (let d = 0; d <= state.run.steps; d++) {
    for (const k of [step - d, step + d]) {
      const p = state.meshes.get(`${id}|${k}|${channel}`);
      if (p && p.ready) return p.value;
    }
  }
  return undefined;
}
function showGeometry(obj, g) {
  if (g === undefined) return;
  obj.visible = !!g && g.attributes.position !== undefined;
  if (g) obj.geometry = g;
}
async function showStep3d(step) {
  const run = state.run; if (!run) return;
  three.err.visible = false;
  for (const [obj, ch] of [[three.mask, 'mask'], [three.si, 'si']]) {
    const p = meshPromise(run.id, step, ch);
    if (p.ready) showGeometry(obj, p.value);
    else {
      showGeometry(obj, nearestReady(run.id, step, ch));
      p.then((g) => { if (state.run === run && state.step === step) { showGeometry(obj, g); render(); } });
    }
  }
  render();
}
async function prefetch(run, token) {
  const order = [];
  for (let k = 0; k <= run.steps; k += 5) order.push(k);
  for (let k = 0; k <= run.steps; k++) if (k % 5) order.push(k);
  for (const k of order) {
    if (state.fetchToken !== token) return;
    await Promise.all([meshPromise(run.id, k, 'mask'), meshPromise(run.id, k, 'si')]);
  }
}

// --- cross-section ----------------------------------------------------------------------------------
function drawSection(step) {
  const c = $('section'), ctx = c.getContext('2d');
  ctx.fillStyle = '#fff'; ctx.fillRect(0, 0, c.width, c.height);
  if (!state.slices) return;
  // side by side with A when A is pinned (same time)
  const panels = [[state.slices, 'current']];
  if (state.a && state.a.slices) panels.push([state.a.slices, 'A']);
  const pw = c.width / panels.length;
  panels.forEach(([sl, label], p) => {
    const [n, , D, W] = sl.shape, plane = D * W, base = Math.min(step, n - 1) * 2 * plane;
    const img = ctx.createImageData(W, D);
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
    const scale = Math.min((pw - 8) / W, (c.height - 16) / D);
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(tmp, p * pw + (pw - W * scale) / 2, 16, W * scale, D * scale);
    if (panels.length > 1) { ctx.fillStyle = '#334'; ctx.font = '11px system-ui'; ctx.fillText(label, p * pw + 6, 12); }
  });
}

// --- chart ------------------------------------------------------------------------------------------
function drawChart() {
  const c = $('chart'), ctx = c.getContext('2d');
  ctx.clearRect(0, 0, c.width, c.height);
  const run = state.run; if (!run) return;
  const names = Object.keys(run.metrics);
  const series = [[run, []], [state.a, [6, 4]], [state.sim, [2, 3]]].filter(([s]) => s);
  let ymin = 0, ymax = 1;
  for (const [s] of series) for (const n of names) for (const v of (s.metrics[n] || [])) if (v !== null) { ymin = Math.min(ymin, v); ymax = Math.max(ymax, v); }
  const L = 44, R = 120, T = 8, B = 24, w = c.width - L - R, h = c.height - T - B;
  const tmax = Math.max(...series.map(([s]) => s.times_s[s.times_s.length - 1]));
  const X = (t) => L + (w * t) / tmax, Y = (v) => T + h * (1 - (v - ymin) / (ymax - ymin || 1));
  ctx.strokeStyle = '#99a'; ctx.fillStyle = '#445'; ctx.font = '11px system-ui'; ctx.lineWidth = 1;
  ctx.strokeRect(L, T, w, h);
  for (let i = 0; i <= 4; i++) {
    const v = ymin + ((ymax - ymin) * i) / 4; ctx.fillText(v.toFixed(0), 4, Y(v) + 4);
    const t = (tmax * i) / 4; ctx.fillText(t.toFixed(1), X(t) - 8, c.height - 8);
  }
  ctx.fillText('nm', L + w + 8, T + h); ctx.fillText('time (s)', L + w + 22, c.height - 8);
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
  ctx.setLineDash([]); ctx.strokeStyle = '#000'; ctx.beginPath();
  const xt = X(run.times_s[state.step]); ctx.moveTo(xt, T); ctx.lineTo(xt, T + h); ctx.stroke();
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
  showStep3d(step); drawSection(step); drawChart(); metricsTable();
}
function togglePlay() {
  if (state.playing) { clearInterval(state.playing); state.playing = null; $('play').textContent = 'Play'; return; }
  if (state.step >= state.run.steps) setStep(0);
  $('play').textContent = 'Pause';
  state.playing = setInterval(() => {
    if (state.step >= state.run.steps) { togglePlay(); return; }
    setStep(state.step + 1);
  }, 100);
}

// --- run --------------------------------------------------------------------------------------------
async function run() {
  showError('');
  let body;
  try { body = requestBody(); } catch (e) { showError(e.message); return; }
  $('run').disabled = true; $('run').textContent = 'Running…';
  const t0 = performance.now();
  try {
    const { data } = await api('POST', '/rollout', body);
    state.run = data; state.body = body; state.sim = null; state.fetchToken++;
    $('comparison').innerHTML = ''; $('rmse').hidden = true; $('job-status').textContent = '';
    const w = $('warnings');
    w.hidden = !data.warnings.length;
    w.innerHTML = data.warnings.map((x) => `⚠ ${x}`).join('<br>');
    for (const s of state.specs) state.inputs[s.name].div.classList.remove('api-out');
    for (const e of data.extrapolation || []) if (state.inputs[e.control]) state.inputs[e.control].div.classList.add('out', 'api-out');
    const sl = (await api('GET', `/rollouts/${data.id}/slices`)).data;
    sl.bytes = Uint8Array.from(atob(sl.data), (ch) => ch.charCodeAt(0)); state.slices = sl;
    const slider = $('time'); slider.max = data.steps; slider.disabled = false;
    await Promise.all([meshPromise(data.id, data.steps, 'mask'), meshPromise(data.id, data.steps, 'si')]);
    setStep(data.steps);
    if (state.a) renderAB();
    state.firstViewMs = performance.now() - t0;
    document.body.dataset.runs = String((+document.body.dataset.runs || 0) + 1);
    for (const id of ['play', 'pin-a', 'verify', 'mech-run']) $(id).disabled = false;
    prefetch(data, state.fetchToken);
    if (!$('recipe-mode').checked) mechanisms();
  } catch (e) {
    showError(e.message);
  } finally { $('run').disabled = false; $('run').textContent = 'Run'; }
}

// --- mechanisms -------------------------------------------------------------------------------------
async function mechanisms() {
  const c = $('mech'), ctx = c.getContext('2d'); ctx.clearRect(0, 0, c.width, c.height);
  ctx.font = '11px system-ui'; ctx.fillStyle = '#445';
  const q = new URLSearchParams(Object.entries(readControls()).map(([k, v]) => [k, String(v)]));
  let res;
  try { res = (await api('GET', `/mechanisms?${q}`)).data.result; } catch (e) { ctx.fillText(e.message, 4, 14); return; }
  const bars = [];
  const tot = Object.values(res.base.M).reduce((a, b) => a + Math.abs(b || 0), 0) || 1;
  for (const f of res.families) bars.push([`share ${f}`, (100 * (res.base.M[f] || 0)) / tot, '#1f77b4']);
  for (const iv of res.interventions) bars.push([`Cl+×${iv.s_cl_plus} Cl×${iv.s_cl}: ΔR`, iv.delta_R_pct || 0, '#d62728']);
  const amax = Math.max(1, ...bars.map((b) => Math.abs(b[1])));
  const rowH = Math.min(16, (c.height - 4) / bars.length), x0 = 170, half = (c.width - x0 - 40) / 2;
  bars.forEach(([label, v, col], i) => {
    const y = 2 + i * rowH; ctx.fillStyle = '#334'; ctx.fillText(label, 2, y + rowH - 4);
    ctx.fillStyle = col; const len = (half * v) / amax;
    ctx.fillRect(x0 + half + Math.min(0, len), y + 2, Math.abs(len), rowH - 4);
    ctx.fillStyle = '#334'; ctx.fillText(`${v.toFixed(1)}%`, x0 + half + Math.max(0, len) + 3, y + rowH - 4);
  });
  state.mechanisms = res;
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
      await new Promise((r) => setTimeout(r, 300));
    }
    if (job.status === 'cancelled') { $('job-status').textContent = `job ${job.id}: cancelled`; return; }
    if (job.status !== 'done') { showError(`simulator job ${job.status}: ${job.message || ''}`); return; }
    showComparison(job.result);
  } catch (e) { showError(e.message); } finally {
    $('verify').disabled = false; $('job-progress').hidden = true; $('job-cancel').hidden = true;
  }
}
function showComparison(res) {
  state.sim = { metrics: res.simulator_metrics, times_s: res.times_s, result: res };
  const c = $('rmse'); c.hidden = false; const ctx = c.getContext('2d'); ctx.clearRect(0, 0, c.width, c.height);
  const r = res.rmse_per_step.map((v) => v || 0), rmax = Math.max(...r, 1e-6), L = 44, w = c.width - L - 8, h = c.height - 28;
  ctx.strokeStyle = '#99a'; ctx.strokeRect(L, 6, w, h); ctx.fillStyle = '#445'; ctx.font = '11px system-ui';
  ctx.fillText(rmax.toFixed(3), 2, 14); ctx.fillText('0', 30, 6 + h); ctx.fillText('per-step RMSE (normalized SDF) vs time', L + 4, c.height - 6);
  ctx.strokeStyle = '#d62728'; ctx.beginPath();
  r.forEach((v, k) => { const x = L + (w * k) / (r.length - 1), y = 6 + h * (1 - v / rmax); k ? ctx.lineTo(x, y) : ctx.moveTo(x, y); });
  ctx.stroke();
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
      await new Promise((r) => setTimeout(r, 1000));
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
  $('mech-run').addEventListener('click', mechanisms);
  $('verify').addEventListener('click', verify);
  $('job-cancel').addEventListener('click', () => state.job && api('DELETE', state.job.location).catch((e) => showError(e.message)));
  $('recipe-mode').addEventListener('change', (e) => { $('recipe').hidden = !e.target.checked; });
  $('add-phase').addEventListener('click', () => { state.recipe.push({ duration: 2.5, controls: readControls() }); renderRecipe(); });
  state.setStep = setStep;
  document.body.dataset.ready = '1';
}
start();
