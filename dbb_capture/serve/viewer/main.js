// The dbb-serve viewer: billboards streamed over dbb-stream/1 (docs/protocol.md) in a three.js
// scene, with their proxy meshes at work in cannon-es, orbit and fly controls, WebXR, a HUD, and
// a test hook (window.dbb).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { VRButton } from 'three/addons/webxr/VRButton.js';
import { Billboard } from './billboard.js';
import { decodeFrame, fingerprint, rawPixels } from './decode.js';
import { Fly } from './fly.js';
import { Physics } from './physics.js';
import { FORMAT_NAMES, FORMAT_RAW, Stream, packRequest, parseFrameHeader } from './stream.js';

const params = new URLSearchParams(location.search);
const options = {
  plain: params.get('plain') === '1',          // tests: no floor, plain background
  hud: params.get('hud') !== '0',
  background: params.get('bg') || '#20242b',
  quality: params.get('quality') || 'auto',
  // Frame encoding: raw RGBA bytes from a server on this machine (no encoding or decoding on
  // either side; 256 KB per 256 px frame is nothing on loopback), else JPEG colour + PNG alpha.
  encoding: params.get('encoding') || 'auto',     // auto, jpeg, png, raw
  wireframe: params.get('wireframe') === '1',
  bake: params.get('bake') !== '0',              // baked floor shadows while nothing moves
  shadows: true,
};
const SAMPLES = 400;                             // latency samples kept per object
const REQUEST_TIMEOUT_MS = 4000;                 // an answer this late is given up on (a new request goes out)

// ---- WebXR emulation for tests and desktop trials (?xr=emulate): the iwer runtime from npm ----
let xrDevice = null;
if (params.get('xr') === 'emulate') {
  const iwer = await import('/vendor/iwer/build/iwer.module.js');
  xrDevice = new iwer.XRDevice(iwer.metaQuest3, { stereoEnabled: true });
  xrDevice.installRuntime({ forceInstall: true });
}

// ---- renderer, scene, camera ----
function softwareGL() {      // SwiftShader, llvmpipe: multisampling costs them dearly
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const ext = gl && gl.getExtension('WEBGL_debug_renderer_info');
    const name = ext ? String(gl.getParameter(ext.UNMASKED_RENDERER_WEBGL)) : '';
    gl?.getExtension('WEBGL_lose_context')?.loseContext();
    return /swiftshader|llvmpipe|software/i.test(name);
  } catch {
    return false;
  }
}
const software = softwareGL();
const antialias = params.has('aa') ? params.get('aa') !== '0' : !software;
const renderer = new THREE.WebGLRenderer({ antialias, powerPreference: 'high-performance' });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.outputColorSpace = THREE.SRGBColorSpace;
renderer.toneMapping = THREE.NoToneMapping;
renderer.shadowMap.enabled = params.get('shadows') !== '0';
renderer.shadowMap.type = THREE.PCFShadowMap;
// Drawn only when something changed (the camera, a texture, a moving body, a setting), and the
// shadow map only when a shadow caster moved: a software-rendered browser keeps up this way.
renderer.shadowMap.autoUpdate = false;
let needsRender = true, needsShadow = true;
function invalidate(shadow = false) { needsRender = true; if (shadow) needsShadow = true; }
renderer.xr.enabled = true;
document.getElementById('app').appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color(options.background);
const camera = new THREE.PerspectiveCamera(50, window.innerWidth / window.innerHeight, 0.01, 200);
camera.position.set(0, 0.25, 0.6);
// In VR the headset's poses are relative to this rig, which puts the viewer in front of the objects.
const rig = new THREE.Group();
rig.add(camera);
scene.add(rig);

const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
controls.dampingFactor = 0.12;
controls.minDistance = 0.02;
const fly = new Fly(camera, renderer.domElement);

const hemi = new THREE.HemisphereLight(0xffffff, 0x55585e, 1.6);
scene.add(hemi);
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.castShadow = true;
sun.shadow.mapSize.setScalar(Number(params.get('shadowmap') || 1024));
sun.shadow.radius = 5;                           // soft edges (PCF)
sun.shadow.bias = -0.0004;
sun.shadow.normalBias = 0.001;
scene.add(sun, sun.target);

const floorMaterial = params.get('floor') === 'standard'
  ? new THREE.MeshStandardMaterial({ color: 0xa7a59e, roughness: 0.95, metalness: 0 })
  : new THREE.MeshLambertMaterial({ color: 0xa7a59e });
const floor = new THREE.Mesh(new THREE.CircleGeometry(1, 96), floorMaterial);
floor.rotation.x = -Math.PI / 2;
floor.receiveShadow = true;
scene.add(floor);

