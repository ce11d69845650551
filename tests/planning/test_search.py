"""The planner's separation search (planning/search.py, planner.plan's refine and rivals): on a closed-form
model, no renders. E's objective is eq. 8's CQM = S / (S + B) with S = 1, B = g(d) and an ideal sensor
(W = 1), so each curve's global maximum is known by brute force on a 0.01-mm grid of the closed form."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.planning.planner import (
    IDEAL_SENSOR,
    SEARCHES,
    Samples,
    default_separations,
    plan,
    search_plan,
)
from polarstripe.planning.search import midpoints, peaks
from polarstripe.sim.scene import SceneError

FINE = np.arange(0.01, 0.6 + 1e-9, 1e-5)      # the brute-force grid [m]


class ClosedForm:
    """A :class:`~polarstripe.planning.planner.PlanModel` with the backscatter g(d) per unit signal at one
    observed point (DOP 0.5): E's objective is 1 / (1 + g(d)). Every evaluation is recorded."""

    noise = IDEAL_SENSOR
    edge = "margin"

    def __init__(self, g):
        self.g, self.calls = g, []

    def observed_pixels(self):
        return np.array([[0, 0]])

    def lateral_positions_m(self):
        return np.zeros(1)

    def flood(self, d):
        self.calls.append(d)
        return Samples(np.ones(1), np.zeros(1), np.array([float(self.g(d))]), np.array([0.5]))

    stripes = flood


def bowl(d, at, depth, width):
    return depth * np.exp(-0.5 * ((d - at) / width) ** 2)


GRID = default_separations(SEARCHES["coarse"].separations)         # the default search's first grid
STEP = GRID[1] - GRID[0]
NARROW = GRID[3] + 0.3 * STEP                                        # between two of its points


def second_peak(d):
    """A broad minimum of B at 40 cm (0.30) and a deeper, narrow one (0.24; a quarter of the grid's step wide
    on a 4-cm shoulder) between the coarse grid's points, which see it only on its flank."""
    return 0.62 - bowl(d, 0.40, 0.32, 0.10) - bowl(d, NARROW, 0.26, 0.04) - bowl(d, NARROW, 0.1, 0.25 * STEP)


def flat_top(d):
    """B flat at 0.3 from 15 to 45 cm within a ripple of ±0.003 (1.13-cm period): a plateau point is up to
    1.6 % worse in 1 − v than the ripple's best."""
    d = np.asarray(d, np.float64)
    edge = np.maximum(0.0, np.maximum(0.15 - d, d - 0.45))
    return 0.3 + 40.0 * edge ** 2 + 0.003 * np.cos(2 * np.pi * (d - 0.305) / 0.0113)


def truth(g):
    v = 1.0 / (1.0 + g(FINE))
    return float(FINE[np.argmax(v)]), float(v.max())


@pytest.mark.parametrize("g, bound", [(second_peak, 1.005), (flat_top, 1.001)],
                         ids=["narrow second peak", "flat top"])
def test_the_default_search_finds_the_global_maximum(g, bound):
    """Against the brute-force maximum (the coarse grid's best alone is far off on the second peak, below)."""
    d_true, v_true = truth(g)
    model = ClosedForm(g)
    plans = search_plan(model, modalities=("flood",))
    c = plans["flood"].curve
    s = SEARCHES["coarse"]
    finest = (0.6 - 0.01) / (s.separations - 1) / 2 ** s.refine
    v_pick = 1.0 / (1.0 + g(c.best_separation_m))
    assert (1.0 - v_pick) <= (1.0 - v_true) * bound            # the loss 1 − v at the pick over the least
    if g is second_peak:
        assert abs(c.best_separation_m - d_true) <= finest
    assert plans["flood"].evaluations == len(model.calls) < 60


def test_the_best_alone_misses_the_narrow_peak():
    """The test's curves are hard: refining only the coarse grid's best stays on the broad peak, 10 % or
    more above the least loss; on the flat top the coarse grid's best is over 0.1 % above it."""
    d_true, v_true = truth(second_peak)
    plans = plan(ClosedForm(second_peak), GRID, modalities=("flood",), refine=SEARCHES["coarse"].refine,
                 rivals=0.0)
    c = plans["flood"].curve
    assert abs(c.best_separation_m - 0.40) < 0.03 and abs(d_true - NARROW) < 0.002
    assert 1.0 - c.objective.max() > 1.1 * (1.0 - v_true)
    _, v_flat = truth(flat_top)
    assert 1.0 - (1.0 / (1.0 + flat_top(GRID))).max() > 1.001 * (1.0 - v_flat)   # the bound above


@pytest.mark.parametrize("search", list(SEARCHES))
def test_no_separation_is_evaluated_twice(search):
    model = ClosedForm(flat_top)
    plans = search_plan(model, search, modalities=("flood",))
    calls = np.round(model.calls, 9)
    assert len(set(calls.tolist())) == calls.size == plans["flood"].evaluations
    for mp in plans.values():                      # every reading's curve holds every evaluation
        for c in (mp.readings or {"E": mp.curve}).values():
            np.testing.assert_array_equal(np.round(c.separations_m, 9), np.sort(calls))


