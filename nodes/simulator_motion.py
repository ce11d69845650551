"""The simulator's rig moving during scans (its ``velocity_m_s`` and ``fps`` params; sim/motion.py,
docs/planning.md §11).

When a scan starts (``emitter/scan``), its capture times follow from the event: the method's patterns per
pass, the analyzer angles in order and the hosted drive's speed and settle time (``drive_speed_counts_s`` /
``counts_per_deg``, ``drive_settle_s``: the stage model's move time, whichever stage the rig uses). Frame
``step`` of that scan is then rendered with the rig translated by v·(t_step − t_mid), so the rig passes the
scene's pose, where the ground truth is taken, at the middle of the scan. Frames of a scan the simulator did
not see start (and every frame at rest) are at the scene's pose.
"""

from __future__ import annotations

from polarstripe.msgs import Method, ScanEvent
from polarstripe.sim.motion import RigMotion
from polarstripe.sim.scene import Scene


def rig_motion(params) -> RigMotion:
    """The simulator params' :class:`RigMotion`; ValueError (a SceneError) names a bad param."""
    return RigMotion(params.velocity_m_s, params.fps, params.drive_speed_counts_s / params.counts_per_deg,
                     params.drive_settle_s)


def frames_per_pass(event: ScanEvent) -> int | None:
    """Frames a scan of ``event`` takes at each analyzer angle: a stripe scan ⌈stripes/sheets⌉ (None for a
    method this does not know or a stripe scan without stripes)."""
    method = Method.lookup(event.method)
    if method is None or (method.striped and (event.stripes < 1 or event.sheets < 1)):
        return None
    return len(method.patterns(event.stripes, 1, min(event.sheets, event.stripes) if method.striped else 1))


class ScanMotion:
    """The capture times of the scans running (keyed by scan id) and the scene each frame sees."""

    def __init__(self, params):
        self.rig = rig_motion(params)
        self._times: dict = {}

    def start(self, event: ScanEvent) -> None:
        """Scan ``event.scan_id`` starts: its frames' capture times (nothing at rest)."""
        n = frames_per_pass(event)
        if self.rig.moving and n is not None:
            self._times[event.scan_id] = self.rig.times(n, event.analyzer_deg)

    def end(self, scan_id: int) -> None:
        self._times.pop(scan_id, None)

    def scene_at(self, scene: Scene, scan_id: int, step: int) -> Scene:
        """``scene`` as frame ``step`` of scan ``scan_id`` sees it (``scene`` itself at rest)."""
        times = self._times.get(scan_id)
        return scene if times is None else self.rig.scene_at(scene, times, step)
