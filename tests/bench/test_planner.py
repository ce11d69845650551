"""``polarstripe bench planner`` (bench/planner.py): the ladder's JSON has every fidelity level with its time
per full plan and its regret per method against the end-to-end truth; the table names every level; bad levels
are one error line. A tiny ladder (the default search on 3 separations, 32 px, 4 stripes, a 2-separation truth
at preview) so it takes seconds; what it measures is not checked against a clock."""

from __future__ import annotations

import json
import math

import pytest
from polarstripe.bench.planner import METHOD_NAMES, print_ladder
from polarstripe.planning.planner import SEARCHES
from polarstripe.tools.cli import main

TINY = ["--separations", "3", "--width", "32", "--stripes", "4", "--grid", "2", "--refine", "0",
        "--fidelity", "preview", "--no-cache", "--no-progress"]


@pytest.fixture(scope="module")
def ladder():
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["bench", "planner", *TINY, "--fidelities", "draft,preview,standard", "--json"]) == 0
    return json.loads(out.getvalue())


def test_every_level_has_its_time_and_regret(ladder):
    assert [(lv["variant"], lv["fidelity"], lv["search"]) for lv in ladder["levels"]] == [
        ("error", "draft", "coarse"), ("error", "preview", "coarse"), ("error", "standard", "coarse")]
    assert ladder["separations"] == 3 and ladder["searches"] == {"coarse": vars(SEARCHES["coarse"])}
    s = SEARCHES["coarse"]
    truth = ladder["truth"]["tank_sigma5"]["best"]                          # the default scene: σ_t 5
    assert set(truth) == set(METHOD_NAMES)
    for lv in ladder["levels"]:
        assert lv["cpu_seconds_per_plan"] > 0 and lv["seconds_per_plan"] > 0
        assert lv["cpu_seconds_per_plan"] == lv["cpu_seconds"]["tank_sigma5"]   # every evaluation timed
        # flood + stripes: the grid, then at most 2 midpoints per round, reading and peak
        assert 2 * 3 < lv["model_evaluations"]["tank_sigma5"] <= 2 * (3 + s.refine * 3 * 3 * 2)
        regret, picks = lv["regret"]["tank_sigma5"], lv["picks_m"]["tank_sigma5"]
        assert set(regret) == set(METHOD_NAMES)
        for m in METHOD_NAMES:
            assert math.isfinite(regret[m]) and regret[m] >= 1.0
            if math.isclose(picks[m], truth[m]["separation_m"]):            # picked the best seen
                assert regret[m] == pytest.approx(1.0)
            else:
                assert regret[m] > 1.0
        assert lv["worst_regret"] == max(regret.values())
        # the grid's propagations are part of the plan: some transforms, within the plan's CPU
        prop = lv["propagations"]["tank_sigma5"]
        assert prop["transforms"] > 0 and 0 < prop["cpu_seconds"] < lv["cpu_seconds_per_plan"]


def test_the_table_names_every_level(ladder, capsys):
    print_ladder(ladder)
    out = capsys.readouterr().out
    assert "coarse: 3 separations, 4 bisection round(s), rivals 0.05" in out
    for fid in ("draft", "preview", "standard"):
        assert f"error    {fid:<9} coarse      tank_sigma5" in out
        assert f"error/{fid}/coarse tank_sigma5: " in out and " transforms, " in out


@pytest.mark.parametrize("argv, needle", [
    (["--fidelities", "ultra"], "fidelity 'ultra' is not preview, standard, reference"),
    (["--fidelities", "reference"], "the error measure is not run at reference"),
    (["--plan-orders", "double"], "--plan-orders: comma-separated error, all, single, got 'double'"),
    (["--searches", "dense"], "--searches: comma-separated coarse, exhaustive, got 'dense'"),
])
def test_bad_levels_are_one_error_line(argv, needle, capsys):
    assert main(["bench", "planner", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
