"""``polarstripe bag info|recover`` (tools/bag_cli.py): what info reports (the recorder's gaps, a type this
build does not know, an empty bag, several files, JSON), what recover prints, and its argument errors. Run in
process through ``polarstripe.tools.cli.main``; tests/runtime/test_bag.py runs the subprocess paths."""

from __future__ import annotations

import json

import numpy as np
import pytest
from polarstripe.msgs import Frame, Header, Log, json_schema, pack
from polarstripe.runtime.bag import BagWriter
from polarstripe.tools.bag_cli import info
from polarstripe.tools.cli import main


def _frame(seq: int) -> Frame:
    return Frame(image=np.full((4, 6), seq, np.uint16), exposure_s=0.01, step=seq,
                 header=Header(stamp_ns=1_700_000_000 * 10**9 + seq, seq=seq))


T0 = 1_700_000_000 * 10**9


def _bag(path, *, recording: dict | str | None = None, seqs=(0, 1, 2, 5), ghost=False):
    with BagWriter(path) as w:
        w.add_metadata("launch", {"launch": "sim", "namespace": "/rig"})
        w.add_metadata("versions", {"polarstripe": "9.9.9"})
        for k, seq in enumerate(seqs):  # 10 Hz
            w.add_message("/rig/camera/frame", _frame(seq), log_time_ns=1_700_000_000 * 10**9 + k * 10**8)
        w.add_message("/rig/log", Log(level="INFO", node="x", text="hi", header=Header(stamp_ns=1)),
                      log_time_ns=1_700_000_000 * 10**9)
        if ghost:
            schema = json_schema(Log)
            schema["properties"]["type"]["const"] = "ghost"
            cid = w.register("/rig/ghost", "polarstripe/ghost", json.dumps(schema).encode(), {})
            w.add_payload(cid, [pack(Log(level="INFO", node="g", text="boo"))], log_time_ns=T0,
                          publish_time_ns=0, sequence=0)
        if recording is not None:
            topics = recording if isinstance(recording, str) else json.dumps(recording)
            w.add_metadata("recording", {"topics": topics, "gaps": "7"})
    return path


def test_info_reports_counts_rates_and_the_recorders_gaps(tmp_path):
    d = info(_bag(tmp_path / "a.mcap", recording={"/rig/camera/frame": {"gaps": 7, "messages": 4}}))
    frame = d["topics"]["/rig/camera/frame"]
    got = (frame["type"], frame["version"], frame["known"], frame["messages"])
    assert got == ("frame", Frame.VERSION, True, 4)
    assert frame["rate_hz"] == pytest.approx(10.0)
    assert frame["gaps"] == 7 and d["topics"]["/rig/log"]["gaps"] is None  # not in the recorder's report
    assert (d["messages"], d["launch"], d["polarstripe"], d["compression"]) == (5, "sim", "9.9.9", ["none"])
    assert d["duration_s"] == pytest.approx(0.3)
    assert "decoded" not in d and "sequence_gaps" not in frame


def test_info_scan_decodes_and_counts_sequence_gaps(tmp_path):
    d = info(_bag(tmp_path / "a.mcap", ghost=True), scan=True)
    assert d["decoded"] == 5  # the unknown type's message is not decoded
    assert d["topics"]["/rig/camera/frame"]["sequence_gaps"] == 2  # seq 2 -> 5
    assert d["topics"]["/rig/ghost"]["known"] is False


def test_info_survives_a_recording_report_that_is_not_json(tmp_path):
    d = info(_bag(tmp_path / "a.mcap", recording="{not json"))
    assert d["topics"]["/rig/camera/frame"]["gaps"] is None


def test_info_table(tmp_path, capsys):
    path = _bag(tmp_path / "a.mcap", recording={"/rig/camera/frame": {"gaps": 7}}, ghost=True)
    assert main(["bag", "info", "--scan", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"file:        {path} (") and "1 chunks, compression none)" in out[0]
    assert out[1].startswith("recorded:    2023-11-")  # T0, local time
    assert out[1].endswith(", 0.300 s, 6 messages, launch 'sim', polarstripe 9.9.9")
    assert out[2] == "decoded:     5 messages, every one valid"
    rows = {line.split()[0]: line.split()[1:] for line in out[4:]}
    assert rows["/rig/camera/frame"] == ["frame", f"v{Frame.VERSION}", "4", "10.00", "7", "2"]
    assert rows["/rig/log"] == ["log", "v1", "1", "0.00", "-", "0"]
    assert rows["/rig/ghost"][:3] == ["ghost", "v1", "(?)"]


def test_info_of_several_files_as_json_lines(tmp_path, capsys):
    a, b = _bag(tmp_path / "a.mcap"), _bag(tmp_path / "b.mcap", seqs=(0,))
    assert main(["bag", "info", "--json", str(a), str(b)]) == 0
    lines = capsys.readouterr().out.splitlines()
    docs = [json.loads(line) for line in lines]
    assert [d["file"] for d in docs] == [str(a), str(b)]
    assert [d["topics"]["/rig/camera/frame"]["messages"] for d in docs] == [4, 1]


def test_info_of_an_empty_bag(tmp_path, capsys):
    with BagWriter(tmp_path / "empty.mcap"):
        pass
    assert main(["bag", "info", str(tmp_path / "empty.mcap"), str(tmp_path / "empty.mcap")]) == 0
    out = capsys.readouterr().out
    assert out.count("topics:      none") == 2 and "recorded:    -, 0.000 s, 0 messages" in out
    assert "\n\nfile:" in out  # files are separated by a blank line


def test_a_bad_file_among_good_ones_is_one_error_line(tmp_path, capsys):
    good = _bag(tmp_path / "a.mcap")
    (tmp_path / "bad.mcap").write_text("not a bag")
    assert main(["bag", "info", str(good), str(tmp_path / "bad.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [f"polarstripe bag: error: bag {tmp_path / 'bad.mcap'}: not an MCAP "
                                        "file (starts with b'not a ba')"]


def test_recover_of_a_complete_bag_says_so(tmp_path, capsys):
    src = _bag(tmp_path / "a.mcap")
    assert main(["bag", "recover", str(src), "-o", str(tmp_path / "b.mcap"), "--compression", "lz4"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"recovered 5 messages in 1 chunks to {tmp_path / 'b.mcap'}; the input was complete",
                   "  /rig/camera/frame: 4", "  /rig/log: 1"]
    assert info(tmp_path / "b.mcap")["compression"] == ["lz4"]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["bag"], "the following arguments are required: ACTION"),
        (["bag", "info"], "the following arguments are required: FILE"),
        (["bag", "recover", "x.mcap"], "the following arguments are required: -o/--output"),
        (["bag", "recover", "x.mcap", "-o", "y.mcap", "--compression", "gzip"], "invalid choice: 'gzip'"),
    ],
)
def test_argument_errors_are_usage_errors(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and needle in capsys.readouterr().err


def test_recover_of_a_missing_file_is_one_line(tmp_path, capsys):
    assert main(["bag", "recover", str(tmp_path / "nope.mcap"), "-o", str(tmp_path / "out.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("polarstripe bag: error: ") and "nope.mcap" in err[0]
