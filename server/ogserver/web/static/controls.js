// The page's camera controls: orbit (turn about a point ahead of the camera) and fly (turn in place, move
// with the keys), both about the map's world up, so the horizon stays level: the camera has a position, a
// yaw about up and a pitch (within +-89 degrees), and never a roll.
import * as THREE from "three";

const MAX_PITCH = THREE.MathUtils.degToRad(89);
const TURN_PER_PIXEL = 0.005; // radians
const ZOOM_PER_WHEEL = 0.001; // orbit distance factor exp(delta * this); fly: metres per delta at speed 1
const TURN_PER_SECOND = 1.5; // arrow keys, radians
const FAST = 4; // with Shift held
const MOVES = { KeyW: [0, 0, 1], KeyS: [0, 0, -1], KeyA: [-1, 0, 0], KeyD: [1, 0, 0], KeyQ: [0, -1, 0],
                KeyE: [0, 1, 0] }; // [right, up, forward]
const TURNS = { ArrowLeft: [1, 0], ArrowRight: [-1, 0], ArrowUp: [0, 1], ArrowDown: [0, -1] }; // [yaw, pitch]

export class ViewControls {
  constructor(camera, element) {
    this.camera = camera;
    this.mode = "orbit";
    this.position = new THREE.Vector3();
    this.yaw = 0;
    this.pitch = 0;
    this.distance = 1; // from the camera to the point it orbits, along its view
    this.speed = 1; // metres per second for the keys, set from the scene's size
    this.touched = false; // whether the user has moved the camera
    this.up = new THREE.Vector3();
    this.east = new THREE.Vector3(); // yaw 0
    this.north = new THREE.Vector3(); // yaw 90 degrees: up x east
    this.setUp(new THREE.Vector3(0, -1, 0));
    this.held = new Set(); // the movement and turning keys held down
    this.fast = false; // Shift held
    this.pointers = new Map();
    element.addEventListener("pointerdown", (event) => this.pointerDown(event));
    element.addEventListener("pointermove", (event) => this.pointerMove(event));
    element.addEventListener("pointerup", (event) => this.pointers.delete(event.pointerId));
    element.addEventListener("pointercancel", (event) => this.pointers.delete(event.pointerId));
    element.addEventListener("contextmenu", (event) => event.preventDefault());
    element.addEventListener("wheel", (event) => this.wheel(event), { passive: false });
    window.addEventListener("keydown", (event) => this.key(event, true));
    window.addEventListener("keyup", (event) => this.key(event, false));
    window.addEventListener("blur", () => this.held.clear());
  }

  setUp(up) {
    this.up.copy(up).normalize();
    const axes = [new THREE.Vector3(1, 0, 0), new THREE.Vector3(0, 1, 0), new THREE.Vector3(0, 0, 1)];
    const least = axes.reduce((a, b) => (Math.abs(a.dot(this.up)) <= Math.abs(b.dot(this.up)) ? a : b));
    this.east.copy(least).addScaledVector(this.up, -least.dot(this.up)).normalize();
    this.north.crossVectors(this.up, this.east);
  }

  forward(out = new THREE.Vector3()) {
    const level = Math.cos(this.pitch);
    return out.copy(this.east).multiplyScalar(level * Math.cos(this.yaw))
      .addScaledVector(this.north, level * Math.sin(this.yaw)).addScaledVector(this.up, Math.sin(this.pitch));
  }

  target() {
    return this.position.clone().addScaledVector(this.forward(), this.distance);
  }

  // Place the camera at `position` looking along `look` (its roll dropped), orbiting at `distance`.
  look(position, look, distance = this.distance) {
    const direction = look.clone().normalize();
    const height = THREE.MathUtils.clamp(direction.dot(this.up), -1, 1);
    this.pitch = THREE.MathUtils.clamp(Math.asin(height), -MAX_PITCH, MAX_PITCH);
    if (Math.abs(height) < 0.9999) this.yaw = Math.atan2(direction.dot(this.north), direction.dot(this.east));
    this.position.copy(position);
    this.distance = distance;
    this.apply();
  }

