// NEMSim process explorer: controls -> rollout -> 3-D surfaces over time, cross-section and etch profile in
// nm, metric curves, mechanisms, A/B comparison, surrogate-vs-simulator jobs, inverse design and exports.
// Plain ES modules, three.js vendored; `window.explorer` exposes the state to tests and the console.
import { api, busy, download, fetchPatiently, retryDelayS, saveBlob, sleep } from '/static/api.js';
import { FONT, drawProfile, drawSection, niceTicks, ticksWithin, timeColour } from '/static/plot.js';
import { createView, parseGLB } from '/static/view3d.js';
import { initDesign } from '/static/design.js';
import { caseScene, initGeometry } from '/static/geometry.js';

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);
const COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#ff7f0e', '#8c564b', '#17becf'];
const state = {
  model: null, specs: [], inputs: {}, run: null, step: 0, slices: null,
  a: null, sim: null, playing: null, recipe: [], fit: {}, job: null,
};
window.explorer = state;
let view = null; // the 3-D view (view3d.js), once the model is known

// --- one job at a time ----------------------------------------------------------------------------------
// The server runs one job per client (more get 429): a simulator check and a design never overlap.
const jobs = {
  what: null,
  start(what) { if (this.what) return false; this.what = what; syncJobButtons(); return true; },
  end() { this.what = null; syncJobButtons(); },
};
function syncJobButtons() {
  $('verify').disabled = !!jobs.what || !state.run;
  $('design-run').disabled = !!jobs.what;
  for (const id of ['verify', 'design-run']) $(id).title = jobs.what ? `waiting for the running ${jobs.what} job` : '';
}
async function followJob(location, onUpdate) {
  for (;;) {
    const job = (await api('GET', location)).data;
    onUpdate(job);
    if (['done', 'failed', 'cancelled'].includes(job.status)) return job;
    await sleep(300);
  }
}
function showError(msg) { const e = $('error'); e.textContent = msg; e.hidden = !msg; }
/** A failed Run leaves the previous results on screen, greyed (and their trust verdict with them), so they
 * are not read as the answer to the inputs now set; the next successful Run restores them. */
function markStale(on) {
  const stale = on && !!state.run;
  document.body.classList.toggle('stale', stale);
  if (stale) $('error').textContent += ' (the greyed results are those of the previous Run)';
}

// --- controls ---------------------------------------------------------------------------------------
const fwd = (s, v) => (s.kind === 'log' ? Math.log10(Math.max(v, 1e-30)) : v);
const inv = (s, x) => (s.kind === 'log' ? 10 ** x : x);
function fmt(v) { return Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(3) : +v.toPrecision(5); }
const defaults = () => Object.fromEntries(state.specs.map((s) => [s.name, s.default]));

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
  setControls(defaults());
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
function showTab(name) {
  for (const t of ['controls', 'design']) {
    $(`tab-${t}`).hidden = t !== name;
    $(`tab-${t}-btn`).classList.toggle('on', t === name); $(`tab-${t}-btn`).setAttribute('aria-selected', String(t === name));
  }
}

