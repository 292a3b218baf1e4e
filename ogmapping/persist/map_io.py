"""A map model copied out to a ``MapState`` and filled back in from one (``Mapper.state`` / ``from_state``).

States may come from outside (snapshots people share): every tensor is checked against the shape its
config implies before it is copied into the map, and anything that does not fit raises ValueError.
"""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np
import torch

from ogmapping.config import resolution
from ogmapping.mapping.model import MapModel
from ogmapping.optim.keyframes import KeyframeSet
from ogmapping.persist import training
from ogmapping.persist.state import MapState
from ogmapping.queries import KeyframePose, keyframe_poses


def optimisation(model: MapModel, keyframes: KeyframeSet) -> training.Optimisation:
    """The parts of ``model`` and ``keyframes`` the training state lives in."""
    return training.Optimisation(model.anchors, model.optimizer, model.hash_optimizer, model.generator, keyframes,
                                 model.device, model.last_gaussians, model.average, model.config.keyframes.exposure)


def capture(model: MapModel, keyframes: KeyframeSet, training_state: bool) -> MapState:
    """The map as detached copies (hold the mapper's lock): the map that renders (its moving average); with
    ``training_state`` the live map and what its optimisation carries (``ogmapping.persist.training``)."""
    with nullcontext() if training_state else model.average.applied():
        anchors = model.anchors
        tensors: dict[str, torch.Tensor] = {
            "anchors.codes": anchors.codes,
            "anchors.levels": anchors.levels,
            "anchors.log_scales": anchors.log_scales,
            "anchors.offsets": anchors.offsets,
            "anchors.spawned": anchors.spawned.to(torch.uint8),
            "anchors.observations": anchors.observations,
            # A pose correction moves anchors off their cells' centres, and they remember their keyframe.
            "anchors.positions": anchors.positions,
            "anchors.keyframe": anchors.keyframe,
        }
        if anchors.with_features:
            tensors["anchors.features"] = anchors.features
        if anchors.with_colours:
            tensors["anchors.colours"] = anchors.colours
        if model.encoding is not None:
            tensors["encoding.table"] = model.encoding.table
        tensors.update({f"decoders.{name}": value for name, value in model.decoders.state_dict().items()})
        tensors.update({f"octree.{name}": value for name, value in model.octree.state_dict().items()})
        tensors["trajectory.camera_position_sum"] = model.camera_position_sum
        tensors["trajectory.camera_positions"] = torch.tensor([model.camera_positions], dtype=torch.int64)
        tensors.update(_keyframe_pose_tensors(keyframes))
        tensors = {name: value.detach().clone() for name, value in tensors.items()}
        if training_state:
            tensors.update(training.capture(optimisation(model, keyframes)))
        return MapState(model.config, tensors, model.frames, model.iterations)


def _keyframe_pose_tensors(keyframes: KeyframeSet) -> dict[str, torch.Tensor]:
    """The keyframes' client and refined poses, so a snapshot keeps what refinement found and the path its
    camera took (a map loaded from it does not read them back: they describe its making, not the map; a
    viewer reads them with ``keyframe_path``)."""
    poses = keyframe_poses(keyframes)
    return {
        "poses.keyframe_indices": training.frame_indices_as_int64([pose.index for pose in poses]),
        "poses.client_c2w": torch.from_numpy(np.array([pose.client_c2w for pose in poses]).reshape(-1, 4, 4)),
        "poses.refined_c2w": torch.from_numpy(np.array([pose.refined_c2w for pose in poses]).reshape(-1, 4, 4)),
    }


def keyframe_path(state: MapState) -> np.ndarray:
    """The keyframes' refined camera-to-world poses (n, 4, 4) that ``state`` records, in mapping order: none
    for a state written before every snapshot kept them. ValueError for poses that are not finite 4x4s."""
    poses = state.tensors.get("poses.refined_c2w")
    if poses is None:
        return np.zeros((0, 4, 4))
    if poses.dim() != 3 or tuple(poses.shape[1:]) != (4, 4) or not bool(torch.isfinite(poses).all()):
        raise ValueError(f"poses.refined_c2w must hold finite 4x4 poses, not shape {tuple(poses.shape)}")
    return poses.double().cpu().numpy()


def recorded_keyframe_poses(state: MapState) -> list[KeyframePose]:
    """The keyframes' frame indices, client and refined poses that ``state`` records, in mapping order: none for a
    state written before snapshots kept them. ValueError for records that disagree or are not finite 4x4s."""
    refined = keyframe_path(state)
    client, indices = state.tensors.get("poses.client_c2w"), state.tensors.get("poses.keyframe_indices")
    if client is None or indices is None:
        return []
    client = client.double().cpu().numpy()
    if client.shape != refined.shape or indices.shape != (len(refined),) or not np.isfinite(client).all():
        raise ValueError(f"poses.client_c2w {tuple(client.shape)} and poses.keyframe_indices "
                         f"{tuple(indices.shape)} must match poses.refined_c2w {tuple(refined.shape)}")
    return [KeyframePose(index, client[i], refined[i], False)
            for i, index in enumerate(training.frame_indices_from_int64(indices))]


