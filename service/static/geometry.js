// The feature etched (the API's `geometry` block: kind, CD and mask in nm): its inputs with the model's own
// feature prefilled, a cross-section sketch of it, the trained ranges beside it, and A/B: the same recipe on
// two features, their final profile metrics side by side. The page sends the block with every rollout,
// simulator check, design and mechanisms request.

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);
const KINDS = ['hole', 'trench'];

/** The per-case scene a feature draws on the model's grid (nemsim.geometry.feature.Feature.apply): the mask
 * top stays, the Si top moves with the mask, the opening is cd / 2. */
export function caseScene(scene, g) {
  if (!g) return scene;
  const v = scene.voxel_nm;
  return { ...scene, kind: g.kind, si_top: scene.resist_top - Math.round(g.mask_nm / v), opening_radius_vox: g.cd_nm / 2 / v };
}

const plural = (kind) => (kind.endsWith('h') ? `${kind}es` : `${kind}s`); // holes, trenches
const end = (v) => Number(v.toFixed(2)); // a trained range's ends as recorded, to 0.01 nm
const span = (r) => (r[0] === r[1] ? `${end(r[0])} nm` : `${end(r[0])}–${end(r[1])} nm`);

/** Draw the cross-section sketch of features `gs` ([{g, colour, dash}]) on the scene's pitch. */
function sketch(canvas, scene, gs) {
  const dpr = window.devicePixelRatio || 1, w = Math.max(120, canvas.clientWidth || 160), h = 84;
  canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
  const ctx = canvas.getContext('2d'); ctx.setTransform(dpr, 0, 0, dpr, 0, 0); ctx.clearRect(0, 0, w, h);
  const v = scene.voxel_nm, pitch = scene.nx * v, top = scene.resist_top * v;
  const sx = (w - 8) / pitch, sz = (h - 14) / top, X = (x) => 4 + x * sx, Z = (z) => h - 4 - z * sz;
  gs.forEach(({ g, colour, dash }, i) => {
    const si = top - Math.round(g.mask_nm / v) * v, c = pitch / 2, r = g.cd_nm / 2;
    ctx.setLineDash(dash || []);
    if (i === 0) { // the first feature filled: Si orange, mask grey
      ctx.fillStyle = '#e0913c'; ctx.fillRect(X(0), Z(si), pitch * sx, si * sz);
      ctx.fillStyle = '#8a8f99';
      ctx.fillRect(X(0), Z(top), (c - r) * sx, (top - si) * sz); ctx.fillRect(X(c + r), Z(top), (pitch - c - r) * sx, (top - si) * sz);
    }
    ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
    ctx.moveTo(X(0), Z(top)); ctx.lineTo(X(c - r), Z(top)); ctx.lineTo(X(c - r), Z(si)); ctx.lineTo(X(c + r), Z(si));
    ctx.lineTo(X(c + r), Z(top)); ctx.lineTo(X(pitch), Z(top)); ctx.stroke();
  });
  ctx.setLineDash([]); ctx.fillStyle = '#334'; ctx.font = '10px system-ui, sans-serif';
  ctx.fillText(`${gs[0].g.kind}: CD ${gs[0].g.cd_nm} nm, mask ${gs[0].g.mask_nm} nm, pitch ${pitch} nm`, 4, 10);
}

/**
 * Wire the geometry panel. `page`: { model (GET /model), api, fmt, requestBody() (the current controls
 * or recipe), onChange() }. Returns { read(): the A block (null: the model's own), readB() }.
 */
