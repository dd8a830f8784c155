// 2-D drawing for the explorer: round ticks, the x-z plane through the hole axis in nm (the cross-section
// and the etch-profile view), zero-level outlines by marching squares, a scale bar and the colour bar of the
// error-coloured surface. Pure functions of their arguments: the page passes data, scene and a canvas.
//
// Choices: the plane is drawn at equal aspect (1 nm across = 1 nm down), so a tapered or bowed hole looks
// as it is; depth is measured down from the initial Si top (positive into the Si, negative in the mask), the
// convention of etch-profile plots; the SDF is sampled bilinearly between voxel centres, so the filled
// materials and the drawn outline (the zero level, sub-voxel) agree.

export const FONT = '11px system-ui';
const VACUUM = [238, 241, 245], MASK = [138, 143, 153], SI = [224, 145, 60];

/** Round tick values covering [lo, hi] (the axis is widened to the outer ticks). */
export function niceTicks(lo, hi, n = 5) {
  if (!(hi > lo)) hi = lo + 1;
  const step = niceStep((hi - lo) / n);
  const a = Math.floor(lo / step + 1e-9) * step, b = Math.ceil(hi / step - 1e-9) * step;
  return { lo: a, hi: b, ticks: range(a, b, step), label: labeller(step) };
}

/** Round tick values inside [lo, hi] (the axis keeps its limits: images at equal aspect). */
export function ticksWithin(lo, hi, n = 4) {
  const step = niceStep((hi - lo) / n);
  return { lo, hi, ticks: range(Math.ceil(lo / step - 1e-9) * step, hi, step), label: labeller(step) };
}

function niceStep(raw) {
  const mag = 10 ** Math.floor(Math.log10(raw)), f = raw / mag;
  return (f <= 1 ? 1 : f <= 2 ? 2 : f <= 2.5 ? 2.5 : f <= 5 ? 5 : 10) * mag;
}
function range(a, b, step) {
  const out = [];
  for (let k = 0; a + k * step <= b + step * 1e-6; k++) out.push(+(a + k * step).toPrecision(12));
  return out;
}
function labeller(step) {
  let dec = 0;
  while (dec < 6 && Math.abs(Math.round(step * 10 ** dec) - step * 10 ** dec) > 1e-6) dec++;
  return (v) => (Math.abs(v) < step * 1e-6 ? 0 : v).toFixed(dec);
}

/** A length of 1, 2 or 5 x 10^k nm that is at most `maxNm`. */
export function scaleBarNm(maxNm) {
  const mag = 10 ** Math.floor(Math.log10(maxNm));
  return [5, 2, 1].map((f) => f * mag).find((v) => v <= maxNm) || mag;
}

// --- the plane through the hole axis ---------------------------------------------------------------
/** nm coordinates of the slices' padded grid: column i -> x from the hole axis, row j -> depth below the
 * initial Si top (the field is padded by one voxel: index = native + 1). */
export function planeFrame(scene) {
  const v = scene.voxel_nm, cx = (scene.nx - 1) / 2;
  return {
    v, cx,
    xlim: [(-scene.nx * v) / 2, (scene.nx * v) / 2],
    dlim: [(scene.si_top - scene.nz) * v, scene.si_top * v],
    i: (x) => x / v + cx + 1, // nm -> fractional column
    j: (d) => scene.si_top - 0.5 - d / v + 1, // depth nm -> fractional row
    x: (i) => (i - 1 - cx) * v,
    d: (j) => (scene.si_top - 0.5 - (j - 1)) * v,
  };
}

/** Equal-aspect plot of the plane in `box` {x, y, w, h} (CSS px): margins for tick labels and titles. */
export function planeLayout(frame, box, right = 0) {
  const L = 34, T = 16, B = 30;
  const xr = frame.xlim[1] - frame.xlim[0], dr = frame.dlim[1] - frame.dlim[0];
  const s = Math.max(0.1, Math.min((box.w - L - right - 6) / xr, (box.h - T - B) / dr)); // px per nm
  const x0 = box.x + L, y0 = box.y + T;
  return {
    s, rect: { x: x0, y: y0, w: xr * s, h: dr * s },
    X: (x) => x0 + (x - frame.xlim[0]) * s,
    Y: (d) => y0 + (d - frame.dlim[0]) * s,
  };
}

