"""Export the decoded Gaussians as Niantic's SPZ (gzip, version 3), which Spark and SuperSplat read,
through gsply (the ``spz`` extra): a quarter of the .ply's size on the demo's map (15,087 Gaussians:
244,695 bytes against 1,026,331).

SPZ keeps its quantisation to itself: positions in 24-bit fixed point (1/4096 m with 12 fractional bits),
opacity and colour in 8 bits (colour as 0.15 x the SH DC coefficient), log-scales in 1/16 steps and
rotations as the smallest three of the quaternion. Its axes are right-up-back (RUB, three.js's), where a
3DGS .ply's are taken as right-down-front (RDF): the export turns the map's coordinates by 180 degrees about
x, as Niantic's own converter does for a .ply, so its tools and the viewers that follow them show the .spz
where they show ``ogmap export``'s .ply.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ogmapping.model.gaussians import GaussianSet
from ogmapping.persist.export import splat_arrays

FRACTIONAL_BITS = 12
RDF_TO_RUB = np.array([1.0, -1.0, -1.0], dtype=np.float32)  # a half turn about x: y and z negated


def write_spz(gaussians: GaussianSet, path: str | Path) -> int:
    """Write ``gaussians`` to ``path`` as SPZ; returns how many. ValueError without the gsply package."""
    try:
        from gsply import write_spz as write
        from gsply.gsdata import GSData
    except ImportError as error:
        raise ValueError(f"--format spz needs the gsply package: pip install 'ogmapping[spz]' ({error})") from None
    splats = splat_arrays(gaussians)
    quats = splats.quats.copy()
    quats[:, 2:] *= -1  # the same half turn on each rotation: (w, x, -y, -z)
    count = splats.means.shape[0]
    data = GSData(means=splats.means * RDF_TO_RUB, scales=splats.log_scales, quats=quats,
                  opacities=splats.logit_opacities, sh0=splats.sh_dc, shN=np.zeros((count, 0, 3), dtype=np.float32))
    write(str(path), data, version=3, fractional_bits=FRACTIONAL_BITS)
    return count