// The floor's shadows, baked. The proxies and the sun stand still, so while no ball or box moves
// the lit, shadowed floor around the objects is drawn once, from above, into a texture, and the
// floor becomes that texture, unlit: beyond the baked square its edge texels (lit floor, no
// shadow) stretch to the horizon. The sun then casts no shadow at all: while it does, every lit
// material samples the shadow map (shaders select, so even a floor that receives none pays for
// it), which with the floor's own lighting is more than a software-rendered browser draws at 60
// frames/s beside the server. Bodies bring the live floor and shadows back.
const BAKE_PX = 1024;
// Linear 8-bit texels (the floor's tones are mid-greys, where that shows no steps) with mipmaps:
// a software renderer samples an sRGB texture, or a large one without mipmaps, slowly.
const bakeTarget = new THREE.WebGLRenderTarget(BAKE_PX, BAKE_PX, {
  generateMipmaps: true, minFilter: THREE.LinearMipmapLinearFilter });
const bakeCamera = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.001, 10);
bakeCamera.up.set(0, 0, -1);                     // image up along -z: the patch's own texture layout
const bakedFloorMaterial = new THREE.MeshBasicMaterial({ map: bakeTarget.texture });
let floorBaked = false, bakes = 0;

const physics = new Physics(scene);
const gltf = new GLTFLoader();
// Drawing order (all in three's opaque list, by renderOrder): the floor (0); the billboards,
// blended back to front (1.x); the wireframes (1.9); the proxies, depth only (2); the balls and
// boxes (3). The proxy is invisible (no colour) yet writes depth and is drawn into the shadow
// map: each billboard stands on the floor with the shadow of its real shape, and a ball behind
// the object's front surface is hidden by the object while one in front of it is drawn over it.
// Its depth pass matters only while balls or boxes exist, so the proxies sit on a layer of their
// own that the camera sees only then (a software-rendered browser spends more on that pass than
// on the billboards); the shadow camera always sees it. Layers 1 and 2 are three.js's XR eyes.
const proxyMaterial = new THREE.MeshBasicMaterial({ colorWrite: false, depthWrite: true });
const PROXY_LAYER = 3;
sun.shadow.camera.layers.enable(PROXY_LAYER);
const wireMaterial = new THREE.MeshBasicMaterial({
  color: 0x39e6b0, wireframe: true, opacity: 0.22, transparent: false, depthWrite: false,
  blending: THREE.CustomBlending, blendSrc: THREE.SrcAlphaFactor, blendDst: THREE.OneMinusSrcAlphaFactor });

// ---- state ----
const state = {
  status: 'connecting', detail: '', connects: 0, hello: null, objects: [], errors: [],
  drawn: { count: 0, since: performance.now() }, fps: 0, quality: options.quality,
  xr: { supported: false, presenting: false, views: 0, shared: true },
};
let objects = [];          // per object: see makeObject
let floorY = 0;
let sceneCentre = new THREE.Vector3();
let sceneRadius = 0.2;

function makeObject(info) {
  const bb = new Billboard(info);
  scene.add(bb.mesh);
  return {
    info, bb, visible: true, outstanding: null, lastSent: null, wantNext: false, nextFrame: null,
    decoding: false, frames: 0, drawnFrames: 0, recvTimes: [], shownTimes: [], rtt: [], photon: [],
    last: null, shownSeq: 0, drawnSeq: 0, photonPending: null, photonWait: null, error: null,
    proxy: null, top: null,
  };
}

function clearObjects() {
  invalidate(true);
  for (const o of objects) {
    scene.remove(o.bb.mesh);
    o.bb.dispose();
    if (o.proxy) scene.remove(o.proxy.shadow, o.proxy.wire);
    physics.removeCollider(o.info.index);
  }
  objects = [];
}

// ---- the stream ----
let stream = null;                                 // opened at the end, once the page is set up

function onHello(hello) {
  const same = state.hello && JSON.stringify(state.hello.objects) === JSON.stringify(hello.objects);
  state.hello = hello;
  if (!same) {
    clearObjects();
    objects = hello.objects.map(makeObject);
    layoutScene();
    for (const o of objects) loadProxy(o);
    if (!userMovedCamera) frameAll();
  }
  for (const o of objects) { o.outstanding = null; o.lastSent = null; }
  sendQuality();
}

const LOOPBACK = /^(localhost|127(\.\d+){3}|\[::1\])$/.test(location.hostname);

function sendQuality() {
  const q = state.quality, e = options.encoding;
  if (!stream) return;
  const msg = { type: 'quality', lossless: q === 'lossless' || e === 'png',
                raw: e === 'raw' || (e === 'auto' && LOOPBACK), max_size: /^\d+$/.test(q) ? Number(q) : null };
  stream.control(msg);
  for (const o of objects) o.lastSent = null;     // ask again at the new quality
}

