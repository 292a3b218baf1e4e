"""Export the decoded Gaussians as a standard 3DGS ``.ply`` (binary little-endian).

Colours and opacities depend on the viewpoint through the decoders, so the export decodes every
anchor as seen from one camera position (by default the centroid of the map's keyframe poses).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ogmapping.gaussians import generate

SH_C0 = 0.28209479177387814  # zeroth spherical-harmonic basis constant, 3DGS's colour encoding


def export_ply(mapper, path: str | Path, camera_center: np.ndarray | None = None) -> int:
    """Write the map's Gaussians to ``path``; returns how many were written."""
    with mapper.lock, torch.no_grad():
        if camera_center is None:
            poses = [kf.c2w[:3, 3] for kf in mapper.keyframes.keyframes]
            center = torch.stack(poses).mean(0) if poses else mapper.anchors.positions.mean(0)
        else:
            center = torch.as_tensor(camera_center, dtype=torch.float32, device=mapper.device)
        rows = torch.arange(len(mapper.anchors), device=mapper.device)
        gaussians = generate(mapper.anchors, mapper._features, mapper.decoders, center, rows,
                             compiled=mapper.profile.compiled)
    means = gaussians.means.cpu().numpy().astype(np.float32)
    count = means.shape[0]
    opacity = gaussians.opacities.clamp(1e-6, 1 - 1e-6).cpu().numpy()
    quats = torch.nn.functional.normalize(gaussians.quats, dim=-1).cpu().numpy()
    columns = {
        "x": means[:, 0], "y": means[:, 1], "z": means[:, 2],
        "nx": np.zeros(count), "ny": np.zeros(count), "nz": np.zeros(count),
        "f_dc_0": None, "f_dc_1": None, "f_dc_2": None,
        "opacity": np.log(opacity / (1 - opacity)),
        "scale_0": None, "scale_1": None, "scale_2": None,
        "rot_0": quats[:, 0], "rot_1": quats[:, 1], "rot_2": quats[:, 2], "rot_3": quats[:, 3],
    }
    colors = (gaussians.colors.cpu().numpy() - 0.5) / SH_C0
    log_scales = np.log(np.maximum(gaussians.scales.cpu().numpy(), 1e-12))
    for axis in range(3):
        columns[f"f_dc_{axis}"] = colors[:, axis]
        columns[f"scale_{axis}"] = log_scales[:, axis]
    table = np.zeros(count, dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        table[name] = values
    header = "ply\nformat binary_little_endian 1.0\n" f"element vertex {count}\n"
    header += "".join(f"property float {name}\n" for name in columns) + "end_header\n"
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(table.tobytes())
    return count