/** Frame, round ticks in nm on both axes, axis titles. */
export function planeAxes(ctx, frame, P, title) {
  const { rect: r } = P, xt = ticksWithin(...frame.xlim, 4), dt = ticksWithin(...frame.dlim, 5);
  ctx.strokeStyle = '#99a'; ctx.lineWidth = 1; ctx.strokeRect(r.x, r.y, r.w, r.h);
  ctx.fillStyle = '#445'; ctx.font = FONT; ctx.beginPath();
  ctx.textAlign = 'center';
  for (const x of xt.ticks) { ctx.moveTo(P.X(x), r.y + r.h); ctx.lineTo(P.X(x), r.y + r.h + 3); ctx.fillText(xt.label(x), P.X(x), r.y + r.h + 13); }
  const xlabel = ctx.measureText('x from the axis (nm)').width <= r.w + 40 ? 'x from the axis (nm)' : 'x (nm)';
  ctx.fillText(xlabel, r.x + r.w / 2, r.y + r.h + 26);
  ctx.textAlign = 'right';
  for (const d of dt.ticks) { ctx.moveTo(r.x - 3, P.Y(d)); ctx.lineTo(r.x, P.Y(d)); ctx.fillText(dt.label(d), r.x - 5, P.Y(d) + 4); }
  ctx.stroke();
  ctx.textAlign = 'left';
  ctx.fillText(title, Math.max(2, r.x - 30), r.y - 5);
}

/** A horizontal scale bar of a round length at the plot's lower left, on a white backing. */
export function scaleBar(ctx, P) {
  const nm = scaleBarNm((0.45 * P.rect.w) / P.s), len = nm * P.s, x = P.rect.x + 6, y = P.rect.y + P.rect.h - 8;
  const label = `${nm} nm`, tw = ctx.measureText(label).width;
  ctx.fillStyle = '#ffffffd0'; ctx.fillRect(x - 3, y - 15, Math.max(len, tw) + 6, 19);
  ctx.fillStyle = '#1d2430'; ctx.fillRect(x, y - 2, len, 3);
  ctx.textAlign = 'left'; ctx.fillText(label, x, y - 5);
}

// --- fields of the slices -----------------------------------------------------------------------------
/** The plane of `channel` (0 mask, 1 Si, 'union' both) at `step` as signed values (q - 127.5 has the SDF's
 * sign; 0 is the surface). */
export function planeField(sl, step, channel) {
  const [n, , D, W] = sl.shape, plane = D * W, base = Math.min(step, n - 1) * 2 * plane;
  const out = new Float32Array(plane);
  for (let k = 0; k < plane; k++) {
    const m = sl.bytes[base + k], s = sl.bytes[base + plane + k];
    out[k] = (channel === 0 ? m : channel === 1 ? s : Math.min(m, s)) - 127.5;
  }
  return out;
}

function bilinear(f, W, D, i, j) {
  i = Math.min(Math.max(i, 0), W - 1); j = Math.min(Math.max(j, 0), D - 1);
  const i0 = Math.min(Math.floor(i), W - 2), j0 = Math.min(Math.floor(j), D - 2), a = i - i0, b = j - j0;
  const k = j0 * W + i0;
  return (1 - b) * ((1 - a) * f[k] + a * f[k + 1]) + b * ((1 - a) * f[k + W] + a * f[k + W + 1]);
}