function layoutScene() {
  const box = new THREE.Box3();
  for (const o of objects) {
    const c = new THREE.Vector3(...o.info.position);
    box.expandByPoint(c.clone().addScalar(o.info.canvas_size_m / 2));
    box.expandByPoint(c.clone().addScalar(-o.info.canvas_size_m / 2));
  }
  box.getCenter(sceneCentre);
  sceneRadius = Math.max(0.05, box.getSize(new THREE.Vector3()).length() / 2);
  setFloor(Math.min(...objects.map(standsAt)));
  const r = Math.max(2.0, 16 * sceneRadius);        // the floor fades into the background
  floor.scale.setScalar(r);
  scene.fog = new THREE.Fog(scene.background, 0.6 * r, r);
  sun.position.copy(sceneCentre).add(new THREE.Vector3(0.5, 1.6, 0.7).multiplyScalar(3 * sceneRadius));
  sun.target.position.copy(sceneCentre);
  const sc = sun.shadow.camera;
  sc.left = sc.bottom = -2.5 * sceneRadius;
  sc.right = sc.top = 2.5 * sceneRadius;
  sc.near = 0.01;
  sc.far = 12 * sceneRadius;
  sc.updateProjectionMatrix();
}

/** Draw the lit floor with its shadows around the objects into the baked texture (the shadow map
 *  first), and place the texture on the floor's own coordinates. */
function bakeFloor() {
  bakes += 1;
  const h = 3 * sceneRadius;                     // shadows fall within ~2.1 radii of the centre
  // The floor's UVs span its disc (radius r, centred at x = z = 0): u = (x / r + 1) / 2 and, the
  // disc turned to face up, v = (1 - z / r) / 2. The bake's image spans the square of side 2h
  // around the scene's centre, its v along -z.
  const r = floor.scale.x, t = bakeTarget.texture;
  t.repeat.set(r / h, r / h);
  t.offset.set((h - r - sceneCentre.x) / (2 * h), (h - r + sceneCentre.z) / (2 * h));
  bakeCamera.left = bakeCamera.bottom = -h;
  bakeCamera.right = bakeCamera.top = h;
  bakeCamera.near = 0.5 * h;
  bakeCamera.far = 2 * h;
  bakeCamera.position.set(sceneCentre.x, floorY + h, sceneCentre.z);
  bakeCamera.lookAt(sceneCentre.x, floorY, sceneCentre.z);
  bakeCamera.updateProjectionMatrix();
  const shown = [];
  // Only the floor is drawn; the shadow casters stay for the shadow map (the bake camera sees
  // layer 0 only, not theirs).
  scene.traverse((n) => {
    if (n.visible && n !== floor && !n.castShadow && (n.isMesh || n.isLine || n.isPoints)) { shown.push(n); n.visible = false; }
  });
  const fog = scene.fog, xr = renderer.xr.enabled;
  scene.fog = null;
  renderer.xr.enabled = false;
  floor.material = floorMaterial;
  floor.receiveShadow = true;
  sun.castShadow = true;
  renderer.shadowMap.needsUpdate = true;
  renderer.setRenderTarget(bakeTarget);
  renderer.render(scene, bakeCamera);
  renderer.setRenderTarget(null);
  renderer.xr.enabled = xr;
  scene.fog = fog;
  for (const n of shown) n.visible = true;
}

/** Baked floor shadows while nothing moves; the live shadow map while bodies exist. */
function updateShadows() {
  const live = physics.bodies.length > 0;
  if (options.bake && options.shadows && renderer.shadowMap.enabled && !live) {
    bakeFloor();
    floorBaked = true;
  } else {
    renderer.shadowMap.needsUpdate = true;
    floorBaked = false;
  }
  sun.castShadow = options.shadows && !floorBaked;
  floor.receiveShadow = !floorBaked;
  floor.material = floorBaked ? bakedFloorMaterial : floorMaterial;
}

// Where an object stands: the table it was filmed on (its bundle's support plane), else its
// proxy's lowest point, else the bottom of its sphere.
function standsAt(o) {
  if (o.info.support_y != null) return o.info.support_y;
  return o.proxy ? o.proxy.box.min.y : o.info.position[1] - o.info.radius_m;
}

function setFloor(y) {
  invalidate(true);
  floorY = y;
  floor.position.y = y;
  physics.setFloor(y);
}

function rowMajor(m) {          // THREE.Matrix4 (column-major storage) -> 16 numbers row by row
  const e = m.elements;
  return [e[0], e[4], e[8], e[12], e[1], e[5], e[9], e[13], e[2], e[6], e[10], e[14], e[3], e[7], e[11], e[15]];
}