  // Orbit `target` from `distance` away, the view's yaw kept and its pitch as given.
  aim(target, distance, pitch) {
    this.pitch = pitch;
    this.distance = distance;
    this.position.copy(target).addScaledVector(this.forward(), -distance);
    this.apply();
  }

  apply() {
    this.camera.position.copy(this.position);
    this.camera.up.copy(this.up);
    this.camera.lookAt(this.target());
    this.camera.updateMatrixWorld(true);
  }

  turn(yaw, pitch) {
    const target = this.target();
    this.yaw += yaw;
    this.pitch = THREE.MathUtils.clamp(this.pitch + pitch, -MAX_PITCH, MAX_PITCH);
    if (this.mode === "orbit") this.position.copy(target).addScaledVector(this.forward(), -this.distance);
    this.touched = true;
  }

  // Move by [right, up, forward] in metres: up is the world's, forward the view's.
  move([right, up, forward]) {
    const view = this.forward();
    const side = new THREE.Vector3().crossVectors(view, this.up).normalize();
    this.position.addScaledVector(side, right).addScaledVector(this.up, up).addScaledVector(view, forward);
    this.touched = true;
  }

  // Slide the view across the screen by pixels, as if dragging the scene along.
  pan(dx, dy) {
    const scale = (this.mode === "orbit" ? this.distance : this.speed) * 2 / Math.max(1, window.innerHeight);
    const view = this.forward();
    const side = new THREE.Vector3().crossVectors(view, this.up).normalize();
    const screenUp = new THREE.Vector3().crossVectors(side, view);
    this.position.addScaledVector(side, -dx * scale).addScaledVector(screenUp, dy * scale);
    this.touched = true;
  }

  zoom(delta) {
    if (this.mode === "orbit") {
      const target = this.target();
      this.distance = THREE.MathUtils.clamp(this.distance * Math.exp(delta * ZOOM_PER_WHEEL), 0.05, 1000);
      this.position.copy(target).addScaledVector(this.forward(), -this.distance);
      this.touched = true;
    } else {
      this.move([0, 0, -delta * ZOOM_PER_WHEEL * this.speed]);
    }
  }

  pointerDown(event) {
    event.target.setPointerCapture?.(event.pointerId);
    this.pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
  }

  pointerMove(event) {
    const last = this.pointers.get(event.pointerId);
    if (!last) return;
    const dx = event.clientX - last.x;
    const dy = event.clientY - last.y;
    if (this.pointers.size === 2) {
      const [a, b] = [...this.pointers.values()];
      const before = Math.hypot(a.x - b.x, a.y - b.y);
      last.x = event.clientX;
      last.y = event.clientY;
      this.pan(dx / 2, dy / 2);
      this.zoom((before - Math.hypot(a.x - b.x, a.y - b.y)) * 4);
      return;
    }
    last.x = event.clientX;
    last.y = event.clientY;
    if (event.buttons & 2 || event.buttons & 4 || event.shiftKey) this.pan(dx, dy);
    else this.turn(-dx * TURN_PER_PIXEL, -dy * TURN_PER_PIXEL);
  }

  wheel(event) {
    event.preventDefault();
    this.zoom(event.deltaY * (event.deltaMode === 1 ? 30 : 1));
  }

  key(event, down) {
    if (event.target.closest?.("input, select, textarea") || event.ctrlKey || event.metaKey || event.altKey) return;
    if (!(event.code in MOVES) && !(event.code in TURNS)) return;
    if (down) this.held.add(event.code);
    else this.held.delete(event.code);
    this.fast = event.shiftKey;
  }

  // Apply the held keys for `seconds` and place the camera.
  update(seconds) {
    const step = seconds * this.speed * (this.fast ? FAST : 1);
    for (const code of this.held) {
      if (code in MOVES) this.move(MOVES[code].map((part) => part * step));
      else this.turn(TURNS[code][0] * TURN_PER_SECOND * seconds, TURNS[code][1] * TURN_PER_SECOND * seconds);
    }
    this.apply();
  }
}
