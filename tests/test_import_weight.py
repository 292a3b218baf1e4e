"""The client and the API package stay light: no torch for the client, no engine for ``ogapi``.

Loading torch costs a client command about a second; ``ogapi`` is the language-neutral API and
must not depend on the engine. Each check runs in a fresh interpreter (with this one's
environment, PYTHONPATH included), since this one has long loaded torch for other tests.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

NO_TORCH = "assert 'torch' not in sys.modules, sorted(m for m in sys.modules if m.startswith('ogmapping'))"

CHECKS = {
    "client": f"import ogclient.__main__, ogclient.commands, ogclient.demo, sys; {NO_TORCH}",
    "engine's torch-free modules": (
        "import ogmapping.config, ogmapping.datasets, ogmapping.frames.camera, ogmapping.frames.frame, "
        "ogmapping.frames.preprocess, ogmapping.frames.rotation, ogmapping.frames.selection, ogmapping.cli.options, "
        "ogmapping.frames.trajectory, "
        "ogmapping.quality.evaluation, "
        f"sys; {NO_TORCH}"
    ),
    "streaming a dataset": (
        "import sys\n"
        "from ogclient.messages import frame_to_proto\n"
        "from ogmapping.config import resolve\n"
        "from ogmapping.quality.evaluation import open_frames\n"
        "frames = open_frames('synthetic', 'synthetic', '0:3', scale=0.25)\n"
        "frame_to_proto(frames.load(frames.selection.streamed[0]))\n"
        "resolve('sparse', overrides={'keyframes.iterations': '3'})\n"
        f"{NO_TORCH}"
    ),
    "reading a ROS bag": f"import ogmapping.datasets.rosbag.source, sys; {NO_TORCH}",
    "ogapi": (
        "import ogapi, ogapi.convert, ogapi.images, ogapi.recording, sys; "
        "engine = [m for m in sys.modules if m.startswith('ogmapping')]; assert not engine, engine"
    ),
}


@pytest.mark.parametrize("code", CHECKS.values(), ids=CHECKS.keys())
def test_import_stays_light(code: str) -> None:
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
