// The project's camera in three.js: a camera-to-world pose in OpenCV axes (x right, y down, z forward) and
// pinhole intrinsics in pixels (pixel j's centre at j + 0.5), as `ogmap render --pose --intrinsics` take them.
import * as THREE from "three";

const OPENCV_TO_OPENGL = new THREE.Matrix4().makeScale(1, -1, -1);

// Place `camera` at the 4x4 camera-to-world matrix `c2w` (16 numbers, row-major, OpenCV axes).
export function setPose(camera, c2w) {
  const m = new THREE.Matrix4().set(...c2w).multiply(OPENCV_TO_OPENGL);
  m.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
}

// An off-centre perspective projection from fx, fy, cx, cy for a width x height image.
export function setIntrinsics(camera, { fx, fy, cx, cy, width, height }, near = 0.01, far = 1000) {
  camera.near = near;
  camera.far = far;
  camera.aspect = width / height;
  camera.fov = THREE.MathUtils.radToDeg(2 * Math.atan(height / (2 * fy)));
  camera.projectionMatrix.set(
    (2 * fx) / width, 0, 1 - (2 * cx) / width, 0,
    0, (2 * fy) / height, (2 * cy) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
}

// The camera the URL's fragment names: #pose=16 numbers&fx=..&fy=..&cx=..&cy=..&size=WxH, or null.
export function fromFragment(hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  if (!params.has("pose")) return null;
  const pose = params.get("pose").split(",").map(Number);
  const [width, height] = (params.get("size") || "").split("x").map(Number);
  const intrinsics = { fx: +params.get("fx"), fy: +params.get("fy"), cx: +params.get("cx"), cy: +params.get("cy"),
                       width, height };
  const numbers = [...pose, ...Object.values(intrinsics)];
  if (pose.length !== 16 || !numbers.every(Number.isFinite) || !(width > 0 && height > 0)) {
    throw new Error("the fragment's camera must be pose=16 numbers&fx=&fy=&cx=&cy=&size=WxH");
  }
  return { pose, intrinsics };
}
