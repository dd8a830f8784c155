// Inverse design on the page: targets in nm -> a `POST /design` job (progress, cancel) -> ranked recipes
// with the model's intervals and a training-data flag -> "Load & run" puts a recipe into the controls and
// runs it, after which "Verify with simulator" checks it. Built on the API as it is: each card says what its
// `verdict` says (predicted by the surrogate, or confirmed by the simulator), the job's `phase` is the progress
// line, and `expected_calls_to_target` is shown as what it is, the benchmark's average.

const METRICS = [ // what `POST /design` accepts, with its default tolerance (nm) and physical range
  ['etch_depth', 'etch depth', 5, (s) => s.si_top * s.voxel_nm],
  ['top_width', 'top width', 3, (s) => Math.min(s.nx, s.ny) * s.voxel_nm],
  ['bottom_width', 'bottom width', 3, (s) => Math.min(s.nx, s.ny) * s.voxel_nm],
  ['mask_loss', 'mask loss', 2, (s) => (s.resist_top - s.si_top) * s.voxel_nm],
  ['bowing', 'bowing', 2, (s) => Math.min(s.nx, s.ny) * s.voxel_nm],
];
const VERDICT = { // a recipe's `verdict` -> [class, words]
  confirmed: ['ok', 'confirmed by the simulator: meets every target'],
  simulator_miss: ['warn', 'missed a target in the simulator'],
  predicted: ['ok', 'predicted to meet every target (not simulated)'],
  predicted_miss: ['warn', 'predicted to miss a target'],
};
const FLAG = {
  inside: 'near the training data',
  far: '⚠ far from every training case: less reliable',
  outside_box: '⚠ outside the trained range: an extrapolation',
};
const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);
const nm = (v) => (v === null || v === undefined ? '–' : (Math.abs(v) < 0.05 ? 0 : v).toFixed(1)); // no "-0.0"

/** Wire the design tab. `page`: {model, api, followJob, jobs: {start(what), end()}, load(controls), fmt, defaults}. */
export function initDesign(page) {
  const sc = page.model.scene, dt = sc.snapshot_dt_s || 0.1, horizonS = page.model.horizon_steps * dt;
  const rows = METRICS.map(([name, label, tol, hi]) => `<tr><td class="left">${label}</td>
    <td><input type="number" id="t-${name}" min="0" max="${+hi(sc).toFixed(1)}" step="any" placeholder="0–${+hi(sc).toFixed(0)}"></td>
    <td><input type="number" id="tol-${name}" min="0.1" step="any" placeholder="${tol}"></td></tr>`).join('');
  $('design-targets').innerHTML = `<tr><th>target</th><th>value (nm)</th><th>± tol (nm)</th></tr>${rows}`;
  $('design-time').max = horizonS; $('design-time').placeholder = `${horizonS}`;
  const state = { job: null, result: null };
  $('design-run').addEventListener('click', () => run(page, state));
  $('design-cancel').addEventListener('click', () => state.job && page.api('DELETE', state.job).catch((e) => status(e.message)));
  return state;
}

function status(text) { $('design-status').textContent = text; }

function requestBody(page) {
  const targets = {};
  for (const [name] of METRICS) {
    const v = $(`t-${name}`).value.trim(), tol = $(`tol-${name}`).value.trim();
    if (v === '') continue;
    targets[name] = tol === '' ? { value: Number(v) } : { value: Number(v), tol: Number(tol) };
  }
  if (!Object.keys(targets).length) throw new Error('inverse design: give at least one target value (nm)');
  const body = { targets, k: Math.round(Number($('design-k').value) || 3) };
  const g = page.geometry ? page.geometry() : null; // the feature set on the Controls tab (null: the model's own)
  if (g) body.geometry = g;
  const t = $('design-time').value.trim();
  if (t !== '') body.step = Math.max(1, Math.round(Number(t) / (page.model.scene.snapshot_dt_s || 0.1)));
  return body;
}