async function loadProxy(o) {
  try {
    const g = await gltf.loadAsync(o.info.proxy_url);
    if (!objects.includes(o)) return;
    g.scene.updateMatrixWorld(true);
    let node = null;
    g.scene.traverse((n) => { if (n.isMesh && !node && /-colonly$/.test(n.name) && !/convcolonly$/.test(n.name)) node = n; });
    if (!node) throw new Error('proxy.glb has no -colonly node');
    const sceneFromBundle = new THREE.Matrix4().set(...o.info.scene_from_bundle.flat());
    const geom = node.geometry.clone();
    geom.applyMatrix4(new THREE.Matrix4().multiplyMatrices(sceneFromBundle, node.matrixWorld));
    geom.computeBoundingBox();
    geom.computeVertexNormals();
    const shadow = new THREE.Mesh(geom, proxyMaterial);
    shadow.castShadow = true;
    shadow.renderOrder = 2;
    shadow.layers.set(PROXY_LAYER);
    const wire = new THREE.Mesh(geom, wireMaterial);
    wire.renderOrder = 1.9;
    wire.visible = options.wireframe && o.visible;
    shadow.visible = o.visible;
    scene.add(shadow, wire);
    physics.addCollider(o.info.index, geom);
    // The top: the highest vertex (where balls are dropped).
    const p = geom.attributes.position;
    let top = 0;
    for (let i = 1; i < p.count; i++) if (p.getY(i) > p.getY(top)) top = i;
    o.top = new THREE.Vector3(p.getX(top), p.getY(top), p.getZ(top));
    o.proxy = { shadow, wire, geom, box: geom.boundingBox.clone() };
    invalidate(true);
    setFloor(Math.min(...objects.map(standsAt)));
  } catch (e) {
    state.errors.push({ type: 'proxy', object: o.info.index, message: String(e) });
    console.warn(`object ${o.info.index}: its proxy mesh could not be loaded: ${e}`);
  }
}

// ---- requests ----
const _pos = new THREE.Vector3(), _quat = new THREE.Quaternion(), _one = new THREE.Vector3(1, 1, 1);
const _mat = new THREE.Matrix4(), _size = new THREE.Vector2();

/** The viewpoint requests are made for, and the billboards turn toward. In VR, ONE SHARED
 *  FRAME per object, rendered from the head (the midpoint of the eyes), not one per eye: the
 *  eyes' views of a 0.1–1 m object a metre away differ by a few degrees, which the flat canvas
 *  could not show correctly anyway (its geometry, a plane through the object's centre, already
 *  gets the stereo depth right); two frames would double the server's render work for every
 *  object and eye, and would arrive at different moments, and eyes showing different instants
 *  of a moving object are worse than no parallax within the image. Both eyes see the same
 *  square, turned toward the head every display frame. */
function currentView() {
  if (renderer.xr.isPresenting) {
    const cams = renderer.xr.getCamera().cameras;
    if (cams.length) {
      rig.updateMatrixWorld();
      _pos.set(0, 0, 0);
      for (const c of cams) _pos.add(c.position);
      _pos.multiplyScalar(1 / cams.length).applyMatrix4(rig.matrixWorld);
      const c0 = cams[0];
      const P = c0.projectionMatrix.elements;
      const w = c0.viewport.z || 1, h = c0.viewport.w || 1;
      return { position: _pos.clone(), quaternion: rig.quaternion.clone().multiply(c0.quaternion).normalize(), fx: P[0] * w / 2,
               fy: P[5] * h / 2, cx: (1 - P[8]) * w / 2, cy: (1 + P[9]) * h / 2, width: w, height: h,
               fovYDeg: 2 * THREE.MathUtils.radToDeg(Math.atan(1 / P[5])) };
    }
  }
  camera.updateMatrixWorld();
  camera.matrixWorld.decompose(_pos, _quat, new THREE.Vector3());
  renderer.getDrawingBufferSize(_size);
  const P = camera.projectionMatrix.elements;
  return { position: _pos.clone(), quaternion: _quat.clone().normalize(), fx: P[0] * _size.x / 2,
           fy: P[5] * _size.y / 2, cx: _size.x / 2, cy: _size.y / 2, width: _size.x, height: _size.y,
           fovYDeg: camera.fov };
}

/** The canvas's side (scene metres) seen from distance D, as the server renders it: the square
 *  through the centre that the object's bounding sphere fills as it does from far away. */
function canvasSide(info, D) {
  const r = info.radius_m;
  if (!(D > r)) return info.canvas_size_m;
  return D * Math.tan(Math.asin(r / D)) * info.canvas_size_m / r;
}

function sizeOnScreen(o, view) {
  const D = Math.max(view.position.distanceTo(o.bb.centre), 1e-6);
  return Math.max(16, Math.min(4096, Math.ceil(view.fy * canvasSide(o.info, D) / D)));
}

function maybeRequest(o, view, now) {
  if (!o.visible || !stream?.isOpen) return;
  if (o.outstanding && now - o.outstanding.sentMs < REQUEST_TIMEOUT_MS) return;   // ≤ 1 in flight
  const q = state.quality;
  const sizePx = /^\d+$/.test(q) ? Number(q) : sizeOnScreen(o, view);
  const moved = !o.lastSent || o.lastSent.position.distanceToSquared(view.position) > 1e-10
                || o.lastSent.sizePx !== sizePx;
  if (!moved && !o.wantNext) return;
  // A dynamic object's picture changes at its model's frame rate: without a camera move, ask
  // for the next frame when the next step is due, not sooner (the same step again is waste).
  if (!moved && o.info.kind === 'dynamic' && o.info.fps && now - o.lastSent.sentMs < 900 / o.info.fps) return;
  _mat.compose(view.position, view.quaternion, _one);
  const seq = stream.nextSeq();
  const clientMs = performance.now();
  const ok = stream.send(packRequest({
    seq, clientMs, object: o.info.index, eye: 0, c2w: rowMajor(_mat), fovYDeg: view.fovYDeg,
    fx: view.fx, fy: view.fy, cx: view.cx, cy: view.cy, viewportW: view.width, viewportH: view.height, sizePx,
  }));
  if (!ok) return;
  o.outstanding = { seq, sentMs: clientMs };
  o.lastSent = { position: view.position.clone(), sizePx, sentMs: clientMs };
  o.wantNext = false;
}