/** Zero-level segments of a (D, W) field by marching squares: [i0, j0, i1, j1, ...] in grid indices. */
export function contour(f, W, D) {
  const seg = [];
  const cross = (a, b) => a / (a - b);
  for (let j = 0; j < D - 1; j++) for (let i = 0; i < W - 1; i++) {
    const v00 = f[j * W + i], v10 = f[j * W + i + 1], v01 = f[(j + 1) * W + i], v11 = f[(j + 1) * W + i + 1];
    const c = (v00 < 0) | ((v10 < 0) << 1) | ((v11 < 0) << 2) | ((v01 < 0) << 3);
    if (c === 0 || c === 15) continue;
    const e = [ // crossing points on the cell's edges: bottom, right, top, left
      (v00 < 0) !== (v10 < 0) ? [i + cross(v00, v10), j] : null,
      (v10 < 0) !== (v11 < 0) ? [i + 1, j + cross(v10, v11)] : null,
      (v01 < 0) !== (v11 < 0) ? [i + cross(v01, v11), j + 1] : null,
      (v00 < 0) !== (v01 < 0) ? [i, j + cross(v00, v01)] : null,
    ].filter(Boolean);
    if (e.length === 2) seg.push(...e[0], ...e[1]);
    else if (e.length === 4) { // a saddle: pair the edges by the sign at the cell's centre
      const centreIn = (v00 + v10 + v01 + v11) / 4 < 0, pairA = centreIn === (v00 < 0);
      if (pairA) seg.push(...e[0], ...e[1], ...e[2], ...e[3]);
      else seg.push(...e[0], ...e[3], ...e[1], ...e[2]);
    }
  }
  return seg;
}

function strokeContour(ctx, seg, frame, P) {
  ctx.beginPath();
  for (let k = 0; k < seg.length; k += 4) {
    ctx.moveTo(P.X(frame.x(seg[k])), P.Y(frame.d(seg[k + 1])));
    ctx.lineTo(P.X(frame.x(seg[k + 2])), P.Y(frame.d(seg[k + 3])));
  }
  ctx.stroke();
}

// --- the cross-section ----------------------------------------------------------------------------------
/** Materials of the plane at `step` (mask grey, Si orange), their outlines, nm axes and a scale bar; one
 * panel per [slices, label] side by side (the pinned run A beside the current one). */
export function drawSection(ctx, size, panels, step, scene, dpr) {
  const frame = planeFrame(scene), pw = size.w / panels.length;
  panels.forEach(([sl, label], p) => {
    const P = planeLayout(frame, { x: p * pw, y: 0, w: pw, h: size.h });
    const [, , D, W] = sl.shape, m = planeField(sl, step, 0), s = planeField(sl, step, 1);
    const r = P.rect, pxW = Math.max(1, Math.round(r.w * dpr)), pxH = Math.max(1, Math.round(r.h * dpr));
    const img = new ImageData(pxW, pxH);
    for (let y = 0; y < pxH; y++) {
      const j = frame.j(frame.dlim[0] + (y + 0.5) / (dpr * P.s));
      for (let x = 0; x < pxW; x++) {
        const i = frame.i(frame.xlim[0] + (x + 0.5) / (dpr * P.s));
        const rgb = bilinear(s, W, D, i, j) < 0 ? SI : bilinear(m, W, D, i, j) < 0 ? MASK : VACUUM;
        img.data.set(rgb, 4 * (y * pxW + x)); img.data[4 * (y * pxW + x) + 3] = 255;
      }
    }
    const tmp = document.createElement('canvas'); tmp.width = pxW; tmp.height = pxH;
    tmp.getContext('2d').putImageData(img, 0, 0);
    ctx.drawImage(tmp, r.x, r.y, r.w, r.h);
    ctx.save(); ctx.beginPath(); ctx.rect(r.x, r.y, r.w, r.h); ctx.clip();
    ctx.strokeStyle = '#1d2430'; ctx.lineWidth = 1.2;
    strokeContour(ctx, contour(m, W, D), frame, P); strokeContour(ctx, contour(s, W, D), frame, P);
    ctx.restore();
    planeAxes(ctx, frame, P, label ? `${label}: depth (nm)` : 'depth (nm)');
    scaleBar(ctx, P);
  });
}

// --- the etch profile -----------------------------------------------------------------------------------
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [190, 215, 40]];
export function timeColour(f) {
  const x = Math.min(Math.max(f, 0), 1) * (VIRIDIS.length - 1), k = Math.min(Math.floor(x), VIRIDIS.length - 2), a = x - k;
  const c = VIRIDIS[k].map((v, q) => Math.round(v + a * (VIRIDIS[k + 1][q] - v)));
  return `rgb(${c.join(',')})`;
}

/** The hole's outline (mask and Si together) at several times overlaid, coloured by time, with the
 * current step in black and, when pinned, run A's outline at the same step dashed; returns whether the
 * legend fitted. `lines`: [{sl, step, label, colour, width, dash}]. */
