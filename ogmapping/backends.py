"""The rasterizer backends' names, in a module that imports nothing of the project.

``ogmapping.config`` types ``backend`` with them and must stay importable without torch (the
client imports it); ``ogmapping.render`` dispatches on them and must not import engine modules
above it, and ``ogmapping/render/`` itself cannot hold them because importing any module there
runs ``render/__init__`` (torch). A leaf of the package is the one place both may import.
"""

from typing import Literal, get_args

RasterizerBackend = Literal["torch", "cpu", "gsplat"]
BACKENDS: tuple[str, ...] = get_args(RasterizerBackend)