function onFrame(buffer, receivedMs) {
  let head;
  try { head = parseFrameHeader(buffer); } catch (e) { state.errors.push({ type: 'frame', message: String(e) }); return; }
  const o = objects[head.object];
  if (!o) return;
  if (o.outstanding && o.outstanding.seq === head.seq) o.outstanding = null;
  o.error = null;
  o.frames += 1;
  o.recvTimes.push(receivedMs);
  push(o.rtt, receivedMs - head.clientMs);
  // Dynamic objects move by themselves: a frame asks for the next one. Static ones only when
  // the camera moved (checked every display frame).
  if (o.info.kind === 'dynamic') o.wantNext = true;
  o.nextFrame = { head, buffer, receivedMs };
  if (!o.decoding) decodeLoop(o);
}

// Decoding happens in a worker (decoder.js), off the page's thread, which a software-rendered
// WebGL canvas keeps busy; on the page itself where module workers are missing.
let decoder = null;
const decodeWaiting = new Map();
let decodeIds = 0;
try {
  decoder = new Worker(new URL('./decoder.js', import.meta.url), { type: 'module' });
  decoder.onmessage = (e) => {
    const w = decodeWaiting.get(e.data.id);
    decodeWaiting.delete(e.data.id);
    if (w) (e.data.error ? w.reject(new Error(e.data.error)) : w.resolve(e.data));
  };
  decoder.onerror = () => { decoder = null; for (const w of decodeWaiting.values()) w.reject(new Error('decoder failed')); };
} catch {
  decoder = null;
}

function decode(buffer, head) {
  if (head.format === FORMAT_RAW) {            // nothing to decode: no trip through the worker
    return new Promise((resolve) => {
      const rgba = rawPixels(buffer, head);
      resolve({ rgba, hash: fingerprint(rgba) });
    });
  }
  if (!decoder) {
    return decodeFrame(buffer, head).then((rgba) => ({ rgba, hash: fingerprint(rgba) }));
  }
  return new Promise((resolve, reject) => {
    const id = ++decodeIds;
    decodeWaiting.set(id, { resolve, reject });
    decoder.postMessage({ id, buffer, head }, [buffer]);
  });
}

async function decodeLoop(o) {
  o.decoding = true;
  while (o.nextFrame) {
    const f = o.nextFrame;
    o.nextFrame = null;
    if (f.head.seq < o.shownSeq && f.head.seq + 1e6 > o.shownSeq) continue;     // older than what is shown
    const bytes = f.buffer.byteLength;
    try {
      const { rgba, hash } = await decode(f.buffer, f.head);
      if (!objects.includes(o)) break;
      o.bb.setFrame(f.head, rgba);
      invalidate();
      o.shownSeq = f.head.seq;
      o.last = { seq: f.head.seq, step: f.head.step, width: f.head.width, height: f.head.height,
                 format: f.head.format, render_ms: f.head.renderMs, canvas_side_m: f.head.sideM,
                 canvas_centre: f.head.centre, c2w: f.head.c2w, client_ms: f.head.clientMs,
                 bytes, hash, decoded_ms: performance.now() - f.receivedMs };
      o.photonPending = f.head.clientMs;          // on screen with the next render
    } catch (e) {
      state.errors.push({ type: 'decode', object: o.info.index, message: String(e) });
    }
  }
  o.decoding = false;
}

function push(arr, v) { arr.push(v); if (arr.length > SAMPLES) arr.shift(); }

// ---- the loop ----
let lastT = performance.now();
const lastRendered = { matrix: new THREE.Matrix4(), projection: new THREE.Matrix4() };
let userMovedCamera = false;
let framing = null;                                 // {from, to, t0} of a click-to-frame move
controls.addEventListener('start', () => { userMovedCamera = true; framing = null; });

