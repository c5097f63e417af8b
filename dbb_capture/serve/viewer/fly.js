// Fly mode: drag to look around, W A S D (or arrows) to move, Q / E down and up, Shift faster.

import * as THREE from 'three';

export class Fly {
  constructor(camera, dom) {
    this.camera = camera;
    this.dom = dom;
    this.enabled = false;
    this.speed = 0.4;                     // metres per second
    this.keys = new Set();
    this.yaw = 0;
    this.pitch = 0;
    this._drag = null;
    dom.addEventListener('pointerdown', (e) => {
      if (this.enabled) this._drag = { x: e.clientX, y: e.clientY };
    });
    window.addEventListener('pointerup', () => { this._drag = null; });
    window.addEventListener('pointermove', (e) => {
      if (!this.enabled || !this._drag) return;
      this.yaw -= (e.clientX - this._drag.x) * 0.004;
      this.pitch = THREE.MathUtils.clamp(this.pitch - (e.clientY - this._drag.y) * 0.004, -1.55, 1.55);
      this._drag = { x: e.clientX, y: e.clientY };
    });
    window.addEventListener('keydown', (e) => {
      if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
      this.keys.add(e.code);
    });
    window.addEventListener('keyup', (e) => this.keys.delete(e.code));
    window.addEventListener('blur', () => this.keys.clear());
  }

  start() {
    const e = new THREE.Euler().setFromQuaternion(this.camera.quaternion, 'YXZ');
    this.yaw = e.y;
    this.pitch = e.x;
    this.enabled = true;
  }

  stop() { this.enabled = false; this.keys.clear(); }

  update(dtS) {
    if (!this.enabled) return;
    this.camera.quaternion.setFromEuler(new THREE.Euler(this.pitch, this.yaw, 0, 'YXZ'));
    const k = this.keys;
    const move = new THREE.Vector3(
      (k.has('KeyD') || k.has('ArrowRight') ? 1 : 0) - (k.has('KeyA') || k.has('ArrowLeft') ? 1 : 0),
      (k.has('KeyE') ? 1 : 0) - (k.has('KeyQ') ? 1 : 0),
      (k.has('KeyS') || k.has('ArrowDown') ? 1 : 0) - (k.has('KeyW') || k.has('ArrowUp') ? 1 : 0));
    if (move.lengthSq() === 0) return;
    move.normalize().applyQuaternion(this.camera.quaternion);
    const fast = k.has('ShiftLeft') || k.has('ShiftRight') ? 3 : 1;
    this.camera.position.addScaledVector(move, this.speed * fast * dtS);
  }
}