def old_bisections(seps, values, rounds):
    """The search before the coarse one, for one curve: the grid, then ``rounds`` rounds of the midpoints
    between the best and its neighbours."""
    seps = list(seps)
    for _ in range(rounds):
        order = np.argsort(seps)
        d = np.asarray(seps)[order]
        v = np.array([values(x) for x in d])
        i = int(np.argmax(v))
        seps += [0.5 * (d[i] + d[j]) for j in (i - 1, i + 1) if 0 <= j < d.size
                 and round(0.5 * (d[i] + d[j]), 9) not in np.round(seps, 9)]
    return np.sort(seps)


def test_the_exhaustive_search_is_the_old_grid_and_bisections():
    model = ClosedForm(second_peak)
    plans = search_plan(model, "exhaustive", modalities=("flood",))
    seps = plans["flood"].curve.separations_m
    grid = np.linspace(0.01, 0.6, 60)                                  # 1 cm steps
    assert np.isin(np.round(grid, 9), np.round(seps, 9)).all()
    # the curves E, E_b, S_hat each refined around their own best (S_hat is 1 everywhere: its first point)
    e = old_bisections(grid, lambda d: 1 / (1 + second_peak(d)), 2)
    e_b = old_bisections(grid, lambda d: 1 / (1 + 0.5 * second_peak(d)), 2)
    s_hat = old_bisections(grid, lambda d: 1.0, 2)
    np.testing.assert_allclose(seps, np.unique(np.round(np.r_[e, e_b, s_hat], 9)), atol=1e-12)


def test_peaks_take_rivals_within_the_tolerance_one_step_apart():
    seps = np.arange(10) * 0.01
    v = np.array([0.1, 0.5, 0.2, 0.79, 0.8, 0.3, 0.78, 0.2, 0.7, 0.1])   # local maxima at 1, 4, 6, 8
    assert peaks(seps, v) == [4]
    # the error measure: loss 1 − v; 0.78's is within 15 % of 0.2, 0.7's and 0.5's are not
    assert peaks(seps, v, rivals=0.15, error=True, spread=0.01) == [4, 6]
    assert peaks(seps, v, rivals=0.6, error=True, spread=0.01) == [4, 6, 8]       # at most three
    assert peaks(seps, v, rivals=0.15, error=True, spread=0.02) == [4]             # 6 is within the spread
    assert peaks(seps, v, rivals=0.05, error=False, spread=0.01) == [4, 6]        # |v*| the scale: 0.04
    flat = np.array([0.0, 0.0, 0.0, 0.5, 0.5, 0.2, 0.0, 0.0])     # inside a plateau is no rival, its edge is
    assert peaks(seps[:8], flat, rivals=1.0, error=True) == [3, 4]
    assert peaks(seps[:8], flat, rivals=1.0, error=True, spread=0.01) == [3]


def test_midpoints_stop_at_the_finest_step_and_skip_evaluated_ones():
    seps = np.array([0.1, 0.2, 0.25, 0.4])
    v = np.array([0.2, 0.9, 0.5, 0.3])
    lost = np.zeros(4)
    assert midpoints(seps, [(v, lost)]) == [0.15, 0.225]
    assert midpoints(seps, [(v, lost)], finest=0.05) == [0.15]            # 0.05 to 0.25: fine enough
    assert midpoints(seps, [(v, lost), (v, lost)]) == [0.15, 0.225]       # a second curve repeats none


@pytest.mark.parametrize("drop, approached", [(0.03, True), (0.3, False)])
def test_toward_a_saturating_neighbour_bisection_stops_a_centimetre_from_it(drop, approached):
    """The coarse grid's best beside a neighbour that loses pixels to saturation (below a cliff at 29 cm,
    where the best is): when the neighbour's loss is within CLIFF_RIVALS of the peak's, the midpoints
    approach the cliff until the gap is CLIFF_STEP (1 cm) or less, no nearer; when it loses far more
    (``drop``), not at all (planning.md §8)."""
    def curve(d):
        lost = np.where(d < 0.29, 0.05, 0.0)
        return 0.66 - 0.5 * np.abs(d - 0.29) - drop * (d < 0.29), lost

    done = [0.2853, 0.3247]                                  # 3.94 cm apart, as the default grid
    for _ in range(6):
        d = np.sort(done)
        done += midpoints(d, [curve(d)])
    d = np.sort(done)
    nearest = d[d > 0.2853][0]
    if approached:                                          # 0.985 cm from the lost point: no nearer
        assert nearest == pytest.approx(0.2853 + 0.0394 / 4)
    else:
        assert nearest == pytest.approx(0.3247)


def test_bad_rivals_are_one_error():
    with pytest.raises(SceneError, match="rivals"):
        plan(ClosedForm(flat_top), default_separations(4), modalities=("flood",), rivals=-0.1)
    with pytest.raises(SceneError, match="search must be"):
        search_plan(ClosedForm(flat_top), "dense")
