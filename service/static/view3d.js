// The 3-D view: the mask and Si surfaces in nm (the meshes' own unit and frame: x, y from the hole axis, z up
// from the initial Si top), a cutaway through the hole axis, nm rulers along two edges of the box in the
// frame of the 2-D views (x from the hole axis, depth below the initial Si top), and the simulator's surface
// coloured by the surrogate's error with its colour bar. Also the PNG of the view (legend and colour bar
// drawn in).
//
// Choices: the rulers are geometry in the scene (not an overlay), so they stay true under orbit and zoom,
// and they lie in the cutaway plane, where the cut surfaces are, so perspective does not scale them
// differently from the hole; the renderer keeps its drawing buffer, so the PNG is the view on screen,
// rendered again at the export's scale.
import * as THREE from '/static/vendor/three/three.module.min.js';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';
import { FONT, drawColourBar, ticksWithin } from '/static/plot.js';

const LEGEND = {
  plain: 'grey: mask · orange: Si · rulers: nm from the feature axis, depth below the initial Si top',
  error: 'grey: mask (surrogate) · Si: the simulator\'s surface coloured by the surrogate\'s error (colour bar) · rulers: nm from the feature axis, depth below the initial Si top',
};

export function createView(canvas, scene, els) {
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setClearColor(0xeef1f5);
  const world = new THREE.Scene(), vx = scene.voxel_nm;
  const size = new THREE.Vector3(scene.nx * vx, scene.ny * vx, scene.nz * vx);
  const centre = size.clone().multiplyScalar(0.5);
  const camera = new THREE.PerspectiveCamera(35, canvas.width / canvas.height, 1, 50 * size.length());
  camera.up.set(0, 0, 1);
  // the whole box and the rulers' labels in view (35 degrees: about 1.3 box heights at this distance)
  camera.position.set(centre.x + 1.05 * size.z, centre.y - 1.65 * size.z, centre.z + 0.6 * size.z);
  const controls = new OrbitControls(camera, canvas);
  controls.target.set(centre.x, centre.y, 0.45 * size.z); controls.update();
  world.add(new THREE.AmbientLight(0xffffff, 0.55));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6); sun.position.set(1, -2, 3); world.add(sun);
  const back = new THREE.DirectionalLight(0xffffff, 0.5); back.position.set(-2, 1, -1); world.add(back);
  // cutaway: the half nearer the camera (y below the hole axis) is clipped away so the hole shows
  const cut = new THREE.Plane(new THREE.Vector3(0, 1, 0), -size.y / 2);
  renderer.localClippingEnabled = true;
  const clip = () => (els.cutaway.checked ? [cut] : []);
  const mat = (c) => new THREE.MeshStandardMaterial({ color: c, roughness: 0.7, side: THREE.DoubleSide, clippingPlanes: clip() });
  const mask = new THREE.Mesh(new THREE.BufferGeometry(), mat(0x8a8f99));
  const si = new THREE.Mesh(new THREE.BufferGeometry(), mat(0xe0913c));
  const err = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.MeshStandardMaterial({ vertexColors: true, side: THREE.DoubleSide, clippingPlanes: clip() }));
  err.visible = false;
  // the scene is laid out from the box corner; the meshes' frame has its origin on the hole axis at the Si top
  const surfaces = new THREE.Group();
  surfaces.position.set(size.x / 2, size.y / 2, scene.si_top * vx);
  surfaces.add(mask, si, err);
  let rulers = buildRulers(size, scene.si_top * vx);
  world.add(surfaces, rulers);
  const view = { renderer, camera, controls, mask, si, err, size };
  // a feature with another mask moves the Si top (the meshes' frame origin): the surfaces and rulers follow
  let placedAt = scene.si_top;
  view.placeFrame = (siTop) => {
    if (siTop === placedAt) return;
    placedAt = siTop; surfaces.position.z = siTop * vx;
    world.remove(rulers); rulers = buildRulers(size, siTop * vx); world.add(rulers);
  };

  view.render = () => {
    rulers.position.y = els.cutaway.checked ? size.y / 2 - 0.5 : -0.5; // in the cut face, else the front face
    renderer.render(world, camera);
    els.legend.textContent = err.visible ? LEGEND.error : LEGEND.plain;
    els.colourbar.hidden = !err.visible;
  };
  let w = 0, h = 0; // CSS pixels
  view.resize = () => {
    w = Math.max(200, Math.floor(canvas.parentElement.clientWidth));
    // 0.4 of the window's height leaves room below for the cross-section (explorer.js, planeHeight)
    h = Math.round(Math.max(220, Math.min(0.8 * w, 0.4 * window.innerHeight)));
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setSize(w, h, false);
    canvas.style.height = `${h}px`;
    camera.aspect = w / h; camera.updateProjectionMatrix();
    drawOverlayBar(els.colourbar, vx);
  };
  /** Show the simulator's error-coloured surface instead of the surrogate's Si (null: back to normal). */
  view.showError = (geom) => {
    if (geom) err.geometry = geom;
    err.visible = !!geom; if (geom) si.visible = false;
    view.render();
  };
  /** The view as a PNG blob at `scale` pixels per CSS pixel: the view on screen rendered at that scale, the
   * colour bar when shown, and a caption line; then rendered for the screen again. */
  view.png = (caption, scale) => {
    renderer.setPixelRatio(scale); renderer.setSize(w, h, false); view.render();
    const out = document.createElement('canvas'); out.width = canvas.width; out.height = canvas.height + Math.round(34 * scale);
    const ctx = out.getContext('2d');
    ctx.fillStyle = '#fff'; ctx.fillRect(0, 0, out.width, out.height);
    ctx.drawImage(canvas, 0, 0);
    view.resize(); view.render();
    ctx.scale(scale, scale);
    if (err.visible) drawColourBar(ctx, { x: w - 236, y: 8, w: 224 }, vx);
    ctx.font = FONT; ctx.fillStyle = '#334'; ctx.textAlign = 'left';
    ctx.fillText(els.legend.textContent, 6, h + 13);
    ctx.fillText(caption, 6, h + 28);
    return new Promise((resolve) => out.toBlob(resolve, 'image/png'));
  };
  /** Pixels of the frame covered by surfaces (the rulers left out): what "not blank" means. */
  view.surfacePixels = () => {
    rulers.visible = false; renderer.render(world, camera);
    const gl = renderer.getContext(), w = gl.drawingBufferWidth, h = gl.drawingBufferHeight, px = new Uint8Array(4 * w * h);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    rulers.visible = true; view.render();
    let n = 0;
    for (let i = 0; i < px.length; i += 4) if (Math.abs(px[i] - px[0]) + Math.abs(px[i + 1] - px[1]) + Math.abs(px[i + 2] - px[2]) > 12) n++;
    return n;
  };
  els.cutaway.addEventListener('change', () => {
    for (const m of [mask, si, err]) { m.material.clippingPlanes = clip(); m.material.needsUpdate = true; }
    view.render();
  });
  controls.addEventListener('change', view.render);
  view.resize(); view.render();
  return view;
}