function animate(time, xrFrame) {
  const now = performance.now();
  const dt = Math.min(0.1, (now - lastT) / 1000);
  lastT = now;
  // Frames drawn in the previous render are on screen now: pose-to-photon samples.
  for (const o of objects) {
    if (o.photonWait != null) {
      push(o.photon, now - o.photonWait);
      o.shownTimes.push(now);
      o.drawnFrames += 1;
      o.drawnSeq = o.shownSeq;
      o.photonWait = null;
    }
  }
  if (!renderer.xr.isPresenting) {
    if (framing) stepFraming(now);
    if (fly.enabled) fly.update(dt); else controls.update(dt);
  }
  physics.step(dt);
  if (camera.layers.isEnabled(PROXY_LAYER) !== physics.bodies.length > 0) {
    camera.layers.toggle(PROXY_LAYER);
    invalidate(true);                               // baked shadows or live ones from here on
  }
  if (physics.moving()) invalidate(true);
  const view = currentView();
  for (const o of objects) {
    o.bb.face(view.position);                       // every display frame, locally
    maybeRequest(o, view, now);
  }
  const far = objects.map((o) => [o.bb.centre.distanceToSquared(view.position), o]).sort((a, b) => b[0] - a[0]);
  far.forEach(([, o], k) => { o.bb.mesh.renderOrder = 1 + k / (far.length + 1) * 0.8; });
  camera.updateMatrixWorld();
  if (!camera.matrixWorld.equals(lastRendered.matrix) || !camera.projectionMatrix.equals(lastRendered.projection)) {
    needsRender = true;
  }
  if (needsRender || renderer.xr.isPresenting) {
    if (needsShadow) { updateShadows(); needsShadow = false; }
    needsRender = false;
    lastRendered.matrix.copy(camera.matrixWorld);
    lastRendered.projection.copy(camera.projectionMatrix);
    const r0 = performance.now();
    renderer.render(scene, camera);
    state.renderMs = 0.9 * (state.renderMs || 0) + 0.1 * (performance.now() - r0);
    state.drawn.count += 1;
  }
  for (const o of objects) {
    if (o.photonPending != null && o.bb.mesh.visible) { o.photonWait = o.photonPending; o.photonPending = null; }
  }
  state.xr.presenting = renderer.xr.isPresenting;
  state.xr.views = renderer.xr.isPresenting ? renderer.xr.getCamera().cameras.length : 0;
  if (xrFrame) state.xr.frames = (state.xr.frames || 0) + 1;
}
renderer.setAnimationLoop(animate);

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  invalidate();
});

// ---- camera helpers ----
function setCamera(position, target) {
  framing = null;
  fly.stop();
  document.getElementById('fly').classList.remove('on');
  camera.position.set(...position);
  controls.target.set(...target);
  camera.lookAt(controls.target);
  controls.update();
  userMovedCamera = true;
}

function frameAll() {
  const d = 1.4 * sceneRadius / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  const dir = new THREE.Vector3(0.25, 0.45, 1).normalize();
  camera.position.copy(sceneCentre).addScaledVector(dir, Math.max(d, 0.15));
  controls.target.copy(sceneCentre);
  camera.lookAt(sceneCentre);
  controls.update();
}

function frameObject(o) {
  const centre = o.bb.centre.clone();
  const dist = Math.max(1.5 * o.info.radius_m, 0.75 * o.bb.side / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
  const dir = camera.position.clone().sub(controls.target).normalize();
  framing = { t0: performance.now(), fromPos: camera.position.clone(), fromTarget: controls.target.clone(),
              toPos: centre.clone().addScaledVector(dir, dist), toTarget: centre };
  if (fly.enabled) toggleFly();
}

function stepFraming(now) {
  const t = Math.min(1, (now - framing.t0) / 450);
  const s = t * t * (3 - 2 * t);
  camera.position.lerpVectors(framing.fromPos, framing.toPos, s);
  controls.target.lerpVectors(framing.fromTarget, framing.toTarget, s);
  if (t >= 1) framing = null;
}

// Click (not drag) on a billboard: frame it.
const raycaster = new THREE.Raycaster();
let downAt = null;
renderer.domElement.addEventListener('pointerdown', (e) => { downAt = [e.clientX, e.clientY]; });
renderer.domElement.addEventListener('pointerup', (e) => {
  if (!downAt || Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]) > 4 || fly.enabled) return;
  const ndc = new THREE.Vector2((e.clientX / window.innerWidth) * 2 - 1, -(e.clientY / window.innerHeight) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  const hits = raycaster.intersectObjects(objects.filter((o) => o.visible && o.bb.mesh.visible).map((o) => o.bb.mesh));
  const hit = hits.length ? objects.find((o) => o.bb.mesh === hits[0].object) : null;
  if (hit) frameObject(hit);
});

// ---- balls and boxes ----
function dropTargets(object) {
  const withProxy = objects.filter((o) => o.visible && o.top);
  if (object != null) return withProxy.filter((o) => o.info.index === object);
  return withProxy;
}

function ballRadius(o) { return THREE.MathUtils.clamp(0.1 * o.info.radius_m, 0.004, 0.03); }

