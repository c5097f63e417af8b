// The proxy at work: each object's `-colonly` mesh as a static trimesh collider (cannon-es), a
// floor, and balls and boxes dropped onto them. Everything in the scene frame (metres, +Y up).

import * as CANNON from 'cannon-es';
import * as THREE from 'three';

const STEP_S = 1 / 120;
const ROLLING_DECEL = 0.02 * 9.81;       // m/s²

export class Physics {
  constructor(scene) {
    this.scene = scene;
    this.world = new CANNON.World({ gravity: new CANNON.Vec3(0, -9.81, 0) });
    this.world.allowSleep = true;
    this.world.broadphase = new CANNON.SAPBroadphase(this.world);
    this.material = new CANNON.Material('dbb');
    this.world.defaultContactMaterial = new CANNON.ContactMaterial(this.material, this.material,
      { friction: 0.6, restitution: 0.15, contactEquationStiffness: 1e7, contactEquationRelaxation: 3 });
    this.floor = new CANNON.Body({ mass: 0, material: this.material, shape: new CANNON.Plane() });
    this.floor.quaternion.setFromEuler(-Math.PI / 2, 0, 0);
    this.world.addBody(this.floor);
    // cannon-es has no rolling resistance: bodies touching something slow down by ROLLING_DECEL
    // (a resistance coefficient of 0.02), so a ball that rolled off stops instead of rolling for ever.
    this.world.addEventListener('postStep', () => {
      const touching = new Set();
      for (const c of this.world.contacts) { touching.add(c.bi); touching.add(c.bj); }
      const dv = ROLLING_DECEL * this.world.dt;
      for (const b of this.bodies) {
        if (!touching.has(b.body)) continue;
        const v = b.body.velocity, speed = v.length();
        const k = speed > dv ? (speed - dv) / speed : 0;
        v.scale(k, v);
        b.body.angularVelocity.scale(k, b.body.angularVelocity);
      }
    });
    this.colliders = new Map();          // object index -> static body
    this.bodies = [];                    // {body, mesh, kind, size}
    this.ballMaterial = new THREE.MeshStandardMaterial({ color: 0xe8663d, roughness: 0.45, metalness: 0.05 });
    this.boxMaterial = new THREE.MeshStandardMaterial({ color: 0x3d8ee8, roughness: 0.6 });
  }

  setFloor(y) { this.floor.position.set(0, y, 0); }

  /** A static trimesh collider from a world-space BufferGeometry (positions, optional index). */
  addCollider(index, geometry) {
    this.removeCollider(index);
    const pos = geometry.attributes.position.array;
    const idx = geometry.index ? Array.from(geometry.index.array) : [...Array(pos.length / 3).keys()];
    const shape = new CANNON.Trimesh(Array.from(pos), idx);
    const body = new CANNON.Body({ mass: 0, material: this.material, shape });
    this.world.addBody(body);
    this.colliders.set(index, body);
    for (const b of this.bodies) b.body.wakeUp();
  }

  removeCollider(index) {
    const b = this.colliders.get(index);
    if (b) this.world.removeBody(b);
    this.colliders.delete(index);
  }

  /** Drop a ball (radius r) or a box (side 2r) at `at` (THREE.Vector3). */
  drop(kind, at, r) {
    let body, mesh;
    if (kind === 'box') {
      // cannon-es has no box–trimesh contact: the box also carries a small sphere in each corner
      // (inside it, touching its faces), which meet the proxy's triangles; the Box shape itself
      // meets the floor, other boxes and balls.
      body = new CANNON.Body({ mass: 8 * r * r * r * 400, material: this.material });
      body.addShape(new CANNON.Box(new CANNON.Vec3(r, r, r)));
      const s = 0.3 * r;
      for (const x of [-1, 1]) for (const y of [-1, 1]) for (const z of [-1, 1]) {
        body.addShape(new CANNON.Sphere(s), new CANNON.Vec3(x * (r - s), y * (r - s), z * (r - s)));
      }
      body.quaternion.setFromEuler(Math.random() * 3, Math.random() * 3, Math.random() * 3);
      mesh = new THREE.Mesh(new THREE.BoxGeometry(2 * r, 2 * r, 2 * r), this.boxMaterial);
    } else {
      body = new CANNON.Body({ mass: (4 / 3) * Math.PI * r * r * r * 400, material: this.material,
                               shape: new CANNON.Sphere(r) });
      mesh = new THREE.Mesh(new THREE.SphereGeometry(r, 24, 16), this.ballMaterial);
    }
    body.linearDamping = 0.1;
    body.angularDamping = 0.5;
    body.sleepSpeedLimit = kind === 'box' ? 0.02 : 0.01;
    body.sleepTimeLimit = 0.4;
    body.position.set(at.x, at.y, at.z);
    mesh.castShadow = true;
    mesh.renderOrder = 3;
    mesh.receiveShadow = true;
    this.world.addBody(body);
    this.scene.add(mesh);
    this.bodies.push({ body, mesh, kind, size: r });
    this._sync(this.bodies[this.bodies.length - 1]);
  }

  clear() {
    for (const b of this.bodies) {
      this.world.removeBody(b.body);
      this.scene.remove(b.mesh);
      b.mesh.geometry.dispose();
    }
    this.bodies = [];
  }

  step(dtS) {
    this.world.step(STEP_S, Math.min(dtS, 0.1), 12);
    for (const b of this.bodies) this._sync(b);
  }

  /** Whether any body is awake (the picture and the shadows change). */
  moving() {
    return this.bodies.some((b) => b.body.sleepState !== CANNON.Body.SLEEPING);
  }

  _sync(b) {
    b.mesh.position.set(b.body.position.x, b.body.position.y, b.body.position.z);
    b.mesh.quaternion.set(b.body.quaternion.x, b.body.quaternion.y, b.body.quaternion.z, b.body.quaternion.w);
  }

  /** Positions (world frame), speeds and sleep states, for the HUD and tests. */
  state() {
    return this.bodies.map((b) => ({
      kind: b.kind, radius: b.size,
      position: [b.body.position.x, b.body.position.y, b.body.position.z],
      speed: b.body.velocity.length(),
      sleeping: b.body.sleepState === CANNON.Body.SLEEPING,
    }));
  }
}
