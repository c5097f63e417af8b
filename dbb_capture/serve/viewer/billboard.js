// A billboard: a camera-facing square of the frame's canvas_side_m at canvas_centre, textured
// with the latest frame. Frames carry straight alpha; the texture stores it premultiplied so that
// bilinear filtering never mixes the (filler) colour of transparent pixels into the edge (no dark
// or bright fringes), and the material blends premultiplied: out = c·a + dst·(1 − a), exactly
// the straight-alpha "over" of the protocol, in the images' own (sRGB) values.

import * as THREE from 'three';

const VERTEX = /* glsl */`
varying vec2 vUv;
void main() {
  vUv = uv;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

const FRAGMENT = /* glsl */`
uniform sampler2D map;
uniform float opacity;
varying vec2 vUv;
void main() {
  // Image rows run top to bottom; the plane's v runs bottom to top.
  vec4 t = texture2D(map, vec2(vUv.x, 1.0 - vUv.y));
  if (t.a < 0.002) discard;
  gl_FragColor = t * opacity;          // premultiplied, raw (already display-encoded) values
}`;

const _n = new THREE.Vector3(), _x = new THREE.Vector3(), _y = new THREE.Vector3();
const _m = new THREE.Matrix4();

export class Billboard {
  constructor(info) {
    this.info = info;
    this.centre = new THREE.Vector3(...info.position);
    this.side = info.canvas_size_m;
    this.up = new THREE.Vector3(0, 1, 0);           // the last frame's camera +y
    this.texture = null;
    this.material = new THREE.ShaderMaterial({
      uniforms: { map: { value: null }, opacity: { value: 1 } },
      vertexShader: VERTEX, fragmentShader: FRAGMENT,
      // Not `transparent`: drawn in the opaque list before the proxies' depth and the bodies
      // (see main.js); the blending below still applies.
      transparent: false, depthWrite: false, side: THREE.DoubleSide,
      blending: THREE.CustomBlending, blendEquation: THREE.AddEquation,
      blendSrc: THREE.OneFactor, blendDst: THREE.OneMinusSrcAlphaFactor,
      blendSrcAlpha: THREE.OneFactor, blendDstAlpha: THREE.OneMinusSrcAlphaFactor,
    });
    this.mesh = new THREE.Mesh(new THREE.PlaneGeometry(1, 1), this.material);
    this.mesh.matrixAutoUpdate = false;
    this.mesh.visible = false;                        // until the first frame
    this.mesh.userData.billboard = this;
    this.mesh.frustumCulled = false;
  }

  /** Show a decoded frame (premultiplied RGBA) with its header's canvas. */
  setFrame(head, rgba) {
    const w = head.width, h = head.height;
    if (!this.texture || this.texture.image.width !== w || this.texture.image.height !== h) {
      this.texture?.dispose();
      this.texture = new THREE.DataTexture(rgba, w, h, THREE.RGBAFormat, THREE.UnsignedByteType);
      this.texture.colorSpace = THREE.NoColorSpace;
      this.texture.minFilter = THREE.LinearFilter;
      this.texture.magFilter = THREE.LinearFilter;
      this.texture.generateMipmaps = false;
      this.texture.flipY = false;
      this.texture.premultiplyAlpha = false;        // premultiplied above, by us
      this.texture.unpackAlignment = 4;
      this.material.uniforms.map.value = this.texture;
    } else {
      this.texture.image.data = rgba;
    }
    this.texture.needsUpdate = true;
    this.centre.set(...head.centre);
    this.side = head.sideM;
    this.up.set(head.c2w[1], head.c2w[5], head.c2w[9]);   // column 1 of the row-major pose
    this.mesh.visible = true;
  }

  /** Turn the square toward `eye` (a world position): called every display frame. */
  face(eye) {
    _n.subVectors(eye, this.centre);
    if (_n.lengthSq() < 1e-12) return;
    _n.normalize();
    // Image up: the rendered camera's +y made orthogonal to the new normal (exact for the
    // rendered camera, smooth in between); the scene's up where that degenerates.
    _y.copy(this.up).addScaledVector(_n, -this.up.dot(_n));
    if (_y.lengthSq() < 1e-6) _y.set(0, 1, 0).addScaledVector(_n, -_n.y);
    if (_y.lengthSq() < 1e-6) _y.set(0, 0, -1);
    _y.normalize();
    _x.crossVectors(_y, _n).normalize();
    const s = this.side;
    _m.set(_x.x * s, _y.x * s, _n.x * s, this.centre.x,
           _x.y * s, _y.y * s, _n.y * s, this.centre.y,
           _x.z * s, _y.z * s, _n.z * s, this.centre.z,
           0, 0, 0, 1);
    this.mesh.matrix.copy(_m);
    this.mesh.matrixWorldNeedsUpdate = true;
  }

  dispose() {
    this.texture?.dispose();
    this.material.dispose();
    this.mesh.geometry.dispose();
  }
}
