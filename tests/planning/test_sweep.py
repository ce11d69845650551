"""Design-study sweeps: the spec's checks, the table, local == Dask, worker deaths and Ctrl-C."""

import math
import os
import subprocess
import sys
from pathlib import Path

import cloudpickle
import numpy as np
import pytest
from polarstripe.planning.planner import SceneModel, plan
from polarstripe.planning.sweep import SceneJob, curve_columns, read_table, run_sweep, table_rows, write_table
from polarstripe.planning.sweep_spec import SweepSpecError, load_spec, parse_spec, scene_for
from polarstripe.sim.scene import SceneError

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake evaluators below run in workers

SMALL = {"fidelity": "preview", "grid": {"separation": {"min": 0.02, "max": 0.3, "n": 4},
                                          "sigma_t": [3.0, 7.0], "stripes": [8]}}


def _spec(**over):
    data = {**SMALL, **over}
    return parse_spec(data)


@pytest.mark.parametrize("data,match", [
    ({"colour": 1}, "unknown key 'colour'"),
    ({"grid": {"sigma_tt": [5.0]}}, "unknown key grid.sigma_tt"),
    ({"grid": {"sigma_t": {"min": 1.0, "max": 2.0, "n": 3, "step": 1}}}, "unknown key grid.sigma_t.step"),
    ({"grid": {"sigma_t": [5.0, float("nan")]}}, r"grid.sigma_t\[1\] must be a finite number"),
    ({"grid": {"albedo": []}}, "grid.albedo: empty range"),
    ({"grid": {"sigma_t": {"min": 9.0, "max": 2.0, "n": 4}}}, "grid.sigma_t: empty range"),
    ({"grid": {"separation": {"min": 0.01, "max": 0.6, "n": 10}}}, "0.6 m is beyond the tank"),
    ({"grid": {"sigma_t": {"min": 1.0, "max": 9.0, "n": 101}, "albedo": {"min": 0.5, "max": 1.0, "n": 100}}},
     "10100 scenes .* exceed max_scenes = 10000"),
    ({"grid": {"sigma_t": [-1.0]}}, "grid.sigma_t = -1.0: medium.sigma_t must be >= 0"),
    ({"grid": {"mean_cosine": [1.5]}}, "grid.mean_cosine = 1.5"),
    ({"grid": {"stripes": [2.5]}}, r"grid.stripes\[0\] must be a positive integer"),
    ({"grid": {"exposure": ["sometimes"]}}, r"grid.exposure\[0\] must be a number"),
    ({"modalities": ["laser"]}, "modalities"),
    ({"max_scenes": 0}, "max_scenes"),
    ({"orders": "double"}, "orders must be one of all, single"),
])
def test_bad_specs_fail_before_anything_runs(data, match):
    with pytest.raises(SweepSpecError, match=match):
        parse_spec(data)


def test_a_bad_scene_fails_with_its_key(tmp_path):
    (tmp_path / "scene.toml").write_text("[medium]\nsigmat = 5\n")
    (tmp_path / "spec.toml").write_text('scene = "scene.toml"\n')
    with pytest.raises(SceneError, match="unknown key medium.sigmat"):
        load_spec(tmp_path / "spec.toml")


