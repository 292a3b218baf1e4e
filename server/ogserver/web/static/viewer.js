// A map's page: its Gaussians (Spark on three.js), the keyframes' path, the newest keyframe's input beside
// the render from its pose, and the map's statistics, polled from /api/map/ID/. The camera orbits or flies
// about the world's up (the state's "up"), level; a link in the fragment (link.js) opens a given view. With
// a fixed camera in the fragment (#pose=...) it draws only the map from that camera. window.ogmapReady is
// set once the first frame with the map's Gaussians is on screen, whatever the fragment.
import * as THREE from "three";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import { fromFragment, setIntrinsics, setPose } from "/static/camera.js";
import { ViewControls } from "/static/controls.js";
import * as link from "/static/link.js";

const POLL_MS = 500;
const mapId = location.pathname.split("/").pop();
const credential = location.search; // "?key=..." or "?token=...", passed on to every request
const api = (part, query = "") =>
  `/api/map/${mapId}/${part}${credential}${query ? (credential ? "&" : "?") + query : ""}`;
const element = (id) => document.getElementById(id);

function showMessage(text) {
  element("message-text").textContent = text;
  element("message").hidden = false;
}

// What the fragment asks for: a fixed camera, a view to open, or nothing; a message for one that is neither.
function readFragment() {
  if (!location.hash || location.hash === "#") return {};
  try {
    if (link.namesView(location.hash)) return { view: link.fromFragment(location.hash) };
    const fixed = fromFragment(location.hash);
    if (fixed) return { fixed };
    throw new Error("it names neither a view (#eye=...) nor a camera (#pose=...)");
  } catch (error) {
    showMessage(`This address's fragment (after #) is not a view this page can open: ${error.message}. ` +
                "Showing the map's first view instead.");
    return {};
  }
}

const { fixed, view: linked } = readFragment();
const canvas = element("view");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false });
const scene = new THREE.Scene();
// The engine's rasteriser adds 0.3 px^2 to each splat's 2D covariance without changing its opacity: Spark's
// preBlurAmount; its own blurAmount (which also scales opacity) stays off.
const spark = new SparkRenderer({ renderer, preBlurAmount: 0.3, blurAmount: 0, onDirty: () => { dirty = true; } });
scene.add(spark);
const camera = new THREE.PerspectiveCamera(60, 1, 0.01, 1000);
let mesh = null;
let bounds = null; // the loaded Gaussians' extent: { center, radius }, found when first asked for
let loadedVersion = -1;
let loading = false;
let dirty = true; // the free view draws only when the camera, the map or Spark's sort order changed

function resize() {
  const width = fixed ? fixed.intrinsics.width : canvas.clientWidth;
  const height = fixed ? fixed.intrinsics.height : canvas.clientHeight;
  renderer.setPixelRatio(fixed ? 1 : window.devicePixelRatio);
  renderer.setSize(width, height, !!fixed);
  dirty = true;
  if (!fixed) {
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
  }
}

async function loadSplats() {
  loading = true;
  try {
    const center = fixed ? `center=${fixed.pose[3]},${fixed.pose[7]},${fixed.pose[11]}` : "";
    const response = await fetch(api("splats.ply", center));
    if (!response.ok) throw new Error(`${response.status} ${await response.text()}`);
    const version = Number(response.headers.get("X-Map-Version"));
    const next = new SplatMesh({ fileBytes: await response.arrayBuffer(), fileType: "ply" });
    await next.initialized;
    if (mesh) {
      scene.remove(mesh);
      mesh.dispose();
    }
    mesh = next;
    bounds = null;
    scene.add(mesh);
    loadedVersion = version;
    dirty = true;
  } finally {
    loading = false;
  }
}

// Sort the splats for the camera (Spark does it in a worker), draw, and let two frames pass.
async function drawSorted() {
  for (let pass = 0; pass < 2; pass++) {
    await spark.update({ scene, camera });
    renderer.render(scene, camera);
  }
  await new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)));
  renderer.render(scene, camera);
}

// Draw the map from the fragment's camera once its splats are sorted for it, and again after each new
// version of the map: window.ogmapReady once the first frame is on screen, window.ogmapVersion the map's.
async function drawFixed() {
  await loadSplats();
  await drawSorted();
  window.ogmapVersion = loadedVersion;
  window.ogmapReady = true;
}