function dropBodies(n, kind = 'ball', { object = null, jitter = 0.25, radius = null } = {}) {
  const targets = dropTargets(object);
  const dropped = [];
  for (let i = 0; i < n && targets.length; i++) {
    const o = targets[i % targets.length];
    const r = radius ?? ballRadius(o);
    const a = Math.random() * Math.PI * 2, d = Math.random() * jitter * o.info.radius_m;
    const at = new THREE.Vector3(o.top.x + d * Math.cos(a), o.top.y + 3 * r + Math.floor(i / targets.length) * 3 * r,
                                 o.top.z + d * Math.sin(a));
    physics.drop(kind, at, r);
    dropped.push(at.toArray());
  }
  return dropped;
}

function dropAt(points, kind = 'ball', radius = 0.01) {
  for (const p of points) physics.drop(kind, new THREE.Vector3(...p), radius);
}

// ---- UI ----
const $ = (id) => document.getElementById(id);
$('quality').value = state.quality;
$('quality').addEventListener('change', (e) => setQuality(e.target.value));
$('drop-balls').addEventListener('click', () => dropBodies(6, 'ball'));
$('drop-boxes').addEventListener('click', () => dropBodies(3, 'box'));
$('clear').addEventListener('click', () => { physics.clear(); invalidate(true); });
$('wireframe').checked = options.wireframe;
$('wireframe').addEventListener('change', (e) => setWireframe(e.target.checked));
$('fly').addEventListener('click', toggleFly);
$('reset').addEventListener('click', resetDynamic);
if (!options.hud) document.body.classList.add('bare');

function toggleFly() {
  if (fly.enabled) {
    fly.stop();
    controls.target.copy(camera.position).add(new THREE.Vector3(0, 0, -0.3).applyQuaternion(camera.quaternion));
    controls.enabled = true;
  } else {
    framing = null;
    fly.start();
    controls.enabled = false;
    userMovedCamera = true;
  }
  $('fly').classList.toggle('on', fly.enabled);
}

function setQuality(q) {
  state.quality = String(q);
  $('quality').value = state.quality;
  sendQuality();
}

function setWireframe(on) {
  invalidate();
  options.wireframe = on;
  for (const o of objects) if (o.proxy) o.proxy.wire.visible = on && o.visible;
}

function resetDynamic() {
  for (const o of objects) {
    if (o.info.kind === 'dynamic') {
      stream.control({ type: 'reset', object: o.info.index });
      o.wantNext = true;
    }
  }
}

function setOptions(opt) {
  invalidate(true);
  if ('floor' in opt) floor.visible = opt.floor;
  if ('background' in opt) { scene.background = new THREE.Color(opt.background); if (scene.fog) scene.fog.color = scene.background; }
  if ('shadows' in opt) options.shadows = opt.shadows;
  if ('hud' in opt) document.body.classList.toggle('bare', !opt.hud);
  if ('wireframe' in opt) setWireframe(opt.wireframe);
  if ('visible' in opt) {
    for (const o of objects) {
      o.visible = opt.visible.includes(o.info.index);
      o.bb.mesh.visible = o.visible && o.last !== null;
      if (o.proxy) { o.proxy.shadow.visible = o.visible; o.proxy.wire.visible = o.visible && options.wireframe; }
    }
  }
  if ('bake' in opt) options.bake = opt.bake;
  if ('encoding' in opt) { options.encoding = opt.encoding; sendQuality(); }
  if ('autoRotate' in opt) { controls.autoRotate = opt.autoRotate !== 0; controls.autoRotateSpeed = opt.autoRotate || 0; }
}
if (options.plain) setOptions({ floor: false });

function showStatus() {
  const el = $('status');
  let text = state.status;
  if (state.status === 'disconnected' && stream?.retryAt) {
    text = `disconnected — reconnecting in ${Math.max(0, (stream.retryAt - performance.now()) / 1000).toFixed(1)} s`;
  }
  el.textContent = text;
  el.className = `status ${state.status}`;
}

function pct(arr, p) {
  if (!arr.length) return NaN;
  const s = [...arr].sort((a, b) => a - b);
  return s[Math.min(s.length - 1, Math.floor(p * s.length))];
}

function perSecond(times, now) {
  while (times.length && now - times[0] > 2000) times.shift();
  return times.length / 2;
}

let hudFrames = 0, hudT = performance.now();
function updateHud() {
  const now = performance.now();
  state.fps = (state.drawn.count - hudFrames) / ((now - hudT) / 1000);
  hudFrames = state.drawn.count;
  hudT = now;
  showStatus();
  $('fps').textContent = `${state.fps.toFixed(1)} frames/s drawn${renderer.xr.isPresenting ? ' · VR (one shared frame from the head)' : ''}`;
  const fmt = (v) => (Number.isFinite(v) ? v.toFixed(0) : '–');
  $('objects').innerHTML = objects.map((o) => {
    const l = o.last;
    const res = l ? `${l.width}² ${FORMAT_NAMES[l.format] ?? l.format}` : '–';
    const err = o.error ? ` · <span style="color:#f88">${o.error}</span>` : '';
    return `<div class="obj"><b>${o.info.index} ${o.info.id}</b> ${o.info.kind}${o.visible ? '' : ' (hidden)'} · ${res}` +
      `<br><span class="stats">${perSecond(o.shownTimes, now).toFixed(1)} drawn / ${perSecond(o.recvTimes, now).toFixed(1)} received frames/s` +
      ` · rtt p50 ${fmt(pct(o.rtt, 0.5))} p95 ${fmt(pct(o.rtt, 0.95))} ms` +
      ` · render ${l ? l.render_ms.toFixed(1) : '–'} ms${err}</span></div>`;
  }).join('');
}
setInterval(updateHud, 500);