export function initGeometry(page) {
  const info = page.model.geometry, scene = page.model.scene;
  const trained = info.kinds;
  for (const id of ['geo-kind', 'geo-b-kind']) {
    $(id).innerHTML = KINDS.map((k) => `<option value="${k}"${k in trained ? '' : ' disabled'}>${k}${k in trained ? '' : ' (not trained)'}</option>`).join('');
  }
  const set = (p, g) => { $(`${p}-kind`).value = g.kind; $(`${p}-cd`).value = g.cd_nm; $(`${p}-mask`).value = g.mask_nm; };
  const readOf = (p) => {
    const g = { kind: $(`${p}-kind`).value, cd_nm: Number($(`${p}-cd`).value), mask_nm: Number($(`${p}-mask`).value) };
    for (const k of ['cd_nm', 'mask_nm']) if (!(Number.isFinite(g[k]) && g[k] > 0)) throw new Error(`feature ${k.replace('_nm', '')}: a number of nm > 0`);
    return g;
  };
  const same = (a, b) => a.kind === b.kind && a.cd_nm === b.cd_nm && a.mask_nm === b.mask_nm;
  set('geo', info.default);
  set('geo-b', { ...info.default, cd_nm: info.default.cd_nm + 10 });
  const note = () => {
    let a = null, b = null;
    try { a = readOf('geo'); b = readOf('geo-b'); } catch (e) { $('geo-note').textContent = e.message; return; }
    const r = trained[a.kind];
    const inside = r && a.cd_nm >= r.cd_nm[0] && a.cd_nm <= r.cd_nm[1] && a.mask_nm >= r.mask_nm[0] && a.mask_nm <= r.mask_nm[1];
    $('geo-note').textContent = r
      ? `trained on ${plural(a.kind)} of CD ${span(r.cd_nm)}, mask ${span(r.mask_nm)}${inside ? '' : ': outside, the answer is not to be trusted'}`
      : `this model was not trained on ${plural(a.kind)}`;
    $('geo-note').classList.toggle('warn', !inside);
    sketch($('geo-sketch'), scene, [{ g: a, colour: '#1d2430' }, { g: b, colour: '#d62728', dash: [4, 3] }]);
    page.onChange();
  };
  for (const id of ['geo-kind', 'geo-cd', 'geo-mask', 'geo-b-kind', 'geo-b-cd', 'geo-b-mask']) $(id).addEventListener('input', note);
  $('geo-reset').addEventListener('click', () => { set('geo', info.default); note(); });
  $('geo-ab-run').addEventListener('click', () => compare(page, readOf));
  $('geo-ab-run').disabled = false;
  note();
  return {
    read() { const g = readOf('geo'); return same(g, info.default) ? null : g; },
    readB: () => readOf('geo-b'),
    redraw: note,
  };
}

/** A/B: the current controls (or recipe) on feature A and on feature B, final metrics side by side. */
async function compare(page, readOf) {
  const box = $('geo-ab'), btn = $('geo-ab-run');
  let base, a, b;
  try { base = page.requestBody(); a = readOf('geo'); b = readOf('geo-b'); } catch (e) { box.textContent = e.message; return; }
  btn.disabled = true; box.textContent = 'rolling out A and B…';
  try {
    const [ra, rb] = await Promise.all([a, b].map((g) => page.api('POST', '/rollout', { ...base, geometry: g }).then((x) => x.data)));
    const last = (vals) => vals[vals.length - 1];
    const nm = (v) => (v === null || v === undefined ? '–' : v.toFixed(1));
    const label = (r) => `${r.geometry.kind} ${r.geometry.cd_nm}/${r.geometry.mask_nm} nm`;
    let html = `<table><tr><th>final (nm)</th><th>A: ${esc(label(ra))}</th><th>B: ${esc(label(rb))}</th><th>B − A</th></tr>`;
    for (const n of Object.keys(ra.metrics)) {
      const x = last(ra.metrics[n]), y = last(rb.metrics[n]);
      html += `<tr><td>${n}</td><td>${nm(x)}</td><td>${nm(y)}</td><td>${x !== null && y !== null ? (y - x).toFixed(1) : '–'}</td></tr>`;
    }
    const trust = (r) => (r.trust ? r.trust.level : '–');
    html += `<tr><td>trust</td><td>${esc(trust(ra))}</td><td>${esc(trust(rb))}</td><td></td></tr></table>`;
    box.innerHTML = html;
    window.explorer.geometryAB = { a: ra, b: rb };
  } catch (e) { box.textContent = e.message; } finally { btn.disabled = false; }
}