async function runFixed() {
  document.body.classList.add("pose");
  setIntrinsics(camera, fixed.intrinsics);
  setPose(camera, fixed.pose);
  resize();
  await drawFixed();
  for (;;) {
    await new Promise((done) => setTimeout(done, POLL_MS));
    const response = await fetch(api("state"));
    if (response.ok && (await response.json()).version !== loadedVersion) await drawFixed();
  }
}

// The keyframes' path, its buffer grown by doubling as the session maps (a buffer is never refilled past
// its size: three.js would refuse it).
class Path {
  constructor() {
    this.line = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xffaa00 }));
    this.line.frustumCulled = false;
    this.count = -1;
  }

  show(points) {
    if (points.length === this.count) return false;
    let positions = this.line.geometry.getAttribute("position");
    if (!positions || positions.count < points.length) {
      this.line.geometry.dispose();
      this.line.geometry = new THREE.BufferGeometry();
      positions = new THREE.BufferAttribute(new Float32Array(3 * Math.max(8, 2 * points.length)), 3);
      this.line.geometry.setAttribute("position", positions);
    }
    positions.array.set(points.flat());
    positions.needsUpdate = true;
    this.line.geometry.setDrawRange(0, points.length);
    this.count = points.length;
    return true;
  }
}

const path = new Path();
const controls = new ViewControls(camera, canvas);
let first = null; // the first view: { position, look, up, distance }, where reset goes back to
let shownFrame = null; // the sensor time of the keyframe whose images are shown

function showStats(state) {
  element("title").textContent = state.label || state.id;
  document.title = `OG-Mapping: ${state.label || state.id}`;
  element("stats").replaceChildren(...Object.entries(state.stats).flatMap(([name, value]) => {
    const term = document.createElement("dt");
    const detail = document.createElement("dd");
    term.textContent = name.replaceAll("_", " ");
    detail.textContent = typeof value === "number" ? value.toLocaleString() : value;
    return [term, detail];
  }));
  for (const figure of document.querySelectorAll("#panel figure")) figure.hidden = !state.latest;
  if (state.latest && state.latest.sensor_ns !== shownFrame) {
    shownFrame = state.latest.sensor_ns;
    const stamp = `${credential ? "&" : "?"}t=${shownFrame}`;
    element("frame-image").src = api("frame") + stamp;
    element("render").src = api("render.jpg") + stamp;
  }
}

// The first view: the state's start pose (the newest keyframe's) with its roll dropped, about the world's
// up (the start camera's own where the map has no keyframes yet), orbiting a point a metre ahead; or the
// link's view. Placed again while the user has not moved and the map's up is still to come.
function placeFirst(state) {
  if (first && (first.final || controls.touched)) return;
  const start = new THREE.Matrix4().set(...state.start);
  const axis = (column) => new THREE.Vector3().setFromMatrixColumn(start, column);
  const up = state.up ? new THREE.Vector3(...state.up) : axis(1).negate();
  first = { position: axis(3), look: axis(2), up, distance: 1, mode: "orbit", fov: 60, final: !!state.up };
  if (linked) {
    first = { position: new THREE.Vector3(...linked.eye), look: new THREE.Vector3(...linked.look),
              up: new THREE.Vector3(...linked.up), distance: linked.distance, mode: linked.mode, fov: linked.fov,
              final: true };
  }
  resetView();
  controls.touched = false;
}

function resetView() {
  camera.fov = first.fov;
  camera.updateProjectionMatrix();
  setMode(first.mode);
  controls.setUp(first.up);
  controls.look(first.position, first.look, first.distance);
  dirty = true;
}

function setMode(mode) {
  controls.mode = mode;
  element("mode").value = mode;
}

// The middle 90% of the Gaussians' centres along each axis: stray splats far out do not count.
function findBounds() {
  const stride = Math.max(1, Math.floor(mesh.numSplats / 20000));
  const axes = [[], [], []];
  mesh.forEachSplat((index, center) => {
    if (index % stride === 0) [center.x, center.y, center.z].forEach((value, axis) => axes[axis].push(value));
  });
  if (axes[0].length === 0) return null;
  const [low, high] = [0.05, 0.95].map((share) => new THREE.Vector3(...axes.map((values) => {
    values.sort((a, b) => a - b);
    return values[Math.floor(share * (values.length - 1))];
  })));
  return { center: low.clone().add(high).multiplyScalar(0.5), radius: Math.max(0.1, low.distanceTo(high) / 2) };
}

