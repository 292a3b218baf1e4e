"""What crash safety costs a session: a checkpoint's write, the recording's flush per frame, a resume.

Maps a sequence in-process as a session's worker would (record the frame, map it, a checkpoint every
``--interval`` frames) and times each part; then resumes from the last checkpoint as a restarted
server would (read it, rebuild the mapper, copy the cut recording). The flush figure compares the
recorder as it runs (a complete MCAP chunk flushed to the OS before each frame is mapped) with the
same frames written by a plain MCAP writer that buffers 1 MiB chunks (what acknowledged frames would
risk without the flush).

    python bench/checkpoints.py --data ../shared/data/7scenes-redkitchen --frames 0:60 --scale 0.5
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import tempfile
import time
from pathlib import Path

from mcap.writer import CompressionType, Writer
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.access import tokens
from ogserver.recording import checkpoint
from ogserver.recording.checkpoint import Identity, Position
from ogserver.recording.recorder import Recorder, _Channels, frame_record

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--frames", default="0:60")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--preset", default="sparse")
    parser.add_argument("--interval", type=int, default=20, help="frames between checkpoints")
    args = parser.parse_args()

    frames = open_frames(args.data, "auto", args.frames, 1, args.scale)
    mapper = Mapper(resolve(args.preset), "cpu")
    config = pb.SessionConfig(session_id="b" * 32, preset=args.preset, config_json=json.dumps(mapper.config.to_dict()))
    identity = Identity("bench", tokens.TokenHash.of(tokens.new_token()), config)
    directory = Path(tempfile.mkdtemp(prefix="ogbench-"))
    recorder = Recorder(directory / f"{config.session_id}.mcap", config)
    checkpoints = checkpoint.Checkpoints(recorder.path, identity, args.interval)
    records, mapping, flushing, taken = [], [], [], []
    for sequence, position in enumerate(frames.selection.streamed, 1):
        frame = frames.load(position)
        record = frame_record(frame_to_proto(frame), frame, time.time_ns())
        records.append(record)
        start = time.perf_counter()
        recorder.write_frame(record)
        flushing.append(time.perf_counter() - start)
        start = time.perf_counter()
        mapper.process(frame)
        mapping.append(time.perf_counter() - start)
        if checkpoints.due(sequence):
            start = time.perf_counter()
            state = mapper.state(training_state=True)
            captured = time.perf_counter() - start
            data = checkpoint.encode(identity, Position(sequence, frame.index), state)
            encoded = time.perf_counter() - start
            checkpoint.write_atomically(checkpoints.path, data)
            taken.append({"sequence": sequence, "keyframes": len(mapper.keyframes),
                          "anchors": len(mapper.model.anchors),
                          "bytes": len(data), "capture_s": captured, "encode_s": encoded - captured,
                          "write_fsync_s": time.perf_counter() - start - encoded,
                          "total_s": time.perf_counter() - start})

    buffered = io.BytesIO()
    writer = Writer(buffered, compression=CompressionType.ZSTD)
    writer.start(profile="protobuf", library="bench")
    channels = _Channels(writer)
    start = time.perf_counter()
    for record in records:
        for topic, view in record.views:
            channels.add(topic, view, record.received_ns, record.sensor_ns)
    writer.finish()
    unflushed = (time.perf_counter() - start) / len(records)

    start = time.perf_counter()
    saved = checkpoint.read(checkpoints.path)
    Mapper.from_state(saved.state, "cpu", training_state=True)
    restore_s = time.perf_counter() - start
    recording_bytes = recorder.path.stat().st_size
    start = time.perf_counter()
    Recorder.resume(recorder.path).close()
    copy_s = time.perf_counter() - start

    print(json.dumps({
        "frames": len(records), "map_s_per_frame_mean": statistics.mean(mapping),
        "record_flush_s_per_frame_mean": statistics.mean(flushing), "record_buffered_s_per_frame": unflushed,
        "recording_bytes_flushed": recording_bytes, "recording_bytes_buffered": len(buffered.getvalue()),
        "checkpoints": taken, "resume_read_and_rebuild_s": restore_s, "resume_recording_copy_s": copy_s,
    }, indent=2))


if __name__ == "__main__":
    main()