function drawOverlayBar(c, voxelNm) {
  const dpr = window.devicePixelRatio || 1, w = 236, h = 66;
  c.width = Math.round(w * dpr); c.height = Math.round(h * dpr); c.style.width = `${w}px`; c.style.height = `${h}px`;
  const ctx = c.getContext('2d'); ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  drawColourBar(ctx, { x: 6, y: 3, w: w - 12 }, voxelNm);
}

// --- rulers -------------------------------------------------------------------------------------------
/** Rulers in the plane y = 0 of the group (moved to the cut face): along x at the bottom of the box (nm from
 * the hole axis) and up the left edge (depth below the initial Si top, `siTop` nm above the box's bottom),
 * ticks at round nm with labels; the last label carries the unit. */
function buildRulers(size, siTop) {
  const group = new THREE.Group(), pts = [], tick = 0.025 * size.z;
  const xt = ticksWithin(-size.x / 2, size.x / 2, 4), zt = ticksWithin(siTop - size.z, siTop, 5);
  pts.push(0, 0, 0, size.x, 0, 0, 0, 0, 0, 0, 0, size.z);
  const label = (text, x, z, align) => {
    const s = textSprite(text, 0.045 * size.z);
    s.center.set(align === 'right' ? 1.05 : 0.5, align === 'right' ? 0.5 : 1.1);
    s.position.set(x, 0, z); group.add(s);
  };
  xt.ticks.forEach((v, k) => {
    const x = v + size.x / 2;
    pts.push(x, 0, 0, x, 0, -tick);
    label(xt.label(v) + (k === xt.ticks.length - 1 ? ' nm' : ''), x, -tick, 'below');
  });
  zt.ticks.forEach((d, k) => {
    const z = siTop - d;
    pts.push(0, 0, z, -tick, 0, z);
    label(zt.label(d) + (k === zt.ticks.length - 1 ? ' nm deep' : ''), -tick, z, 'right');
  });
  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.Float32BufferAttribute(pts, 3));
  group.add(new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: 0x1d2430 })));
  return group;
}

function textSprite(text, height) {
  const px = 48, c = document.createElement('canvas'), ctx = c.getContext('2d');
  ctx.font = `${px}px system-ui`;
  c.width = Math.ceil(ctx.measureText(text).width) + 8; c.height = Math.ceil(px * 1.25);
  ctx.font = `${px}px system-ui`; ctx.fillStyle = '#1d2430'; ctx.textBaseline = 'middle';
  ctx.fillText(text, 4, c.height / 2);
  const tex = new THREE.CanvasTexture(c); tex.colorSpace = THREE.SRGBColorSpace; tex.anisotropy = 4;
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false, transparent: true }));
  sprite.scale.set((height * c.width) / c.height, height, 1);
  sprite.renderOrder = 2;
  return sprite;
}

// --- meshes -------------------------------------------------------------------------------------------
/** A glTF binary (`format=glb` of the API) as a BufferGeometry with normals (and vertex colours if any). */
export function parseGLB(buf) {
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
    return { arr: new T(bin.slice(start, start + a.count * n * T.BYTES_PER_ELEMENT)), n };
  };
  const p = read(prim.attributes.POSITION);
  geom.setAttribute('position', new THREE.BufferAttribute(p.arr, 3));
  if (prim.attributes.COLOR_0 !== undefined) {
    const c = read(prim.attributes.COLOR_0);
    geom.setAttribute('color', new THREE.BufferAttribute(c.arr, c.n, !(c.arr instanceof Float32Array)));
  }
  if (prim.indices !== undefined) geom.setIndex(new THREE.BufferAttribute(read(prim.indices).arr, 1));
  geom.computeVertexNormals();
  return geom;
}