function frameScene() {
  bounds = bounds || (mesh && mesh.numSplats ? findBounds() : null);
  if (!bounds) return;
  const fit = bounds.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov) / 2);
  controls.aim(bounds.center, fit, -THREE.MathUtils.degToRad(25));
  controls.speed = Math.max(0.3, bounds.radius / 2);
  dirty = true;
}

function viewLink() {
  return location.origin + location.pathname + location.search + link.toFragment({
    eye: controls.position, look: controls.forward(), up: controls.up, fov: camera.fov, mode: controls.mode,
    distance: controls.distance,
  });
}

async function copyLink() {
  const field = element("link");
  field.value = viewLink();
  field.hidden = false;
  field.select();
  try {
    await navigator.clipboard.writeText(field.value);
    element("copy-link").textContent = "link copied";
  } catch {
    element("copy-link").textContent = "copy the link below";
  }
  setTimeout(() => { element("copy-link").textContent = "copy link to this view"; }, 2000);
}

function togglePanel() {
  const hidden = document.body.classList.toggle("panel-hidden");
  element("panel-toggle").textContent = hidden ? "show panel" : "hide panel";
  element("panel-toggle").setAttribute("aria-expanded", String(!hidden));
}

function toggleHelp(show = element("help").hidden) {
  element("help").hidden = !show;
}

// The camera as the project writes one (camera-to-world, row-major, OpenCV axes) and the points of the path
// drawn: for tests and tools.
window.ogmapCamera = () => {
  const c2w = camera.matrixWorld.clone().multiply(new THREE.Matrix4().makeScale(1, -1, -1));
  return { c2w: c2w.transpose().toArray(), fov: camera.fov, mode: controls.mode, up: controls.up.toArray(),
           pathPoints: path.count };
};

const KEYS = { r: resetView, f: frameScene, l: copyLink, p: togglePanel, "?": () => toggleHelp(),
               m: () => setMode(controls.mode === "orbit" ? "fly" : "orbit"), Escape: () => toggleHelp(false) };

function bindControls() {
  element("mode").addEventListener("change", (event) => setMode(event.target.value));
  element("reset").addEventListener("click", resetView);
  element("frame").addEventListener("click", frameScene);
  element("copy-link").addEventListener("click", copyLink);
  element("help-button").addEventListener("click", () => toggleHelp(true));
  element("help").addEventListener("click", () => toggleHelp(false));
  element("panel-toggle").addEventListener("click", togglePanel);
  element("message-close").addEventListener("click", () => { element("message").hidden = true; });
  window.addEventListener("keydown", (event) => {
    if (event.target.closest?.("input, select, textarea") || event.ctrlKey || event.metaKey || event.altKey) return;
    const action = KEYS[event.key.length === 1 ? event.key.toLowerCase() : event.key];
    if (action) {
      event.preventDefault();
      action();
      dirty = true;
    }
  });
}

// Once the first version with Gaussians is sorted and drawn: the loading note goes, window.ogmapReady is set.
async function loaded() {
  if (mesh.numSplats === 0) {
    element("loading-text").textContent = "no Gaussians yet: waiting for the first keyframe…";
    return false;
  }
  await drawSorted();
  element("loading").hidden = true;
  window.ogmapVersion = loadedVersion;
  window.ogmapReady = true;
  return true;
}

async function poll() {
  let ready = false;
  for (;;) {
    try {
      const response = await fetch(api("state"));
      if (response.ok) {
        const state = await response.json();
        showStats(state);
        placeFirst(state);
        if (path.show(state.path)) dirty = true;
        if (state.version !== loadedVersion && !loading) {
          await loadSplats();
          ready = ready || await loaded();
          window.ogmapVersion = loadedVersion;
        }
      } else {
        element("loading-text").textContent = `the map could not be loaded: ${response.status}`;
      }
    } catch (error) {
      element("loading-text").textContent = `the map could not be loaded: ${error.message}`;
    }
    await new Promise((done) => setTimeout(done, POLL_MS));
  }
}

function runFree() {
  element("back").href = `/${credential}`;
  scene.add(path.line);
  bindControls();
  window.addEventListener("resize", resize);
  resize();
  let last = performance.now();
  renderer.setAnimationLoop((now) => {
    const before = camera.matrixWorld.clone();
    controls.update(Math.min(0.1, (now - last) / 1000));
    last = now;
    if (dirty || !before.equals(camera.matrixWorld)) {
      dirty = false;
      renderer.render(scene, camera);
    }
  });
  poll();
}

if (fixed) {
  runFixed().catch((error) => {
    window.ogmapError = String(error);
    console.error(error);
  });
} else {
  runFree();
}
