"""Step 4 of the sequencer (nodes/sequencer.py): after a pass over the methods, whether the plan the planner
made in answer to the estimate of one of the pass's scans is worth scanning again.

It is, when that plan's separation is more than one step of its grid away from the one scanned and, where the
plan carries its objective curve, the curve predicts a gain of at least ``min_gain`` there; the source is then
moved to it. :class:`Rescanning` is a mixin of :class:`~polarstripe.nodes.sequencer.Sequencer` (it uses the
node's params, graph, log, ``plan``, ``pass_scans``, ``wait_for`` and ``move_source_to``).
"""

from __future__ import annotations

import numpy as np
from polarstripe.msgs import Method, Plan
from polarstripe.runtime.bus import BusTimeout
from polarstripe.runtime.liveness import PeerLost


class Rescanning:
    """The sequencer's rescan decision (see the module docstring)."""

    def plan_moved(self) -> bool:
        """Step 4: True when the plan answering this pass's estimate moved the source by more than one grid
        step (the source is moved then)."""
        p, est_node = self.params, self.params.estimator
        if not (p.rescan and self.plan is not None and est_node in self.graph.get("nodes", {})
                and any(Method(m).striped for m in p.methods)):
            return False
        try:
            est = self.wait_for("medium/estimate", lambda e: e.scan_id in self.pass_scans,
                                p.estimate_timeout_s, peers=[est_node])
            new = self.wait_for("planner/plan", lambda q: _answers(q, est.scan_id), p.estimate_timeout_s,
                                peers=["planner"])
        except (BusTimeout, PeerLost) as exc:
            self.log.warning("no rescan: no estimate and plan after scans %s: %s", self.pass_scans, exc)
            return False
        step, at_new, at_old = _move(new, self.plan.separation_m)
        what = est.reason or f"sigma_t {est.sigma_t_per_m:.3g} /m, g {est.mean_cosine:.3f}, p {est.p:.3f}"
        gain = "" if at_new is None else f"; objective {at_new:.3f} there, {at_old:.3f} where scanned"
        self.log.info("estimate of scan %d: %s; plan d_LC = %.3f m (scanned at %.3f m, %d grid steps%s)",
                      est.scan_id, what, new.separation_m, self.plan.separation_m, step, gain)
        if step <= 1:
            return False
        if at_new is not None and at_new < at_old + p.min_gain:
            self.log.info("no rescan: the re-made plan predicts no gain of %g at its pick", p.min_gain)
            return False
        if p.move_source:
            self.move_source_to(new)
        self.log.info("rescanning at d_LC = %.3f m (the optimum moved by %d grid steps)", new.separation_m,
                      step)
        self.plan = new
        return True


def _move(new: Plan, scanned_m: float) -> tuple[int, float | None, float | None]:
    """(grid steps from ``scanned_m`` to ``new``'s pick, ``new``'s objective at its pick and at ``scanned_m``;
    None without an objective curve), read on ``new``'s separations. A step is the grid's spacing, the widest
    gap between them: the planner's bisections add midpoints near its best (planning/planner.py)."""
    grid = np.asarray(new.curves.get("separation_m", [new.separation_m]), float)
    i, j = (int(np.argmin(np.abs(grid - d))) for d in (new.separation_m, scanned_m))
    spacing = float(np.max(np.diff(np.sort(grid)))) if grid.size > 1 else 0.0
    steps = int(round(abs(new.separation_m - scanned_m) / spacing)) if spacing > 0 else abs(i - j)
    obj = new.curves.get("objective")
    if obj is None or len(obj) != grid.size:
        return steps, None, None
    return steps, float(obj[i]), float(obj[j])


def _answers(plan: Plan, scan_id: int) -> bool:
    """Whether ``plan`` is the planner's answer to the estimate of scan ``scan_id`` (nodes/planner.py)."""
    sid = plan.curves.get("estimate_scan_id")
    return sid is not None and len(sid) == 1 and int(sid[0]) == scan_id