def load(model: MapModel, keyframes: KeyframeSet, state: MapState, training_state: bool) -> None:
    """Fill the empty ``model`` (built from ``state.config``) with ``state``'s map and counters, and with
    ``training_state`` ``keyframes`` and the optimisers with its training state. ValueError when the
    tensors do not fit the config."""
    try:
        _load_map(model, state)
        if training_state:
            model.drawn.post(training.restore(optimisation(model, keyframes), state.tensors) or 0)
        else:  # the keyframes its anchors belonged to are not loaded: a correction of a new keyframe moves none
            model.anchors.keyframe = torch.full_like(model.anchors.keyframe, -1)
    except (KeyError, RuntimeError, ValueError) as error:
        raise ValueError(f"map state does not match its config: {error}") from error
    model.frames = state.frames
    model.iterations = state.iterations


def _load_map(model: MapModel, state: MapState) -> None:
    if state.tensors["anchors.codes"].numel() and resolution.reshape_pending(state.config):
        raise ValueError("a map with anchors holds resolution rules still to resolve that would rebuild its model")
    model.octree.load_state_dict(state.section("octree"))
    model.octree.device = model.device
    model.decoders.load_state_dict(state.section("decoders"))
    anchors = model.anchors
    count = state.tensors["anchors.codes"].numel()
    n_offsets, feature_dim = anchors.n_offsets, anchors.feature_dim
    tensor = checked_shapes(state.tensors, {
        "anchors.codes": (count,), "anchors.levels": (count,), "anchors.log_scales": (count, 3),
        "anchors.offsets": (count, n_offsets, 3), "anchors.spawned": (count, n_offsets),
        "anchors.observations": (count,),
        **({"anchors.features": (count, feature_dim)} if anchors.with_features else {}),
        **({"encoding.table": tuple(model.encoding.table.shape)} if model.encoding is not None else {}),
    }, model.device)
    if model.encoding is not None:
        model.encoding.table.data.copy_(tensor["encoding.table"])
    codes, levels = tensor["anchors.codes"], tensor["anchors.levels"]
    features = tensor["anchors.features"] if anchors.with_features else None
    # Snapshots written before anchors had colours hold none: theirs start at zero (the decoder's colour).
    colours = (checked_shapes(state.tensors, {"anchors.colours": (count, 3)}, model.device)["anchors.colours"]
               if anchors.with_colours and "anchors.colours" in state.tensors else None)
    # Snapshots written before anchors kept their centres and keyframes hold neither: their anchors sit at
    # their cells' centres (no correction could have moved them) and belong to no keyframe.
    kept = {name: shape for name, shape in (("anchors.positions", (count, 3)), ("anchors.keyframe", (count,)))
            if name in state.tensors}
    extra = checked_shapes(state.tensors, kept, model.device)
    positions = extra.get("anchors.positions")
    if positions is None:
        positions = model.octree.centers_by_level(codes, levels)
    elif not bool(torch.isfinite(positions).all()):
        raise ValueError("anchors.positions must be finite")
    anchors.add(codes, levels, positions, torch.ones(count, device=model.device), features, model.optimizer, colours,
                extra.get("anchors.keyframe", -1))
    anchors.log_scales.data.copy_(tensor["anchors.log_scales"])
    anchors.offsets.data.copy_(tensor["anchors.offsets"])
    anchors.spawned = tensor["anchors.spawned"].bool()
    anchors.observations = tensor["anchors.observations"]
    if "trajectory.camera_position_sum" in state.tensors:  # absent in snapshots written before it was kept
        trajectory = checked_shapes(
            state.tensors, {"trajectory.camera_position_sum": (3,), "trajectory.camera_positions": (1,)}, "cpu"
        )
        position_sum = trajectory["trajectory.camera_position_sum"].double()
        positions = int(trajectory["trajectory.camera_positions"][0])
        if not bool(torch.isfinite(position_sum).all()) or positions < 0:
            raise ValueError("trajectory: the camera position sum must be finite and the count non-negative")
        model.camera_position_sum, model.camera_positions = position_sum, positions


def checked_shapes(
    tensors: dict[str, torch.Tensor], shapes: dict[str, tuple[int, ...]], device: torch.device | str
) -> dict[str, torch.Tensor]:
    """The named tensors on ``device``, each exactly of its shape: a copy into a parameter would
    otherwise broadcast a tensor that is too small."""
    checked = {}
    for name, shape in shapes.items():
        value = tensors[name]
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(value.shape)}, expected {shape}")
        checked[name] = value.to(device)
    return checked
