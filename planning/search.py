"""Which separations the planner evaluates: a coarse grid, then bisections around each curve's best and its
rivals (docs/planning.md §8, "The search").

A plan's cost is one model evaluation per separation and modality (every reading's curve shares it), so the
planner evaluates an even grid of ``separations`` points, then ``refine`` rounds of bisection: in each round,
the midpoints between each curve's peaks and their evaluated neighbours, down to the grid's step / 2**refine.
The peaks are the curve's best and, with ``rivals`` > 0, up to :data:`PEAKS` − 1 other local maxima whose
loss is within ``rivals`` (relative) of the best's, at least one grid step apart: a narrow second peak, or
the other end of a flat top, is refined too, and may win. The loss is the expected error 1 − objective for
the error measure, the objective itself (relative to the best's) for the paper's measures. Toward a
neighbour whose image loses more pixels to saturation than the peak's there is no bisection (there the
error jumps within millimetres, and the prediction places that cliff only to about half a centimetre),
unless the neighbour's loss is within :data:`CLIFF_RIVALS` of the peak's and the gap over :data:`CLIFF_STEP`:
then the optimum may sit at the cliff's edge between them, and the midpoints approach it to the 1-cm grid's
step. (A neighbour that loses far more, such as a frame saturated near the camera, is a cliff the curve
climbs toward; the prediction near it is the least sure, and approaching it moved a pick onto a ripple dip
the truth does not share: docs/planning.md §8.)

:data:`SEARCHES` names the two searches the tools offer: ``coarse`` (the default) and ``exhaustive``, the
planner's grid of 60 separations and two rounds around each best alone (the search before the coarse one).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from polarstripe.sim.scene import SceneError

PEAKS = 3            # most peaks refined per curve: the best and two rivals
CLIFF_STEP = 0.01    # [m] no bisection of a gap this small toward more saturation (docs/planning.md §8)
CLIFF_RIVALS = 0.25  # toward more saturation only if the neighbour's loss is within this of the peak's
_DIGITS = 9          # separations are compared rounded to a nanometre


@dataclass(frozen=True)
class Search:
    """How :func:`polarstripe.planning.planner.plan` chooses its separations: an even grid of
    ``separations`` points, ``refine`` bisection rounds around each curve's peaks, ``rivals`` the
    relative loss within which a local maximum other than the best is refined too (0: the best alone)."""

    separations: int
    refine: int
    rivals: float


SEARCHES = {"coarse": Search(separations=20, refine=4, rivals=0.05),
            "exhaustive": Search(separations=60, refine=2, rivals=0.0)}
DEFAULT_SEARCH = "coarse"


def resolve_search(search: str | Search = DEFAULT_SEARCH, *, separations: int | None = None,
                   refine: int | None = None, rivals: float | None = None) -> Search:
    """The search named ``search`` (:data:`SEARCHES`; or a :class:`Search`) with the settings given here in
    place of its own (None: the search's).

    Raises
    ------
    SceneError
        An unknown name (one line naming the searches).
    """
    if not isinstance(search, Search):
        if search not in SEARCHES:
            raise SceneError(f"search must be one of {', '.join(SEARCHES)}, got {search!r}")
        search = SEARCHES[search]
    given = {"separations": separations, "refine": refine, "rivals": rivals}
    return dataclasses.replace(search, **{k: v for k, v in given.items() if v is not None})


def _slack(best: float, rivals: float, error: bool) -> float:
    """How far below ``best`` an objective may lie and still be within ``rivals`` of its loss."""
    return rivals * ((1.0 - best) if error else abs(best))


def peaks(seps: np.ndarray, values: np.ndarray, *, rivals: float = 0.0, error: bool = True,
          spread: float = 0.0) -> list[int]:
    """Indices of the peaks to refine on one curve (``seps`` increasing): the best (the first maximum), then
    local maxima (not below either neighbour, above one: no point inside a plateau, such as the zeros where
    every pixel saturates) whose loss is within ``rivals`` of the best's,

        v* − v ≤ rivals · (1 − v*)   (the error measure: v = 1 − e, so e ≤ e*(1 + rivals)),
        v* − v ≤ rivals · |v*|       (the paper's measures),

    the higher first, none within ``spread`` of a peak already taken, at most :data:`PEAKS`."""
    v = np.asarray(values, np.float64)
    best = int(np.argmax(v))
    if rivals <= 0.0 or v.size < 3:
        return [best]
    slack = _slack(v[best], rivals, error)
    left, right = np.r_[-np.inf, v[:-1]], np.r_[v[1:], -np.inf]
    above = (v > np.r_[np.inf, v[:-1]]) | (v > np.r_[v[1:], np.inf])      # an end: above its one neighbour
    local = np.flatnonzero((v >= left) & (v >= right) & above & (v[best] - v <= slack))
    out = [best]
    for i in local[np.argsort(-v[local], kind="stable")]:
        if len(out) == PEAKS:
            break
        if all(abs(seps[i] - seps[k]) > spread * (1 + 1e-6) for k in out):
            out.append(int(i))
    return out


def midpoints(seps: np.ndarray, curves: list[tuple[np.ndarray, np.ndarray]], *, rivals: float = 0.0,
              error: bool = True, spread: float = 0.0, finest: float = 0.0) -> list[float]:
    """One bisection round: the separations to evaluate next, none evaluated yet, none repeated.

    ``seps`` are the evaluated separations (increasing); ``curves`` one (objective, lost) pair per curve on
    them, ``lost`` the fraction of the image lost to saturation. For each peak (:func:`peaks`), the midpoint
    toward each neighbour that is more than ``finest`` away; toward one that loses more pixels than the
    peak only if it is more than :data:`CLIFF_STEP` away and its loss within :data:`CLIFF_RIVALS` of the
    peak's."""
    seps = np.asarray(seps, np.float64)
    done = {round(float(d), _DIGITS) for d in seps}
    out = []
    for values, lost in curves:
        for i in peaks(seps, values, rivals=rivals, error=error, spread=spread):
            for j in (i - 1, i + 1):
                if not (0 <= j < seps.size):
                    continue
                gap = abs(seps[j] - seps[i])
                if gap <= finest * (1 + 1e-6):
                    continue
                if lost[j] > lost[i] and (gap <= CLIFF_STEP * (1 + 1e-6) or
                                          values[i] - values[j] > _slack(values[i], CLIFF_RIVALS, error)):
                    continue
                mid = round(0.5 * float(seps[i] + seps[j]), _DIGITS)
                if mid not in done:
                    done.add(mid)
                    out.append(mid)
    return out
