"""The ``polarstripe render`` command: its files, and one-line errors for user mistakes."""

import json
import subprocess
import sys

import cv2
import numpy as np


def _run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "polarstripe", "render", *args], capture_output=True,
                          text=True, timeout=120, cwd=cwd)


def test_render_writes_image_meta_and_components(tmp_path):
    out = tmp_path / "out"
    r = _run("--pattern", "stripe:14/30", "--polarizer", "90", "--fidelity", "preview", "--components",
             "--resolution", "64x48", "-o", str(out))
    assert r.returncode == 0, r.stderr
    img = cv2.imread(str(out / "image.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint16 and img.shape == (48, 64) and img.max() <= 4095
    meta = json.loads((out / "meta.json").read_text())
    assert meta["pattern"] == "stripe:14/30" and meta["fidelity"]["name"] == "preview" and meta["seconds"] > 0
    assert meta["scene"]["camera"]["resolution"] == [64, 48]
    for name in "DAB":
        arr = np.load(out / f"{name}.npy")
        assert arr.dtype == np.float64 and arr.shape == (48, 64) and np.isfinite(arr).all()
    assert np.load(out / "D.npy").max() > 0 and np.load(out / "B.npy").max() > 0


def test_threads_give_the_same_frame_and_a_bad_count_is_one_line(tmp_path):
    arrays = []
    for n in ("1", "2"):
        out = tmp_path / n
        r = _run("--pattern", "stripe:3/8", "--fidelity", "standard", "--components", "--resolution", "96x72",
                 "--threads", n, "-o", str(out))
        assert r.returncode == 0, r.stderr
        assert json.loads((out / "meta.json").read_text())["threads"] == int(n)
        arrays.append([np.load(out / f"{name}.npy") for name in "DAB"])
    assert all(np.array_equal(a, b) for a, b in zip(*arrays, strict=True))
    r = _run("--threads", "-2", "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "--threads must be >= 0" in r.stderr


def test_bad_pattern_is_one_line(tmp_path):
    r = _run("--pattern", "stripes:3", "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0 and "pattern 'stripes:3'" in r.stderr


def test_unreadable_scene_is_one_line(tmp_path):
    r = _run(str(tmp_path / "missing.toml"), "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "missing.toml" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"\xff\xfe[medium")
    r = _run(str(bad), "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0