export function drawProfile(ctx, size, lines, scene) {
  const frame = planeFrame(scene);
  ctx.font = FONT;
  const legendW = 14 + Math.max(...lines.map((l) => ctx.measureText(l.label).width));
  const P = planeLayout(frame, { x: 0, y: 0, w: size.w, h: size.h }, legendW);
  const r = P.rect;
  ctx.fillStyle = '#fff'; ctx.fillRect(r.x, r.y, r.w, r.h);
  ctx.strokeStyle = '#dde'; ctx.setLineDash([3, 3]); ctx.beginPath(); // the initial Si top and mask top
  for (const d of [0, (scene.si_top - scene.resist_top) * scene.voxel_nm]) { ctx.moveTo(r.x, P.Y(d)); ctx.lineTo(r.x + r.w, P.Y(d)); }
  ctx.stroke(); ctx.setLineDash([]);
  ctx.save(); ctx.beginPath(); ctx.rect(r.x, r.y, r.w, r.h); ctx.clip();
  for (const l of lines) {
    const [, , D, W] = l.sl.shape;
    ctx.strokeStyle = l.colour; ctx.lineWidth = l.width || 1.4; ctx.setLineDash(l.dash || []);
    strokeContour(ctx, contour(planeField(l.sl, l.step, 'union'), W, D), frame, P);
  }
  ctx.restore(); ctx.setLineDash([]);
  planeAxes(ctx, frame, P, 'depth (nm)');
  scaleBar(ctx, P);
  const lx = r.x + r.w + 8;
  lines.forEach((l, k) => {
    const y = r.y + 8 + 15 * k;
    ctx.strokeStyle = l.colour; ctx.lineWidth = 2; ctx.setLineDash(l.dash || []);
    ctx.beginPath(); ctx.moveTo(lx, y - 3); ctx.lineTo(lx + 10, y - 3); ctx.stroke(); ctx.setLineDash([]);
    ctx.fillStyle = '#334'; ctx.textAlign = 'left'; ctx.fillText(l.label, lx + 13, y + 1);
  });
  return lx + legendW <= size.w + 0.5 && r.y + 8 + 15 * (lines.length - 1) <= size.h;
}

// --- colour bar of the error-coloured surface ---------------------------------------------------------
/** The colour scale of `GET /jobs/{id}/mesh`: the surrogate's signed distance at the simulator's surface,
 * white at 0, red where the surrogate still has material (it etched less), blue where it has none (it
 * etched more), saturated at one voxel. Drawn in `box` {x, y, w} (height 58 px); `voxelNm` the scale. */
export function drawColourBar(ctx, box, voxelNm) {
  const { x, y, w } = box, h = 10, top = y + 16;
  ctx.font = FONT; ctx.fillStyle = '#ffffffe0'; ctx.fillRect(x - 4, y - 2, w + 8, 62);
  ctx.fillStyle = '#223'; ctx.textAlign = 'left'; ctx.fillText('surrogate error at the Si surface (nm)', x, y + 10);
  const g = ctx.createLinearGradient(x, 0, x + w, 0);
  g.addColorStop(0, 'rgb(255,0,0)'); g.addColorStop(0.5, 'rgb(255,255,255)'); g.addColorStop(1, 'rgb(0,0,255)');
  ctx.fillStyle = g; ctx.fillRect(x, top, w, h); ctx.strokeStyle = '#889'; ctx.strokeRect(x, top, w, h);
  ctx.fillStyle = '#223'; ctx.beginPath();
  const v = +voxelNm.toPrecision(3);
  [[0, `≤ −${v}`, 'left'], [0.5, '0', 'center'], [1, `≥ +${v}`, 'right']].forEach(([f, label, align]) => {
    ctx.moveTo(x + f * w, top + h); ctx.lineTo(x + f * w, top + h + 3);
    ctx.textAlign = align; ctx.fillText(label, x + f * w, top + h + 14);
  });
  ctx.stroke();
  ctx.textAlign = 'left'; ctx.fillText('red: etched less · blue: etched more', x, top + h + 28);
}
