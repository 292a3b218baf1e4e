// A map's page: its Gaussians (Spark on three.js), the keyframes' path, the newest keyframe's input beside
// the render from its pose, and the map's statistics, polled from /api/map/ID/. With a camera in the URL's
// fragment it draws only the map from that camera and sets window.ogmapReady once that frame is shown.
import * as THREE from "three";
import { SparkControls, SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import { fromFragment, setIntrinsics, setPose } from "/static/camera.js";

const POLL_MS = 500;
const mapId = location.pathname.split("/").pop();
const credential = location.search; // "?key=..." or "?token=...", passed on to every request
const api = (part, query = "") =>
  `/api/map/${mapId}/${part}${credential}${query ? (credential ? "&" : "?") + query : ""}`;

const fixed = fromFragment(location.hash);
const canvas = document.getElementById("view");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false });
const scene = new THREE.Scene();
// The engine's rasteriser adds 0.3 px^2 to each splat's 2D covariance without changing its opacity: Spark's
// preBlurAmount; its own blurAmount (which also scales opacity) stays off.
const spark = new SparkRenderer({ renderer, preBlurAmount: 0.3, blurAmount: 0, onDirty: () => { dirty = true; } });
scene.add(spark);
const camera = new THREE.PerspectiveCamera(60, 1, 0.01, 1000);
let mesh = null;
let loadedVersion = -1;
let loading = false;
let dirty = true; // the free-fly view draws only when the camera, the map or Spark's sort order changed

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
    scene.add(mesh);
    loadedVersion = version;
    dirty = true;
  } finally {
    loading = false;
  }
}

// Draw the map from the fragment's camera once its splats are sorted for it, and again after each new
// version of the map: window.ogmapReady once the first frame is on screen, window.ogmapVersion the map's.
async function drawFixed() {
  await loadSplats();
  // Spark sorts the splats for the camera in a worker: wait for it, then draw and let two frames pass.
  for (let pass = 0; pass < 2; pass++) {
    await spark.update({ scene, camera });
    renderer.render(scene, camera);
  }
  await new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)));
  renderer.render(scene, camera);
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

const trajectory = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xffaa00 }));
let placed = false;
let shownFrame = null; // the sensor time of the keyframe whose images are shown

function showState(state) {
  document.getElementById("title").textContent = state.label || state.id;
  document.title = `OG-Mapping: ${state.label || state.id}`;
  const stats = document.getElementById("stats");
  stats.replaceChildren(...Object.entries(state.stats).flatMap(([name, value]) => {
    const term = document.createElement("dt");
    const detail = document.createElement("dd");
    term.textContent = name.replaceAll("_", " ");
    detail.textContent = typeof value === "number" ? value.toLocaleString() : value;
    return [term, detail];
  }));
  for (const figure of document.querySelectorAll("#panel figure")) figure.hidden = !state.latest;
  if (state.path.length !== trajectory.geometry.getAttribute("position")?.count) {
    trajectory.geometry.setFromPoints(state.path.map((p) => new THREE.Vector3(...p)));
    dirty = true;
  }
  if (state.latest && state.latest.sensor_ns !== shownFrame) {
    shownFrame = state.latest.sensor_ns;
    const stamp = `${credential ? "&" : "?"}t=${shownFrame}`;
    document.getElementById("frame").src = api("frame") + stamp;
    document.getElementById("render").src = api("render.jpg") + stamp;
  }
  if (!placed) {
    setPose(camera, state.start);
    placed = dirty = true;
  }
}

async function poll() {
  try {
    const response = await fetch(api("state"));
    if (response.ok) {
      const state = await response.json();
      showState(state);
      if (state.version !== loadedVersion && !loading) await loadSplats();
    }
  } catch (error) {
    console.error(error);
  }
  setTimeout(poll, POLL_MS);
}

function runFreeFly() {
  document.getElementById("back").href = `/${credential}`;
  scene.add(trajectory);
  const controls = new SparkControls({ canvas });
  window.addEventListener("resize", resize);
  resize();
  renderer.setAnimationLoop(() => {
    const before = camera.matrixWorld.clone();
    controls.update(camera);
    camera.updateMatrixWorld();
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
  runFreeFly();
}
