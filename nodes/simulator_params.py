"""The simulator node's params and their checks (the node: nodes/simulator.py)."""

from __future__ import annotations

from typing import Literal

from polarstripe.nodes.simulator_frames import check_medium, micro_polarizers, parse_resolution
from polarstripe.nodes.simulator_motion import rig_motion
from polarstripe.runtime.params import NodeParams, check_frame_size
from polarstripe.sim.mosaic import SONY_EXTINCTION_RATIO, SONY_LAYOUT
from polarstripe.sim.render import resolve_fidelity


class SimulatorParams(NodeParams):
    """The simulator node's params (nodes/simulator.py)."""

    scene: str = ""  # scene TOML; "" = the paper's tank
    resolution: str = ""  # camera "WxH"; "" = the scene's
    fidelity: str = "preview"  # preview | standard | reference | "xi=..,theta=..,phi=..,grid=.."
    render_scale: int = 0  # model resolution divisor; 0 = auto (preview: ~160 px wide, else 1)
    noise: str = "auto"  # poisson | gaussian | auto (gaussian at preview)
    exposure_s: float | None = None  # None: the scene's, scaled by (w/w_scene)^2 to keep the DN level
    medium_sigma_t: float | None = None  # override the scene medium's σ_t [1/m] (the estimator's truth)
    medium_g: float | None = None  # … and its phase function: TTHG of this mean cosine
    light: Literal["scene", "linear", "circular"] = "scene"  # quarter-wave plates (sim with_light)
    auto_exposure: bool = True  # after each source move, shorten the exposure if the flood would clip
    seed: int | None = None  # None: the scene camera's seed
    cache_size: int = 80  # patterns' components kept (one set per pattern and source pose)
    render_ahead: bool = True  # make the scan's next `threads` × `render_batch` frames while this one travels
    render_batch: int = 3  # frames made ahead rendered together (sim/scan_render.py); 1 = one by one
    threads: int = 0  # frames made at once; 0 = the cores of the process's CPU affinity
    analyzer_deg: float = 0.0  # analyzer angle when no drive is hosted [deg]
    can_channel: str = ""  # python-can zmq channel of the simulated drive; "" = no drive
    can_node_id: int = 5
    counts_per_deg: float = 1000.0
    drive_speed_counts_s: float = 200_000.0
    drive_settle_s: float = 0.02
    faults: list[str] = []  # fault commands applied at start, e.g. ["never_settle on"]
    ell14_link: str = ""  # host a simulated ELL14 on a pty and symlink it here ("" = none)
    target: str = ""  # "COLSxROWS": a checkerboard (inner corners) replaces the objects; "" = none
    target_square_m: float = 0.015  # its squares [m]
    target_poses: int = 8  # its seeded poses (simulator/target steps through them)
    target_seed: int = 0
    mosaic_extinction_ratio: float = SONY_EXTINCTION_RATIO  # simulator/render_mosaic's micro-polarizers
    mosaic_extinction_spread: float = 0.1  # σ of log ER over the pixels (fixed per sensor)
    mosaic_crosstalk: list[float] = [0.001, 0.0002]  # to each edge and diagonal neighbour
    mosaic_layout: list[float] = list(SONY_LAYOUT)  # 2x2 angles [deg], row-major from the top left
    velocity_m_s: list[float] = [0.0, 0.0, 0.0]  # during scans [m/s]: along the baseline, across, forward
    fps: float = 30.0  # the camera's frame rate: a scan's frames 1/fps apart (docs/planning.md §11)

    def validate(self):
        super().validate()
        res = parse_resolution(self.resolution)
        if res is not None:
            check_frame_size(*res, what="resolution")
        resolve_fidelity(self.fidelity)
        if self.noise not in ("poisson", "gaussian", "auto"):
            raise ValueError(f"noise must be poisson, gaussian or auto, got {self.noise!r}")
        if (self.render_scale < 0 or self.cache_size < 1 or self.render_batch < 1
                or not self.counts_per_deg > 0):
            raise ValueError("render_scale >= 0, cache_size >= 1, render_batch >= 1 and counts_per_deg > 0 "
                             "are needed")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0: the CPU affinity), got {self.threads}")
        check_medium(self.medium_sigma_t, self.medium_g)
        micro_polarizers(self)
        rig_motion(self)
