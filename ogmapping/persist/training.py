"""What a mapper's optimisation carries besides the map, as plain tensors: the keyframes (with their
pose corrections and exposures), Adam's moments, the map's moving average, the refinement statistics,
the anchors' exact centres and the random states.

A snapshot leaves these out (a map rebuilt from it renders the same, and maps on with fresh
keyframes and moments); a checkpoint keeps them (``Mapper.state(training=True)``), so a session
resumed from one maps the frames after it as the uninterrupted session did. Keyframes dominate the
size: colour as uint8 and depth as float16, as they are kept in memory (``keyframes.Keyframe``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.optim import exposure
from ogmapping.optim.averaging import MapAverage
from ogmapping.optim.keyframes import Keyframe, KeyframeSet
from ogmapping.optim.lazy_adam import LazyAdam
from ogmapping.optim.poses import PoseCorrection
from ogmapping.structure.anchors import LEARNABLE, MOMENTS, AnchorMap
from ogmapping.structure.footprint import Footprint

PREFIX = "training."
STATISTICS = ("positions", "grad_sum", "grad_count", "max_opacity")


@dataclass
class Optimisation:
    """The parts of a mapper its optimisation state lives in (the mapper hands over its own)."""

    anchors: AnchorMap
    optimizer: torch.optim.Optimizer
    hash_optimizer: LazyAdam | None
    generator: torch.Generator
    keyframes: KeyframeSet
    device: torch.device
    last_gaussians: int
    average: MapAverage
    exposure: bool  # keyframes.exposure: every keyframe but the first has an exposure in the optimiser


def _scalar(value: float | int, dtype: torch.dtype) -> torch.Tensor:
    return torch.tensor([value], dtype=dtype)


def frame_indices_as_int64(indices: list[int]) -> torch.Tensor:
    """Frame indices (the protocol's uint64) in an int64 tensor: indices from 2^63 on wrap to negative
    values (two's complement), as a fuzzed client's 2^64 - 1 once made a checkpoint write fail."""
    return torch.tensor([index - (1 << 64) if index >= 1 << 63 else index for index in indices], dtype=torch.int64)


def frame_indices_from_int64(values: torch.Tensor) -> list[int]:
    """The frame indices ``frame_indices_as_int64`` stored, unwrapped."""
    return [index + (1 << 64) if index < 0 else index for index in values.reshape(-1).tolist()]


def capture(mapper: Optimisation) -> dict[str, torch.Tensor]:
    """The training state in a mapper's parts (hold its lock), keyed ``training.*``, as copies on the CPU."""
    tensors: dict[str, torch.Tensor] = {f"anchors.{name}": getattr(mapper.anchors, name) for name in STATISTICS}
    tensors["anchors.average_steps"] = mapper.anchors.average_steps
    tensors.update({f"anchors.average.{name}": mapper.anchors.averages[name] for name in LEARNABLE})
    tensors.update({f"average.{name}": value for name, value in mapper.average.state().items()})
    for group in mapper.optimizer.param_groups:
        for position, param in enumerate(group["params"]):
            for key, value in mapper.optimizer.state.get(param, {}).items():
                value = torch.as_tensor(value)
                live = key in MOMENTS and _is_row_buffer(mapper.anchors, param)
                tensors[f"adam.{group['name']}.{position}.{key}"] = value[: len(mapper.anchors)] if live else value
    if mapper.hash_optimizer is not None:
        tensors["hash_adam.step_count"] = _scalar(mapper.hash_optimizer.step_count, torch.int64)
        tensors["hash_adam.exp_avg"] = mapper.hash_optimizer.exp_avg
        tensors["hash_adam.exp_avg_sq"] = mapper.hash_optimizer.exp_avg_sq
    tensors["generator"] = mapper.generator.get_state()
    tensors["last_gaussians"] = _scalar(mapper.last_gaussians, torch.int64)
    keyframes = mapper.keyframes
    version, internal, gauss = keyframes.random.getstate()
    tensors["keyframes.random"] = torch.tensor([version, *internal], dtype=torch.int64)
    tensors["keyframes.random_gauss"] = _scalar(math.nan if gauss is None else gauss, torch.float64)
    for name in ("local", "global_", "fixed"):
        tensors[f"keyframes.{name}"] = torch.tensor(getattr(keyframes, name), dtype=torch.int64)
    tensors["keyframes.count"] = _scalar(len(keyframes), torch.int64)
    tensors["keyframes.revisits"] = torch.tensor(list(keyframes.revisits), dtype=torch.int64).reshape(-1, 2)
    tensors["keyframes.draws"] = _scalar(keyframes.draws, torch.int64)
    tensors["keyframes.trained"] = torch.tensor(keyframes.trained, dtype=torch.int64)
    for position, keyframe in enumerate(keyframes.keyframes):
        camera = keyframe.intrinsics
        tensors.update({
            f"keyframes.{position}.index": frame_indices_as_int64([keyframe.index]),
            f"keyframes.{position}.rgb": keyframe.rgb,
            f"keyframes.{position}.depth": keyframe.depth,
            f"keyframes.{position}.intrinsics": torch.tensor(
                [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height], dtype=torch.float64),
            f"keyframes.{position}.c2w": keyframe.c2w,
            f"keyframes.{position}.codes": keyframe.footprint.codes(),
        })
        if keyframe.correction is not None:
            tensors[f"keyframes.{position}.correction"] = keyframe.correction.state()
        if keyframe.exposure is not None:
            tensors[f"keyframes.{position}.exposure"] = keyframe.exposure.state()
    return {PREFIX + name: value.detach().cpu().clone() for name, value in tensors.items()}


def _shaped(tensors: dict[str, torch.Tensor], name: str, like: torch.Tensor) -> torch.Tensor:
    value = tensors[name]
    if value.shape != like.shape:
        raise ValueError(f"{PREFIX}{name}: shape {tuple(value.shape)}, expected {tuple(like.shape)}")
    return value.to(like.device, like.dtype)


def _is_row_buffer(anchors: AnchorMap, param: torch.Tensor) -> bool:
    return any(param is anchors.parameter(name) for name in LEARNABLE)


def _moment(state: dict[str, torch.Tensor], key: str, param: torch.Tensor, anchors: AnchorMap) -> torch.Tensor:
    """Adam's moment ``key`` of ``param`` as saved: an anchor buffer's live rows go back into a buffer of
    its capacity (the rows past the count stay zero)."""
    if not _is_row_buffer(anchors, param):
        return _shaped(state, key, param.detach())
    moment = torch.zeros_like(param.detach())
    moment[: len(anchors)] = _shaped(state, key, param.detach()[: len(anchors)])
    return moment


def restore(mapper: Optimisation, tensors: dict[str, torch.Tensor]) -> int | None:
    """Put a captured training state into a mapper's parts, which already hold the map it was
    captured with, and return its ``last_gaussians``; a state without any (a snapshot) leaves the
    fresh one (None). KeyError or ValueError when it does not fit the map."""
    section = {name[len(PREFIX):]: value for name, value in tensors.items() if name.startswith(PREFIX)}
    if not section:
        return None
    anchors = mapper.anchors
    for name in STATISTICS:
        setattr(anchors, name, _shaped(section, f"anchors.{name}", getattr(anchors, name)))
    _restore_average(mapper, section)
    _restore_keyframes(mapper, section)  # first: their exposures join the optimiser, whose moments follow
    optimizer = mapper.optimizer
    for group in optimizer.param_groups:
        for position, param in enumerate(group["params"]):
            prefix = f"adam.{group['name']}.{position}."
            state = {name[len(prefix):]: value for name, value in section.items() if name.startswith(prefix)}
            optimizer.state.pop(param, None)
            if state:
                optimizer.state[param] = {"step": state["step"]}
                for key in MOMENTS:
                    optimizer.state[param][key] = _moment(state, key, param, anchors)
    if mapper.hash_optimizer is not None:
        adam = mapper.hash_optimizer
        adam.step_count = int(section["hash_adam.step_count"][0])
        adam.exp_avg = _shaped(section, "hash_adam.exp_avg", adam.exp_avg)
        adam.exp_avg_sq = _shaped(section, "hash_adam.exp_avg_sq", adam.exp_avg_sq)
    mapper.generator.set_state(section["generator"])
    return int(section["last_gaussians"][0])


def _restore_average(mapper: Optimisation, section: dict[str, torch.Tensor]) -> None:
    """The map's moving average; a checkpoint written before it was kept has none, and the average
    starts afresh from the live map."""
    if "anchors.average_steps" not in section:
        return
    anchors = mapper.anchors
    anchors.average_steps = _shaped(section, "anchors.average_steps", anchors.average_steps)
    for name, average in anchors.averages.items():
        average.copy_(_shaped(section, f"anchors.average.{name}", average))
    prefix = "average."
    mapper.average.load({name[len(prefix):]: value.to(mapper.device)
                         for name, value in section.items() if name.startswith(prefix)})


def _correction(row: torch.Tensor | None, c2w: torch.Tensor, device: torch.device) -> PoseCorrection | None:
    return None if row is None else PoseCorrection.from_state(row, device, c2w.dtype)


def _exposure(mapper: Optimisation, position: int, row: torch.Tensor | None) -> exposure.Exposure | None:
    """Keyframe ``position``'s exposure, joined to the optimiser: none for the first or with the switch off;
    the identity where the state holds none."""
    if not mapper.exposure or position == 0:
        return None
    restored = exposure.Exposure(mapper.device) if row is None else exposure.Exposure.from_state(row, mapper.device)
    exposure.join(mapper.optimizer, restored)
    return restored


def _restore_keyframes(mapper: Optimisation, section: dict[str, torch.Tensor]) -> None:
    keyframes = mapper.keyframes
    pinned = mapper.device.type == "cuda"
    restored = []
    for position in range(int(section["keyframes.count"][0])):
        prefix = f"keyframes.{position}."
        fx, fy, cx, cy, width, height = section[prefix + "intrinsics"].tolist()
        rgb, depth = section[prefix + "rgb"], section[prefix + "depth"]
        restored.append(Keyframe(
            frame_indices_from_int64(section[prefix + "index"])[0], rgb.pin_memory() if pinned else rgb,
            depth.pin_memory() if pinned else depth, Intrinsics(fx, fy, cx, cy, int(width), int(height)),
            section[prefix + "c2w"].to(mapper.device), Footprint.of_codes(section[prefix + "codes"].to(mapper.device)),
            pinned,
            _correction(section.get(prefix + "correction"), section[prefix + "c2w"], mapper.device),
            exposure=_exposure(mapper, position, section.get(prefix + "exposure")),
        ))
    keyframes.keyframes = restored
    for name in ("local", "global_", "fixed"):
        indices = section[f"keyframes.{name}"].tolist()
        if any(not 0 <= index < len(restored) for index in indices):
            raise ValueError(f"{PREFIX}keyframes.{name}: an index beyond the {len(restored)} keyframes")
        setattr(keyframes, name, indices)
    # Corrected keyframes still to join windows; states written before corrections existed hold none.
    revisits = section.get("keyframes.revisits", torch.zeros(0, 2, dtype=torch.int64)).reshape(-1, 2).tolist()
    if any(not 0 <= position < len(restored) or left < 1 for position, left in revisits):
        raise ValueError(f"{PREFIX}keyframes.revisits: a keyframe beyond the {len(restored)} keyframes")
    keyframes.revisits = deque((position, left) for position, left in revisits)
    # When each keyframe was last in a window; states written before the stalest draw existed hold none.
    keyframes.draws = int(section.get("keyframes.draws", torch.zeros(1, dtype=torch.int64))[0])
    trained = section.get("keyframes.trained", torch.full((len(restored),), -1, dtype=torch.int64)).tolist()
    if len(trained) != len(restored) or any(not -1 <= draw <= keyframes.draws for draw in trained):
        raise ValueError(f"{PREFIX}keyframes.trained: not one draw in 0..{keyframes.draws} (or -1) per keyframe")
    keyframes.trained = trained
    version, *internal = section["keyframes.random"].tolist()
    gauss = float(section["keyframes.random_gauss"][0])
    keyframes.random.setstate((version, tuple(internal), None if math.isnan(gauss) else gauss))