async function run(page, state) {
  let body;
  try { body = requestBody(page); } catch (e) { status(e.message); return; }
  if (!page.jobs.start('design')) { status('a simulator check is running: the server runs one job per client at a time'); return; }
  $('design-run').disabled = true; $('design-progress').hidden = false; $('design-progress').value = 0;
  $('design-result').innerHTML = ''; status('submitting…');
  try {
    const { data } = await page.api('POST', '/design', body);
    state.job = data.location; $('design-cancel').hidden = false;
    const job = await page.followJob(data.location, (j) => {
      $('design-progress').value = j.progress; status(`${j.phase || j.status} (${Math.round(100 * j.progress)}%)`);
    });
    if (job.status === 'cancelled') { status('cancelled'); return; }
    if (job.status !== 'done') { status(`the design failed: ${job.message || job.status}`); return; }
    state.result = job.result; status('');
    render(page, job.result);
  } catch (e) { status(e.message); } finally {
    page.jobs.end(); state.job = null;
    $('design-run').disabled = false; $('design-progress').hidden = true; $('design-cancel').hidden = true;
  }
}

function costLine(res) {
  const c = res.cost || {}, parts = [];
  if (c.rollouts !== undefined) parts.push(`${c.rollouts} surrogate rollouts`);
  if (c.wall_s !== undefined) parts.push(`${c.wall_s.toFixed(1)} s`);
  if (res.simulator_calls !== undefined) parts.push(`simulator calls: ${res.simulator_calls}`);
  const avg = res.expected_calls_to_target;
  if (typeof avg === 'number') {
    parts.push(`<span title="${esc(res.expected_calls_basis || '')}">benchmark average, the same for every design: ${+avg.toPrecision(3)} simulator calls per target reached</span>`);
  }
  return parts.join(' · ');
}

function render(page, res) {
  const recipes = res.recipes || [], ivs = recipes[0] && recipes[0].intervals;
  const level = ivs ? ('0.9' in ivs ? '0.9' : Object.keys(ivs)[0]) : null;
  const bands = level ? ` · brackets: ${Math.round(100 * level)} % interval of the prediction`
    : ' · no intervals (the server has no calibration for this model)';
  let html = `<p class="${res.status === 'met' || res.status === 'verified' ? 'ok' : 'warn'}">${esc(res.message || res.status)}</p>`;
  html += `<p class="hint">targets at t = ${(+res.time_s).toFixed(1)} s · ${costLine(res)}${bands}</p>`;
  recipes.forEach((r, i) => {
    const sim = r.simulated_targets; // present when the simulator ran this recipe
    const rows = Object.entries(r.targets).map(([m, t]) => {
      const iv = level && r.intervals[level] && r.intervals[level][m]; // cut to the physical range by the server
      const band = iv ? ` [${nm(iv[0])}, ${nm(iv[1])}]` : '';
      const goal = `${+t.target.toPrecision(4)} ± ${+t.tol.toPrecision(3)}`;
      const met = sim ? sim[m].met : t.met, simCell = sim ? `<td>${nm(sim[m].value)}</td>` : '';
      return `<tr><td class="left">${m}</td><td>${nm(t.value)}${band}</td>${simCell}<td>${goal}</td><td>${met ? '✓' : '✗'}</td></tr>`;
    }).join('');
    const changed = page.specs.filter((s) => r.controls[s.name] !== page.defaults[s.name])
      .map((s) => `${s.name} = ${page.fmt(r.controls[s.name])} ${s.unit}`).join('<br>') || '(the defaults)';
    const flag = (r.training_data && FLAG[r.training_data.flag]) || '';
    const [cls, words] = VERDICT[r.verdict] || VERDICT.predicted_miss;
    const wide = r.verdict === 'predicted' && level && r.intervals_within_tolerance && !r.intervals_within_tolerance[level]
      ? `<div class="hint">its ${Math.round(100 * level)} % interval is wider than the tolerance: only the simulator can confirm it</div>` : '';
    html += `<div class="recipe-card"><div class="bar"><b>#${r.rank}</b>
      <span class="${cls}">${words}</span>
      <button class="load" data-i="${i}">Load &amp; run</button></div>
      ${wide}<div class="hint">${esc(flag)}</div>
      <table><tr><th>metric (nm)</th><th>predicted</th>${sim ? '<th>simulator</th>' : ''}<th>target</th><th></th></tr>${rows}</table>
      <details><summary>controls</summary><div class="hint">${changed}</div></details></div>`;
  });
  const box = $('design-result'); box.innerHTML = html; box.dataset.done = '1';
  box.querySelectorAll('button.load').forEach((b) => b.addEventListener('click', () => page.load(recipes[+b.dataset.i].controls)));
}
