// A link to one view of the map: the free camera in the URL's fragment,
// #eye=X,Y,Z&look=X,Y,Z&up=X,Y,Z&fov=DEGREES&mode=orbit|fly&distance=METRES (world coordinates; look: the
// view's direction; up: the world's up the horizon is kept level to; distance: to the point orbited).
// Numbers are written in the shortest form that reads back exactly, so the link reproduces the camera.

const VECTORS = ["eye", "look", "up"];
const MODES = ["orbit", "fly"];
const FORMAT = "eye=X,Y,Z&look=X,Y,Z&up=X,Y,Z&fov=DEGREES&mode=orbit|fly&distance=METRES";

// Whether the fragment names a view (rather than a fixed camera, #pose=..., or nothing).
export function namesView(hash) {
  return new URLSearchParams(hash.replace(/^#/, "")).has("eye");
}

export function toFragment({ eye, look, up, fov, mode, distance }) {
  const vector = (v) => [v.x, v.y, v.z].map(String).join(",");
  return `#eye=${vector(eye)}&look=${vector(look)}&up=${vector(up)}&fov=${fov}&mode=${mode}&distance=${distance}`;
}

// The view the fragment names: { eye, look, up: [x, y, z], fov, mode, distance }; an Error saying what is
// wrong for a fragment that is not one.
export function fromFragment(hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  const view = {};
  for (const name of VECTORS) {
    const numbers = (params.get(name) || "").split(",").map((part) => (part.trim() === "" ? NaN : Number(part)));
    if (numbers.length !== 3 || !numbers.every(Number.isFinite)) {
      throw new Error(`${name} must be 3 numbers (the link's view: ${FORMAT})`);
    }
    view[name] = numbers;
  }
  const [fov, distance] = [Number(params.get("fov")), Number(params.get("distance"))];
  if (!(fov > 1 && fov < 179)) throw new Error(`fov must be between 1 and 179 degrees (${FORMAT})`);
  if (!(distance > 0 && Number.isFinite(distance))) throw new Error(`distance must be over 0 (${FORMAT})`);
  if (!MODES.includes(params.get("mode"))) throw new Error(`mode must be orbit or fly (${FORMAT})`);
  const length = (v) => Math.hypot(...v);
  const [look, up] = [view.look, view.up];
  const cross = [look[1] * up[2] - look[2] * up[1], look[2] * up[0] - look[0] * up[2], look[0] * up[1] - look[1] * up[0]];
  if (length(look) === 0 || length(up) === 0 || length(cross) < 1e-6 * length(look) * length(up)) {
    throw new Error(`look and up must be non-zero and not parallel (${FORMAT})`);
  }
  return { ...view, fov, mode: params.get("mode"), distance };
}
