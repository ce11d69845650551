"""``polarstripe render --orders``: meta.json says which orders were modelled and the error to expect."""

import json
import subprocess
import sys


def _run(*args):
    return subprocess.run([sys.executable, "-m", "polarstripe", "render", *args], capture_output=True,
                          text=True, timeout=180)


def test_meta_json_records_the_orders_and_the_expected_error(tmp_path):
    for orders in ("all", "single"):
        out = tmp_path / orders
        r = _run("--orders", orders, "--fidelity", "preview", "--resolution", "48x36", "-o", str(out))
        assert r.returncode == 0, r.stderr
        meta = json.loads((out / "meta.json").read_text())
        o = meta["orders"]
        assert o["requested"] == orders and 0 < o["single_scattering_error"] < 1
        if orders == "all":
            assert o["modelled"] == "all orders" and o["expected_error"] == 0.25
            assert 0 < o["similarity"]["f"] < 1 and o["terms"]
            assert meta["fidelity"]["higher"]["cells"] == 10
        else:
            assert o["modelled"] == "single scattering" and "similarity" not in o
        assert "all orders" in r.stdout or "single scattering" in r.stdout


def test_clear_water_skips_the_higher_orders(tmp_path):
    scene = tmp_path / "clear.toml"
    scene.write_text("[medium]\nsigma_t = 0.01\nalbedo = 0.3\n")
    r = _run(str(scene), "--resolution", "32x24", "--fidelity", "preview", "-o", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    o = json.loads((tmp_path / "o" / "meta.json").read_text())["orders"]
    assert o["requested"] == "all" and o["modelled"] == "single scattering" and o["expected_error"] < 0.01


def test_bad_orders_is_one_line(tmp_path):
    r = _run("--orders", "double", "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "--orders" in r.stderr