def test_the_command_reports_one_line_and_exit_2(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text("[grid]\nsigma_t = [5.0, nan]\n")
    out = subprocess.run([sys.executable, "-m", "polarstripe", "sweep", str(spec)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip() == "polarstripe sweep: error: grid.sigma_t[1] must be a finite number, got nan"
    assert not (tmp_path / "spec-sweep").exists()  # nothing ran, nothing written


def test_grid_and_scenes():
    spec = _spec(grid={"separation": {"min": 0.05, "max": 0.25, "n": 3},
                       "sigma_t": {"min": 2, "max": 4, "n": 3}, "object_albedo": [0.3],
                       "exposure": ["auto", 0.004]})
    assert spec.n_scenes == 6 and list(spec.axes) == ["sigma_t", "object_albedo", "exposure", "stripes"]
    np.testing.assert_allclose(spec.separations, [0.05, 0.15, 0.25])
    p = spec.scenes()[1]
    assert p == {"sigma_t": 2.0, "object_albedo": 0.3, "exposure": 0.004, "stripes": 30}
    s = scene_for(spec.base, p)
    assert s.medium.sigma_t == 2.0 and s.camera.exposure_s == 0.004
    assert all(o.albedo == 0.3 for o in s.objects)


def test_serial_table_matches_the_planner():
    spec = _spec()
    res = run_sweep(spec, jobs=0)
    assert not res.failed and not res.missing and len(res.results) == 2
    header, rows = table_rows(res)
    assert len(rows) == 2 * 4 and header[:5] == ["scene", "status", "sigma_t", "exposure", "stripes"]
    # scene 1 (sigma_t = 7) by hand through the planner
    scene = scene_for(spec.base, spec.scenes()[1])
    plans = plan(SceneModel(scene, fidelity="preview", n_stripes=8), spec.separations)
    mine = [r for r in rows if r["scene"] == 1]
    np.testing.assert_array_equal([r["objective_stripes_E_b"] for r in mine],
                                  plans["stripes_polarized"].curve.objective)
    np.testing.assert_array_equal([r["objective_flood_S_hat"] for r in mine],
                                  plans["flood_polarized"].readings["S_hat"].objective)
    assert mine[0]["best_flood_m"] == plans["flood"].curve.best_separation_m
    assert mine[0]["flood_reading"] == plans["flood_polarized"].reading
    # orders = "single" plans with the paper's model, which gives other curves than all orders (the default)
    single = run_sweep(_spec(orders="single"), jobs=0)
    _, rows1 = table_rows(single)
    paper = plan(SceneModel(scene, fidelity="preview", n_stripes=8, orders="single"), spec.separations)
    np.testing.assert_array_equal([r["objective_stripes_E_b"] for r in rows1 if r["scene"] == 1],
                                  paper["stripes_polarized"].curve.objective)
    assert not np.allclose(paper["stripes_polarized"].curve.objective,
                           plans["stripes_polarized"].curve.objective)


def _fake(job: SceneJob) -> dict:
    """A cheap stand-in for a plan: objective = scene index + separation; worker deaths on request."""
    marker = os.environ.get("PS_SWEEP_TEST_DIR", "")
    if job.params["sigma_t"] == 4.0:
        os._exit(3)  # this scene always kills its worker
    if job.params["sigma_t"] == 5.0 and marker and not Path(marker, "died").exists():
        Path(marker, "died").touch()
        os._exit(3)  # dies the first time only
    if job.params["sigma_t"] == 6.0:
        raise ValueError("no light")
    cols = curve_columns(job.spec)
    vals = [job.index + float(d) for d in job.spec.separations]
    return {"objective": {c: vals for c in cols}, "best": {c: float(job.spec.separations[-1]) for c in cols},
            "flood_reading": "E_b", "scan_stripes": "rotate", "scan_stripes_E_b": "rotate"}


@pytest.mark.slow
def test_dead_workers_are_retried_once_and_reported(tmp_path, monkeypatch):
    monkeypatch.setenv("PS_SWEEP_TEST_DIR", str(tmp_path))  # loky workers inherit the environment
    spec = _spec(grid={"separation": {"min": 0.02, "max": 0.3, "n": 3}, "sigma_t": [1.0, 4.0, 5.0, 6.0, 7.0]})
    res = run_sweep(spec, jobs=2, evaluate=_fake)
    assert sorted(res.results) == [0, 2, 4]  # 5.0 died once (in the pool or alone), then passed alone
    assert res.failed[1] == "the worker died twice (retried once, alone)"
    assert res.failed[3] == "ValueError: no light"  # a Python error is not retried
    write_table(res, tmp_path / "t.csv")
    rows = read_table(tmp_path / "t.csv")
    status = {int(r["scene"]): r["status"] for r in rows}
    assert status[1].startswith("failed: the worker died") and status[3] == "failed: ValueError: no light"
    assert sum(r["status"] == "ok" for r in rows) == 3 * 3
    assert all(math.isnan(r["separation_m"]) for r in rows if r["status"] != "ok")


def test_interrupt_keeps_the_finished_scenes(tmp_path):
    def stop_at_third(job):
        if job.index == 2:
            raise KeyboardInterrupt
        return _fake(job)

    spec = _spec(grid={"separation": {"min": 0.02, "max": 0.3, "n": 3}, "sigma_t": [1.0, 2.0, 3.0, 7.0]})
    res = run_sweep(spec, jobs=0, evaluate=stop_at_third)
    assert res.interrupted and sorted(res.results) == [0, 1] and res.missing == [2, 3]
    write_table(res, tmp_path / "t.csv")
    rows = read_table(tmp_path / "t.csv")
    assert [r["status"] for r in rows if r["scene"] >= 2] == ["missing: interrupted"] * 2
    assert len([r for r in rows if r["status"] == "ok"]) == 2 * 3


@pytest.mark.slow
def test_dask_local_cluster_gives_the_local_table(tmp_path):
    distributed = pytest.importorskip("distributed")
    spec = _spec()
    local = run_sweep(spec, jobs=2)
    write_table(local, tmp_path / "local.csv")
    # processes=False: scheduler and worker in this process over the in-process transport (no sockets)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("inproc://")
        remote = run_sweep(spec, scheduler=cluster.scheduler_address)
    write_table(remote, tmp_path / "dask.csv")
    assert not local.failed and not remote.failed and remote.workers == 1
    assert (tmp_path / "local.csv").read_text() == (tmp_path / "dask.csv").read_text()


@pytest.mark.slow
def test_sweep_command_writes_the_table_and_plots(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text('fidelity = "preview"\nmodalities = ["flood"]\n[grid]\n'
                    'separation = {min = 0.05, max = 0.3, n = 4}\nsigma_t = [3.0, 6.0, 9.0]\n')
    out = subprocess.run([sys.executable, "-m", "polarstripe", "sweep", str(spec), "--jobs", "0", "--json"],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    folder = tmp_path / "spec-sweep"
    rows = read_table(folder / "sweep.csv")
    assert len(rows) == 3 * 4 and {r["status"] for r in rows} == {"ok"}
    assert "objective_stripes" not in rows[0] and "objective_flood_S_hat" in rows[0]
    for png in ("optimum_vs_sigma_t.png", "objective_map.png"):
        assert (folder / png).stat().st_size > 10_000