// --- recipe mode ------------------------------------------------------------------------------------
function renderRecipe() {
  const body = $('recipe-table').querySelector('tbody'); body.innerHTML = '';
  const base = defaults();
  state.recipe.forEach((ph, i) => {
    const diff = state.specs.filter((s) => ph.controls[s.name] !== base[s.name])
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
  const g = state.geometry ? state.geometry.read() : null; // null: the model's own feature
  return g ? { ...controlsBody(), geometry: g } : controlsBody();
}
// the scene of a run's feature (its Si top and opening), for the drawings in nm
const runScene = (r) => caseScene(state.model.scene, r && r.geometry);
function controlsBody() {
  if (!$('recipe-mode').checked) return { controls: readControls(), steps: horizon() };
  if (!state.recipe.length) throw new Error('recipe mode: add at least one phase (set the controls, then "Add phase")');
  const rows = [];
  for (const ph of state.recipe) for (let k = 0; k < Math.round(ph.duration * 10); k++) rows.push(ph.controls);
  if (rows.length > horizon()) throw new Error(`the recipe lasts ${rows.length / 10} s; at most ${horizon() / 10} s`);
  return { recipe: rows };
}

// --- metrics: undefined is a gap --------------------------------------------------------------------
// The API sends null where a metric is not defined yet (the hole has not reached the row it is measured
// on): the curves break there and the tables show "–".
const last = (vals) => vals[vals.length - 1];

// --- canvases fit their column ----------------------------------------------------------------------
// Each canvas is as wide as its panel (CSS) and drawn at the screen's resolution, in CSS pixels; the
// page redraws when the window changes size, so nothing is cut at 1280 x 720 or stretched at 1920 x 1080.
// A PNG export redraws its canvas at EXPORT_SCALE pixels per CSS pixel, whatever the screen's.
const EXPORT_SCALE = 2;
let drawScale = 0; // pixels per CSS pixel while drawing; 0: the screen's devicePixelRatio
function fitCanvas(c, cssH) {
  const dpr = drawScale || window.devicePixelRatio || 1, w = Math.max(120, Math.floor(c.clientWidth || c.parentElement.clientWidth));
  const W = Math.round(w * dpr), H = Math.round(cssH * dpr);
  if (c.width !== W) c.width = W;
  if (c.height !== H) c.height = H;
  const ctx = c.getContext('2d'); ctx.setTransform(dpr, 0, 0, dpr, 0, 0); ctx.clearRect(0, 0, w, cssH);
  ctx.font = FONT;
  return { ctx, w, h: cssH, dpr };
}
// the planes take the window's height below their top (the 3-D view above takes 0.4 of it, view3d.js), so
// both are in view unscrolled from 1280 x 720 up, whatever the legends above them wrap to
function planeHeight() {
  const top = $('section').getBoundingClientRect().top + window.scrollY;
  return Math.round(Math.min(380, Math.max(200, window.innerHeight - top - 14)));
}
let resizeQueued = false;
function redrawAll() {
  resizeQueued = false;
  if (view) { view.resize(); view.render(); }
  if (state.run) { drawPlanes(state.step); drawChart(); }
  if (state.mechanisms) drawMechanisms(state.mechanisms);
  if (state.sim) drawRmse(state.sim.result);
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
  const run = state.run; if (!run || !view) return;
  let drawn = false;
  for (const [obj, ch] of [[view.mask, 'mask'], [view.si, 'si']]) {
    const e = nearestSettled(run.id, state.step, ch);
    if (!e) continue; // nothing of this run yet: keep what is drawn
    if (e.geom && obj.geometry !== e.geom) obj.geometry = e.geom;
    if (!(obj === view.si && view.err.visible)) obj.visible = e.status === 'ok' && e.geom.attributes.position !== undefined;
    drawn = true;
  }
  view.render();
  // from the click on Run to the first frame with this run's surfaces
  if (drawn && run.t0 !== undefined && run.firstViewMs === undefined) {
    run.firstViewMs = performance.now() - run.t0;
    (state.firstViews = state.firstViews || []).push(run.firstViewMs);
  }
}
function forgetMeshes(keepId) {
  for (const key of meshes.entries.keys()) if (!key.startsWith(`${keepId}|`)) meshes.entries.delete(key);
}
state.surfacePixels = () => (view ? view.surfacePixels() : 0);
state.meshReady = (step) => !!state.run && CHANNELS.every((ch) => settled(meshes.entries.get(meshKey(state.run.id, step, ch))));
state.meshStats = () => {
  const n = { requests: meshes.requests };
  for (const e of meshes.entries.values()) n[e.status] = (n[e.status] || 0) + 1;
  return n;
};

// --- the plane through the hole axis: cross-section and etch profile ------------------------------------
function drawPlanes(step) {
  const h = planeHeight(), sec = fitCanvas($('section'), h), prof = fitCanvas($('profile'), h);
  if (!state.slices) return;
  const panels = [[state.slices, state.a && state.a.slices ? 'current' : '']];
  if (state.a && state.a.slices) panels.push([state.a.slices, 'A']);
  drawSection(sec.ctx, sec, panels, step, runScene(state.run), sec.dpr);
  const run = state.run, tmax = run.times_s[run.steps], dt = tmax / run.steps;
  const times = ticksWithin(0, tmax, 5);
  const lines = times.ticks.map((t, q) => ({
    sl: state.slices, step: Math.round(t / dt), label: `t = ${times.label(t)} s`, colour: timeColour(q / Math.max(1, times.ticks.length - 1)),
  }));
  lines.push({ sl: state.slices, step, label: `now (${run.times_s[step].toFixed(1)} s)`, colour: '#000', width: 2.2 });
  if (state.a && state.a.slices) lines.push({ sl: state.a.slices, step: Math.min(step, state.a.steps), label: 'A, now', colour: '#d62728', width: 1.8, dash: [5, 3] });
  state.fit.profile = drawProfile(prof.ctx, prof, lines, runScene(state.run));
}

// --- chart ------------------------------------------------------------------------------------------
function drawChart() {
  const c = $('chart'), { ctx, w: cw, h: ch } = fitCanvas(c, 260);
  const run = state.run; if (!run) return;
  const names = Object.keys(run.metrics);
  const series = [[run, []], [state.a, [6, 4]], [state.sim, [2, 3]]].filter(([s]) => s);
  let ymin = 0, ymax = 1;
  for (const [s] of series) for (const n of names) for (const v of (s.metrics[n] || [])) if (v !== null) { ymin = Math.min(ymin, v); ymax = Math.max(ymax, v); }
  const tmax = Math.max(...series.map(([s]) => last(s.times_s)));
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
const fixed = (x, d = 1) => (Math.abs(x) < 0.5 * 10 ** -d ? 0 : x).toFixed(d); // no "-0.0"
const nm1 = (x) => (x === null || x === undefined ? '–' : fixed(x));
function metricsTable() {
  const run = state.run; if (!run) return;
  const k = state.step, cols = [['current', run]];
  if (state.a) cols.push(['A', state.a]);
  if (state.sim) cols.push(['simulator', state.sim]);
  let html = `<table><tr><th>at t = ${run.times_s[k].toFixed(1)} s (nm)</th>${cols.map(([n]) => `<th>${n}</th>`).join('')}</tr>`;
  for (const n of Object.keys(run.metrics)) html += `<tr><td>${n}</td>${cols.map(([, s]) => `<td>${nm1((s.metrics[n] || [])[Math.min(k, s.metrics[n].length - 1)])}</td>`).join('')}</tr>`;
  $('final-metrics').innerHTML = `${html}</table><p class="hint">– : not defined yet (the etch has not reached the row it is measured on)</p>`;
}

// --- time -------------------------------------------------------------------------------------------
function setStep(step) {
  state.step = step; $('time').value = step;
  $('time-label').textContent = `t = ${state.run.times_s[step].toFixed(1)} s (step ${step})`;
  if (view.err.visible) { view.showError(null); delete $('view3d').dataset.errorShown; }
  show3d(); pumpMeshes(); drawPlanes(step); drawChart(); metricsTable();
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

// --- warnings in plain language ---------------------------------------------------------------------
/** The model's measured errors as /model reports them: per evaluation set, mean surface distance
 * (Chamfer, voxels -> nm) and field RMSE; sets named ood* were held out beyond the trained range. */
function measuredErrors() {
  const m = (state.model && state.model.metrics) || {}, vox = state.model.scene.voxel_nm;
  const has = (v) => v && typeof v === 'object' && (typeof v.cd === 'number' || typeof v.avg_rmse === 'number');
  const sets = Object.entries(m).filter(([, v]) => has(v));
  if (!sets.length && has(m)) sets.push(['test set', m]);
  const text = (v) => [
    typeof v.cd === 'number' ? `surfaces ${(v.cd * vox).toFixed(1)} nm from the simulator's on average` : '',
    typeof v.avg_rmse === 'number' ? `field RMSE ${v.avg_rmse.toFixed(3)} of the normalized SDF` : '',
  ].filter(Boolean).join(', ');
  const ood = ([k]) => /^ood/i.test(k);
  return {
    inside: sets.filter((e) => !ood(e)).map(([k, v]) => [k, text(v)]),
    outside: sets.filter(ood).map(([k, v]) => [k, text(v), v.ood_controls]),
  };
}
function rangeNote(ex, clipped) {
  const items = ex.map((e) => `<li><b>${esc(e.control)}</b> = ${fmt(e.value)} ${esc(e.unit)}: ${e.side} the trained range `
    + `${fmt(e.train_min)}–${fmt(e.train_max)}</li>`).join('');
  let html = '<p><b>⚠ Outside the trained range.</b> The model learned from simulations with every control inside its '
    + `trained range. Here:</p><ul>${items}</ul>`;
  html += clipped
    ? '<p>The server clipped these controls to the edge of the range (its policy): the prediction is for the clipped values, '
      + 'not the ones set.</p>'
    : '<p>The prediction is an extrapolation: it may be off by more than the model\'s usual error, even when it looks '
      + 'plausible. Check it with “Verify with simulator”.</p>';
  const err = measuredErrors(), names = new Set(ex.map((e) => e.control));
  const out = err.outside.filter(([, , ctl]) => !ctl || ctl.some((c) => names.has(c)));
  if (out.length) html += `<p>Measured beyond the trained range (held-out simulations): ${out.map(([k, t]) => `${esc(k)}: ${t}`).join('; ')}.</p>`;
  else html += '<p>This server reports no measured error outside the range.</p>';
  if (err.inside.length) html += `<p class="hint">Inside the range, measured on held-out simulations: ${err.inside.map(([k, t]) => `${esc(k)}: ${t}`).join('; ')}.</p>`;
  return html;
}
const TRUST_WHERE = {
  'in-box': 'inside the trained region, near the recipes the model learned from',
  corner: 'inside the control box but far from every recipe the model learned from (towards a face or corner)',
  'zero-flux': 'with some fluxes switched off',
  'axis 1.5': 'up to half a box half-width outside the trained range',
  'axis 2': 'up to one box half-width outside the trained range',
  angle: 'with angular exponents far outside the trained range',
  beyond: 'more than one box half-width outside the trained range',
};
const TRUST_WORD = { ok: '✓ Trusted here', warn: '⚠ Less certain here', reject: '✗ Not to be trusted here' };
/** The server's verdict on where the recipe lies and the error its extrapolation benchmark measured there. */
function showTrust(t) {
  const box = $('trust');
  box.hidden = !t;
  if (!t) return;
  box.className = `level-${t.level}`;
  const g = t.geometry;
  if (g && !g.inside) {  // the feature, not the recipe, decides: say so first (the controls' verdict after)
    const f = g.feature;
    box.innerHTML = `<p><b>${TRUST_WORD[t.level] || esc(t.level)}</b>: this model never saw a ${esc(f.kind)} of CD `
      + `${fmt(f.cd_nm)} nm under ${fmt(f.mask_nm)} nm of mask; the prediction is an extrapolation in geometry, `
      + `not measured.</p><p class="hint">The recipe alone: ${TRUST_WORD[t.controls_level] || esc(t.controls_level)}, `
      + `${TRUST_WHERE[t.group] || esc(t.group)}.</p>`;
    return;
  }
  let html = `<p><b>${TRUST_WORD[t.level] || esc(t.level)}</b>: this recipe lies ${TRUST_WHERE[t.group] || esc(t.group)}.</p>`;
  const m = t.measured;
  if (m) {
    const nm = (k, label) => (k in m.mae_nm ? `${label} ${fmt(m.mae_nm[k])} nm (simulator seed to seed ${fmt(m.seed_to_seed_nm[k])})` : '');
    const parts = [nm('etch_depth', 'depth'), nm('top_width', 'top width'), nm('bottom_width', 'bottom width')].filter(Boolean);
    html += `<p class="hint">Measured there on ${m.cases} simulated recipes: field error ${fmt(m.ratio_to_in_box)}× the in-box error; `
      + `mean errors ${parts.join(', ')}.</p>`;
  } else {
    html += `<p class="hint">${esc(t.reason)}.</p>`;
  }
  box.innerHTML = html;
}
function showWarnings(data) {
  showTrust(data.trust);
  const ex = data.extrapolation || [];
  const other = data.warnings.filter((w) => !(ex.length && /outside the training range/.test(w)));
  let html = ex.length ? rangeNote(ex, data.clipped) : '';
  html += other.map((w) => `<p>⚠ ${esc(w)}</p>`).join('');
  if (ex.length) html += `<details><summary>the server's words</summary>${data.warnings.map((w) => `<p class="hint">${esc(w)}</p>`).join('')}</details>`;
  const box = $('warnings'); box.hidden = !html; box.innerHTML = html;
}

// --- run --------------------------------------------------------------------------------------------
async function run() {
  showError('');
  let body;
  try { body = requestBody(); } catch (e) { showError(e.message); markStale(true); return; }
  if (state.playing) togglePlay();
  $('run').disabled = true; $('run').textContent = 'Running…'; $('play').disabled = true;
  const t0 = performance.now();
  try {
    const { data } = await api('POST', '/rollout', body);
    (state.rolloutMs = state.rolloutMs || []).push(performance.now() - t0);
    data.t0 = t0;
    state.run = data; state.body = body; state.sim = null; markStale(false);
    $('comparison').innerHTML = ''; $('rmse').hidden = true; $('job-status').textContent = '';
    showWarnings(data);
    for (const s of state.specs) state.inputs[s.name].div.classList.remove('api-out');
    for (const e of data.extrapolation || []) if (state.inputs[e.control]) state.inputs[e.control].div.classList.add('out', 'api-out');
    // the final state first: its surfaces are asked for while the cross-sections load
    const slider = $('time'); slider.disabled = true; slider.max = data.steps; slider.value = data.steps;
    forgetMeshes(data.id); state.step = data.steps; view.showError(null); view.placeFrame(runScene(data).si_top); pumpMeshes();
    const [sl] = await Promise.all([
      api('GET', `/rollouts/${data.id}/slices`).then((x) => x.data), meshesSettled(data.id, data.steps),
    ]);
    sl.bytes = Uint8Array.from(atob(sl.data), (ch) => ch.charCodeAt(0)); state.slices = sl;
    slider.disabled = false;
    setStep(data.steps);
    if (state.a) renderAB();
    (state.readyMs = state.readyMs || []).push(performance.now() - t0);
    document.body.dataset.runs = String((+document.body.dataset.runs || 0) + 1);
    for (const id of ['play', 'pin-a', 'mech-run']) $(id).disabled = false;
    for (const b of document.querySelectorAll('#exports button')) b.disabled = false;
    syncJobButtons();
    if (!$('recipe-mode').checked) mechanisms('for the controls of this run');
    else {
      state.mechanisms = null; fitCanvas($('mech'), 20);
      $('mech-note').textContent = 'A recipe changes the controls over time; the mechanisms are computed for one constant set: press Compute to analyse the controls set on the left.';
    }
  } catch (e) {
    showError(e.message); markStale(true);
  } finally { $('run').disabled = false; $('run').textContent = 'Run'; $('play').disabled = !state.run; }
}

// --- mechanisms -------------------------------------------------------------------------------------
async function mechanisms(note = 'for the controls set on the left') {
  const body = { controls: readControls() };
  $('mech-note').textContent = 'computing…';
  try {
    const g = state.geometry.read();
    state.mechanisms = (await api('POST', '/mechanisms', g ? { ...body, geometry: g } : body)).data.result;
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
  const pct = (v) => `${fixed(v)}%`;
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
  if (!state.a || !state.run) { drawChart(); if (state.run) drawPlanes(state.step); return; }
  // a control's values over the run, consecutive repeats merged (one value for constant controls)
  const seq = (r, n) => (r.recipe ? r.recipe.map((c) => c[n]) : [r.controls[n]]).filter((v, i, a) => i === 0 || v !== a[i - 1]);
  const show = (vals) => vals.map(fmt).join(' → ');
  const diff = state.specs.filter((s) => show(seq(state.a, s.name)) !== show(seq(state.run, s.name)));
  let html = '<table><tr><th>control (over time)</th><th>A</th><th>current</th></tr>';
  html += diff.map((s) => `<tr><td>${s.name}</td><td>${show(seq(state.a, s.name))}</td><td>${show(seq(state.run, s.name))}</td></tr>`).join('') || '<tr><td colspan=3>same controls</td></tr>';
  html += '</table><table><tr><th>final (nm)</th><th>A</th><th>current</th><th>current − A</th></tr>';
  for (const n of Object.keys(state.run.metrics)) {
    const a = last(state.a.metrics[n]), b = last(state.run.metrics[n]);
    html += `<tr><td>${n}</td><td>${nm1(a)}</td><td>${nm1(b)}</td><td>${a !== null && b !== null ? fixed(b - a) : '–'}</td></tr>`;
  }
  box.innerHTML = `${html}</table>`;
  drawChart(); metricsTable(); drawPlanes(state.step);
}

// --- simulator jobs ---------------------------------------------------------------------------------
async function verify() {
  showError('');
  if (!jobs.start('simulator')) return;
  const body = { ...state.body, steps: state.run.steps }, run = state.run;
  $('job-progress').hidden = false; $('job-progress').value = 0;
  try {
    const { data } = await api('POST', '/simulations', body);
    $('job-status').textContent = `job ${data.id}: ${data.status}`;
    state.job = data; $('job-cancel').hidden = false;
    const job = await followJob(data.location, (j) => {
      $('job-progress').value = j.progress; $('job-status').textContent = `job ${j.id}: ${j.status} (${Math.round(100 * j.progress)}%)`;
    });
    if (job.status === 'cancelled') { $('job-status').textContent = `job ${job.id}: cancelled`; return; }
    if (job.status !== 'done') { showError(`simulator job ${job.status}: ${job.message || ''}`); return; }
    if (state.run === run) showComparison(job.result);
  } catch (e) { showError(e.message); } finally {
    jobs.end(); $('job-progress').hidden = true; $('job-cancel').hidden = true;
  }
}
/** The job's field RMSE (normalized SDF) in nm: the SDF is normalized by, and clipped at, d_max. */
const sdfNm = (v) => (v === null ? null : v * state.model.scene.d_max_nm);
function drawRmse(res) {
  const { ctx, w: cw, h: ch } = fitCanvas($('rmse'), 150);
  const r = res.rmse_per_step.map(sdfNm), times = res.times_s || r.map((_, k) => k / 10);
  const yt = niceTicks(0, Math.max(1e-6, ...r.filter((v) => v !== null))), xt = niceTicks(0, last(times));
  const L = 8 + Math.max(...yt.ticks.map((v) => ctx.measureText(yt.label(v)).width)), T = 18, B = 30, w = cw - L - 8, h = ch - T - B;
  const X = (t) => L + (w * t) / xt.hi, Y = (v) => T + h * (1 - v / yt.hi);
  ctx.strokeStyle = '#99a'; ctx.strokeRect(L, T, w, h); ctx.fillStyle = '#445';
  ctx.textAlign = 'right'; for (const v of yt.ticks) ctx.fillText(yt.label(v), L - 4, Y(v) + 4);
  ctx.textAlign = 'center'; for (const t of xt.ticks) ctx.fillText(xt.label(t), X(t), T + h + 13);
  ctx.fillText('time (s)', L + w / 2, ch - 4);
  ctx.textAlign = 'left'; ctx.fillText(`nm: RMSE of the signed distance (surrogate vs simulator, per state; clipped at ±${state.model.scene.d_max_nm} nm)`, 2, 11);
  ctx.strokeStyle = '#d62728'; ctx.beginPath(); let pen = false;
  r.forEach((v, k) => { if (v === null) { pen = false; return; } pen ? ctx.lineTo(X(times[k]), Y(v)) : ctx.moveTo(X(times[k]), Y(v)); pen = true; });
  ctx.stroke();
}
function showComparison(res) {
  state.sim = { metrics: res.simulator_metrics, times_s: res.times_s, result: res };
  const surrogate = res.surrogate_metrics;
  $('rmse').hidden = false; drawRmse(res);
  let html = `<p>avg RMSE ${sdfNm(res.avg_rmse).toFixed(2)} nm (signed distance), simulator ${res.simulator_s.toFixed(1)} s, seed ${res.seed}</p>`;
  html += '<table><tr><th>final (nm)</th><th>surrogate</th><th>simulator</th><th>difference</th></tr>';
  for (const n of Object.keys(res.final_differences)) {
    const s = last(surrogate[n]), m = last(state.sim.metrics[n]);
    html += `<tr><td>${n}</td><td>${nm1(s)}</td><td>${nm1(m)}</td><td>${s !== null && m !== null ? fixed(s - m) : '–'}</td></tr>`;
  }
  html += '</table><button id="show-err">Show the simulator\'s Si surface at this time, coloured by the surrogate\'s error</button>';
  const box = $('comparison'); box.innerHTML = html; box.dataset.done = '1';
  $('show-err').addEventListener('click', () => showErrorSurface(res));
  drawChart(); metricsTable();
}
async function showErrorSurface(res) {
  const step = Math.min(state.step, res.steps);
  try {
    const r = await fetchPatiently(res.mesh.replace(/step=\d+/, `step=${step}`));
    if (!r.ok) {
      throw new Error(r.status === 410 ? 'the server no longer keeps this check\'s trajectories: run “Verify with simulator” again'
        : `the error surface could not be loaded (HTTP ${r.status})`);
    }
    view.showError(parseGLB(await r.arrayBuffer()));
    $('view3d').dataset.errorShown = String(step);
  } catch (e) { showError(e.message); }
}

// --- exports ----------------------------------------------------------------------------------------
async function exportFile(kind) {
  const run = state.run; if (!run) return;
  const id = run.id, step = state.step, ch = $('export-channel').value, f = $('export-format').value;
  try {
    let name;
    if (kind === 'csv') name = await download(`/rollouts/${id}/metrics.csv`, `nemsim_${id}_metrics.csv`);
    else if (kind === 'h5') name = await download(`/rollouts/${id}/trajectory.h5`, `nemsim_${id}_trajectory.h5`);
    else if (kind === 'mesh') name = await download(`/rollouts/${id}/mesh?step=${step}&channel=${ch}&format=${f}`, `nemsim_${id}_step${step}_${ch}.${f}`);
    else {
      const which = $('export-view').value;
      name = `nemsim_${id}_step${step}_${which}.png`;
      const caption = `NEMSim ${run.model_id} · t = ${run.times_s[step].toFixed(1)} s (step ${step})`;
      saveBlob(which === '3d' ? await view.png(caption, EXPORT_SCALE) : await canvasPng($(which)), name);
    }
    $('export-status').textContent = `saved ${name}`;
  } catch (e) { showError(e.message); }
}
/** A 2-D view as a PNG blob: redrawn at EXPORT_SCALE, copied, and redrawn for the screen (one task: the
 * page never shows the export's frame). */
function canvasPng(c) {
  const redraw = () => (c.id === 'chart' ? drawChart() : drawPlanes(state.step));
  drawScale = EXPORT_SCALE; redraw();
  const out = document.createElement('canvas'); out.width = c.width; out.height = c.height;
  const ctx = out.getContext('2d'); ctx.fillStyle = '#fff'; ctx.fillRect(0, 0, out.width, out.height); ctx.drawImage(c, 0, 0);
  drawScale = 0; redraw();
  return new Promise((resolve) => out.toBlob(resolve, 'image/png'));
}

// --- start ------------------------------------------------------------------------------------------
function wire() {
  $('run').addEventListener('click', run);
  $('reset').addEventListener('click', () => setControls(defaults()));
  $('time').addEventListener('input', (e) => setStep(+e.target.value));
  $('play').addEventListener('click', togglePlay);
  $('pin-a').addEventListener('click', pinA);
  $('clear-a').addEventListener('click', () => { state.a = null; $('clear-a').disabled = true; $('ab-label').textContent = ''; renderAB(); });
  $('mech-run').addEventListener('click', () => mechanisms());
  $('verify').addEventListener('click', verify);
  $('job-cancel').addEventListener('click', () => state.job && api('DELETE', state.job.location).catch((e) => showError(e.message)));
  $('recipe-mode').addEventListener('change', (e) => { $('recipe').hidden = !e.target.checked; });
  $('add-phase').addEventListener('click', () => { state.recipe.push({ duration: 2.5, controls: readControls() }); renderRecipe(); });
  for (const t of ['controls', 'design']) $(`tab-${t}-btn`).addEventListener('click', () => showTab(t));
  for (const [id, kind] of [['export-csv', 'csv'], ['export-h5', 'h5'], ['export-mesh', 'mesh'], ['export-png', 'png']]) $(id).addEventListener('click', () => exportFile(kind));
  window.addEventListener('resize', () => { if (!resizeQueued) { resizeQueued = true; requestAnimationFrame(redrawAll); } });
  // the planes fill the height below the 3-D view and the time bar: redrawn when a legend there wraps anew
  const above = new ResizeObserver(() => { if (state.slices) drawPlanes(state.step); });
  for (const el of [$('view3d'), $('time').parentElement]) above.observe(el);
}
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
  buildControls();
  view = createView($('canvas3d'), info.scene, { cutaway: $('cutaway'), legend: $('legend-text'), colourbar: $('colourbar') });
  state.geometry = initGeometry({ model: info, api, fmt, requestBody: controlsBody, onChange: () => {} });
  state.design = initDesign({
    model: info, specs: state.specs, defaults: defaults(), fmt, api, followJob, jobs, geometry: () => state.geometry.read(),
    load: (controls) => { $('recipe-mode').checked = false; $('recipe').hidden = true; setControls(controls); showTab('controls'); run(); },
  });
  wire();
  $('run').disabled = false;
  state.setStep = setStep; state.view = view;
  document.body.dataset.ready = '1';
}
start();
