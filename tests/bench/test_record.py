"""``polarstripe bench record`` on tiny frames: the in-process rows, the plain write of the payload's bytes,
and one recorder over the bus (bench/record_bus.py, its own process) that writes every frame."""

import json

import pytest
from polarstripe.bench.record import _frames
from polarstripe.bench.record_bus import over_bus
from polarstripe.msgs import pack
from polarstripe.tools.cli import main


def test_bench_record_in_process_rows(capsys):
    assert main(["bench", "record", "--frames", "4", "--width", "64", "--height", "48", "--repeats", "1",
                 "--cold-pause", "0", "--no-export", "--no-bus", "--chunk-size", "16K", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = doc["rows"]
    assert doc["chunk_size"] == 16384 and len(rows) == 6
    payload = 1e6 * doc["payload_MB"]
    assert rows["plain write (warm)"]["bytes"] == rows["plain write (cold)"]["bytes"] == payload


@pytest.mark.parametrize("transport", ["zmq", "shm"])
def test_the_recorder_over_the_bus_writes_every_frame(tmp_path, transport):
    frames = _frames(5, 256, 320)  # 160 kB: through a ring slot with shm
    calls = []
    row = over_bus(tmp_path, frames, lambda: calls.append(1), recorder_args=("--queue", "2"),
                   transport=transport)
    assert calls == [1] and row["recorded"] == row["sent"] == 5 and row["gaps"] == 0
    assert row["transport"] == transport  # as the bag's recording metadata says
    assert row["bytes"] > sum(len(pack(f)) for f in frames)
    assert 0.0 <= row["cpu_recorder_s"] < 60.0   # the process clock ticks at 10 ms: 5 small frames may read 0
