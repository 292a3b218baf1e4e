"""``ogclient view REC.mcap`` maps a recording's frames (minutes for a long one) behind a progress bar: the
child's bar, redrawn with carriage returns, reaches the terminal as it is drawn."""

from __future__ import annotations

import io
import os
import subprocess
import sys

from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogclient.streaming import stream_frames
from ogclient.viewing import segments

from .inprocess import serving, settings
from .scene import TINY, create_request, messages, scene


def test_segments_end_at_carriage_returns_and_newlines() -> None:
    text = "bar  0%\rbar 50%\rbar 100%\ndone\nogserver view: no such file"
    assert list(segments(io.StringIO(text))) == ["bar  0%\r", "bar 50%\r", "bar 100%\n", "done\n",
                                                 "ogserver view: no such file"]


def test_ogclient_view_of_a_recording_shows_a_progress_bar(tmp_path) -> None:
    with serving(settings(tmp_path)) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        stream_frames(running.stub, session, messages(scene())[:3], None, False)
        closed = running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                           metadata=session.metadata())
        recording = running.record_dir / closed.recording
    process = subprocess.Popen([sys.executable, "-m", "ogclient", "view", str(recording), "--device", "cpu"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE,  # bytes: carriage returns kept
                               env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert process.stdout.readline().decode().startswith("mapping the 3 recorded frames of ")
        assert process.stdout.readline().decode().startswith(f"web view of {recording.name} on http://127.0.0.1:")
        process.terminate()
        assert process.wait(10) == 0
        bar = process.stderr.read().decode()
        assert "mapping the recording:   0%" in bar and "\r" in bar
        assert "mapping the recording: 100%|" in bar and "3/3" in bar
    finally:
        process.kill()
        process.wait()
