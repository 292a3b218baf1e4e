"""Write the compatibility fixture: a recording, a snapshot and renders made by a real server.

Run once, at commit 03e848c, with ``.venv/bin/python tests/compat/make_fixture.py``;
``tests/service/test_compatibility.py`` checks that today's code still loads the snapshot and
replays the recording to the same images. Do not re-run it to make a failing check pass: the files
are the record of what older code wrote.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path[:0] = [str(REPO / "tests")]

from ogapi.v1 import mapping_pb2 as pb  # noqa: E402
from ogclient.connection import SessionRef, connect  # noqa: E402
from ogclient.evaluation import render, snapshot_bytes  # noqa: E402
from ogclient.local_server import LocalServer  # noqa: E402
from ogclient.streaming import stream_frames  # noqa: E402
from service.scene import PRESET, TEST_SERVER_CONFIG, TINY, messages, scene  # noqa: E402

HELD_OUT = 5  # a pose the session never saw


def main() -> None:
    frames = scene()
    with tempfile.TemporaryDirectory() as record_dir, LocalServer(
        record_dir, "--config", str(TEST_SERVER_CONFIG), "--device", "cpu"
    ) as server:
        channel, stub = connect(server.address, timeout=60.0)
        with channel:
            credentials = stub.CreateSession(pb.CreateSessionRequest(preset=PRESET, overrides=TINY, label="compat"))
            session = SessionRef.from_credentials(credentials)
            result = stream_frames(stub, session, messages(frames), progress=False)
            assert not result.rejected, result.summary()
            truth = frames.load(HELD_OUT)
            rendered = render(stub, session, truth.c2w, truth.color_intrinsics)
            (HERE / "snapshot.safetensors").write_bytes(snapshot_bytes(stub, session))
            closed = stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                       metadata=session.metadata())
            shutil.copy(Path(record_dir) / closed.recording, HERE / "recording.mcap")
    k = truth.color_intrinsics
    save_file({
        "color": rendered.color, "depth": rendered.depth, "c2w": truth.c2w.astype(np.float64),
        "intrinsics": np.array([k.fx, k.fy, k.cx, k.cy, k.width, k.height], dtype=np.float64),
    }, HERE / "render.safetensors", metadata={"made_at": "03e848c", "position": str(HELD_OUT)})
    print(result.summary())


if __name__ == "__main__":
    main()