// ---- WebXR ----
async function setUpXR() {
  if (!('xr' in navigator)) return;
  let ok = false;
  try { ok = await navigator.xr.isSessionSupported('immersive-vr'); } catch { ok = false; }
  state.xr.supported = ok;
  if (!ok) return;
  const button = VRButton.createButton(renderer);
  button.id = 'vr-button';
  document.body.appendChild(button);
  renderer.xr.addEventListener('sessionstart', () => {
    // Stand about 0.6 m from the objects, their centre a little below the eyes (local-floor
    // puts the head some 1.6 m above the rig).
    rig.position.set(sceneCentre.x, sceneCentre.y - 1.25, sceneCentre.z + 0.6 + 1.5 * sceneRadius);
    rig.updateMatrixWorld(true);
    controls.enabled = false;
  });
  renderer.xr.addEventListener('sessionend', () => { rig.position.set(0, 0, 0); rig.updateMatrixWorld(true); controls.enabled = !fly.enabled; invalidate(); });
}
setUpXR();

// ---- connect ----
const token = params.get('token');
const wsUrl = `${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/ws${token ? `?token=${encodeURIComponent(token)}` : ''}`;
stream = new Stream(wsUrl, {
  onStatus(s, detail) { state.status = s; state.detail = detail; for (const o of objects) o.outstanding = null; showStatus(); },
  onHello(hello) { state.connects = stream.connects; onHello(hello); },
  onFrame(buffer, receivedMs) { onFrame(buffer, receivedMs); },
  onMessage(msg) {
    if (msg.type === 'error') {
      state.errors.push(msg);
      if (state.errors.length > 50) state.errors.shift();
      const o = objects[msg.object];
      if (o && o.outstanding && (msg.seq == null || msg.seq === o.outstanding.seq)) {
        o.outstanding = null;
        o.error = msg.code;
      }
    }
  },
});

// ---- the test hook ----
window.dbb = {
  setCamera, frameAll,
  frameObject(i) { frameObject(objects[i]); },
  dropBalls(n = 6, opt = {}) { return dropBodies(n, 'ball', opt); },
  dropBoxes(n = 3, opt = {}) { return dropBodies(n, 'box', opt); },
  dropAt, clearBodies() { physics.clear(); invalidate(true); }, setOptions, setQuality, setWireframe, resetDynamic,
  resetStats() {
    for (const o of objects) { o.rtt.length = 0; o.photon.length = 0; o.frames = 0; o.drawnFrames = 0; }
    state.drawn = { count: 0, since: performance.now() };
  },
  enterVR() { document.getElementById('vr-button')?.click(); },
  async exitVR() { await renderer.xr.getSession()?.end(); },
  xrDevice,
  camera() {
    const v = currentView();
    return { position: v.position.toArray(), quaternion: v.quaternion.toArray(), fx: v.fx, fy: v.fy, cx: v.cx,
             cy: v.cy, width: v.width, height: v.height, fov_y_deg: v.fovYDeg, target: controls.target.toArray() };
  },
  object(i) {                      // one object's latest frame and counters, cheaply
    const o = objects[i];
    return o ? { last: o.last, frames: o.frames, drawn_seq: o.drawnSeq, visible: o.visible } : null;
  },
  get state() {
    const now = performance.now();
    return {
      status: state.status, detail: state.detail, connects: state.connects, quality: state.quality, encoding: options.encoding,
      errors: state.errors.slice(), fps: state.fps, render_ms: state.renderMs, software, antialias, floor_y: floorY, floor_baked: floorBaked, bakes,
      sun_dir: sun.position.clone().sub(sun.target.position).normalize().toArray(),
      drawn: { count: state.drawn.count, seconds: (now - state.drawn.since) / 1000 },
      xr: { ...state.xr },
      objects: objects.map((o) => ({
        index: o.info.index, id: o.info.id, kind: o.info.kind, visible: o.visible, frames: o.frames,
        drawn_frames: o.drawnFrames, drawn_seq: o.drawnSeq, last: o.last, rtt: o.rtt.slice(), photon: o.photon.slice(), error: o.error,
        proxy_loaded: !!o.proxy, top: o.top ? o.top.toArray() : null, outstanding: !!o.outstanding,
        plane: { centre: o.bb.centre.toArray(), side: o.bb.side, matrix: o.bb.mesh.matrix.toArray() },
      })),
      bodies: physics.state(),
    };
  },
};
