"""Reading TensorBoard event files back in tests: the TFRecord framing (CRC-checked) parsed into tensorboardX's own
Event proto, so nothing beyond the `tb` extra is needed."""

from __future__ import annotations

import struct
from collections import defaultdict
from pathlib import Path

Scalars = dict[str, list[tuple[int, float]]]


def read_event_file(path: Path) -> Scalars:
    """tag -> [(step, value)] of one event file, in file order; every record's length and data CRC checked (a record
    still being written at the end of the file is left out)."""
    from tensorboardX.proto.event_pb2 import Event
    from tensorboardX.record_writer import masked_crc32c

    data, pos = path.read_bytes(), 0
    out: Scalars = defaultdict(list)
    while pos + 12 <= len(data):
        header = data[pos:pos + 8]
        (length,) = struct.unpack("<Q", header)
        (header_crc,) = struct.unpack("<I", data[pos + 8:pos + 12])
        if pos + 16 + length > len(data):
            break
        body = data[pos + 12:pos + 12 + length]
        (body_crc,) = struct.unpack("<I", data[pos + 12 + length:pos + 16 + length])
        assert header_crc == masked_crc32c(header) and body_crc == masked_crc32c(body), f"corrupt record in {path}"
        pos += 16 + length
        event = Event.FromString(body)
        for value in event.summary.value:
            out[value.tag].append((event.step, value.simple_value))
    return dict(out)


def read_board(run_dir: Path) -> dict[str, Scalars]:
    """worker -> its scalars (each worker's folder holds exactly one event file)."""
    board = {}
    for folder in sorted((run_dir / "tensorboard").iterdir()):
        [events] = list(folder.glob("events.out.tfevents.*"))
        board[folder.name] = read_event_file(events)
    return board
