"""The compositor's depth: light-stripe triangulation of every stripe scan (docs/depth.md).

* the rig geometry comes from the compositor's ``geometry`` param (:func:`load_geometry`): ``""`` the
  simulator's (``rig_geometry`` in the scan's ``simulator/truth`` metrics: its source moves with the plan),
  else the default tank's scene, a scene ``.toml`` (its camera and projector pinholes), a calibration file
  (``polarstripe calibrate -o rig.yaml``: OpenCV ``FileStorage`` YAML/XML/JSON with ``K_cam``, ``dist_cam``,
  ``K_proj``, ``R``, ``T``, ``cam_size``, ``proj_size``), or ``"none"`` (no depth);
* per stripe scan, a :class:`~polarstripe.imaging.delineation.RunningArgmax` per analyzer angle keeps the
  brightest value, its frame (the index of the frame's ``stripe:K/N`` or ``stripe:I/N:xS`` tag) and the
  second-brightest value: memory does not grow with the stripes;
* a scan of several sheets per frame: each pixel's stripe position is the sheet of its brightest frame that
  its ray meets within the depth range (:mod:`polarstripe.imaging.sheets`: the ``depth_range_m`` param, else
  the simulator truth's object depths widened by 10 % each way); sheets that overlap in the image over that
  range are an error (no depth; the metrics' ``error`` says so and how many sheets would do);
* at the end: the sheets of the crossed angle (E_b, the one passing less light over the object-free region,
  as :func:`~polarstripe.imaging.compose.compose` chooses) or of the only one are delineated, triangulated,
  published as a :class:`~polarstripe.msgs.DepthMap` on ``compositor/depth`` and written to
  ``<out>/depth_<method>.npy`` (z [m], NaN invalid, float32) and ``depth_<method>.ply`` (binary
  little-endian PLY, float32 x y z in the camera frame, metres).
"""

from __future__ import annotations

import os

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging import calibration
from polarstripe.imaging.delineation import NoiseModel, RunningArgmax, SheetVotes, delineate
from polarstripe.imaging.sheets import assign_positions, check_sheets, depth_range, epipolar_span
from polarstripe.imaging.triangulation import RigGeometry, Triangulator, stripe_edges
from polarstripe.imaging.validation import ImagingError, roi_slices
from polarstripe.msgs import DepthMap, Method
from polarstripe.msgs.patterns import PatternError, parse
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import SceneError, load_scene

CALIBRATION_KEYS = calibration.FILE_KEYS


class GeometryError(PolarstripeError, ValueError):
    """A geometry param that names no usable rig geometry; the text names the file and the problem."""


def load_geometry(spec: str) -> RigGeometry | None:
    """The rig geometry a ``geometry`` param names (module docstring); None for ``"none"``."""
    if spec.strip().lower() == "none":
        return None
    try:
        if spec == "" or spec.endswith(".toml"):
            try:
                return RigGeometry.from_dict(rig_geometry(load_scene(spec or None)))
            except (SceneError, ValueError) as exc:
                raise GeometryError(f"geometry {spec!r}: {exc}") from None
        return RigGeometry.from_dict(read_calibration(spec))
    except ImagingError as exc:
        raise GeometryError(f"geometry {spec!r}: {exc}") from None


def read_calibration(path: str, *, cam_size=None, proj_size=None) -> dict:
    """The matrices of a calibration file written by ``polarstripe calibrate`` (cv2.FileStorage, read by
    :func:`polarstripe.imaging.calibration.load`; with ``cam_size``/``proj_size`` a file of another rig
    size is an error)."""
    try:
        return calibration.load(path, cam_size=cam_size, proj_size=proj_size)
    except calibration.CalibrationError as exc:
        raise GeometryError(f"geometry: {exc}") from None


def write_calibration(path: str, geom: dict, extra: dict | None = None) -> None:
    """Write a calibration atomically (temporary file + rename: a failed run leaves the old file whole;
    :func:`polarstripe.imaging.calibration.save`)."""
    calibration.save(path, geom, extra)


def write_ply(path: str, points: np.ndarray | None) -> None:
    """Binary little-endian PLY of float32 points (n, 3), written atomically."""
    pts = np.zeros((0, 3), "<f4") if points is None else np.ascontiguousarray(points, "<f4")
    header = ("ply\nformat binary_little_endian 1.0\ncomment polarstripe depth, camera frame, metres\n"
              f"element vertex {len(pts)}\n" + "".join(f"property float {c}\n" for c in "xyz")
              + "end_header\n")
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(pts.tobytes())
    os.replace(tmp, path)


def read_ply(path: str) -> np.ndarray:
    """The points of a PLY written by :func:`write_ply`."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int(next(line.split()[2] for line in data[:end].decode("ascii").splitlines()
                 if line.startswith("element vertex")))
    return np.frombuffer(data[end:], "<f4", count=3 * n).reshape(n, 3)


class DepthStage:
    """The compositor's depth, scan by scan: :meth:`start`, :meth:`add` per frame, :meth:`finish`."""

    def __init__(self, geometry: RigGeometry | None, noise: NoiseModel, *, k_sigma: float = 4.0,
                 min_contrast: float = 0.15, source: str = "", publisher=None, log=None,
                 depth_range_m: tuple[float, float] | None = None):
        self.geometry, self.noise, self.source = geometry, noise, source
        self.depth_range_m = depth_range_m
        self.k_sigma, self.min_contrast = k_sigma, min_contrast
        self.publisher, self.log = publisher, log
        self.running: RunningArgmax | None = None
        self.triangulator: Triangulator | None = None
        self._key: tuple = ()
        self.active, self.count, self.sheets = False, 0, 1

    @classmethod
    def of(cls, params, publisher, log) -> DepthStage:
        """From the compositor's params (``geometry``, ``depth_k_sigma``, ``depth_min_contrast``,
        ``depth_noise``, ``depth_range_m``)."""
        if len(params.depth_noise) != 2 or min(params.depth_noise) < 0:
            raise GeometryError(f"depth_noise must be [read noise DN, DN per electron], got "
                                f"{params.depth_noise}")
        read, gain = params.depth_noise
        try:
            near_far = depth_range(params.depth_range_m) if params.depth_range_m else None
        except ImagingError as exc:
            raise GeometryError(str(exc)) from None
        return cls(load_geometry(params.geometry), NoiseModel(0.0, read, gain),
                   k_sigma=params.depth_k_sigma, min_contrast=params.depth_min_contrast,
                   source=params.geometry, publisher=publisher, log=log, depth_range_m=near_far)

    def run(self, method: str, scan_id: int, dark: float, saturation, object_free, truth, out: str) -> dict:
        """:meth:`finish`, then publish and write it; its metrics, or {} (no stripe scan, or no depth: the
        log says why)."""
        try:
            depth = self.finish(method, scan_id, dark=dark, saturation=saturation, object_free=object_free,
                                truth_depth=None if truth is None else truth.images.get("depth_m"),
                                truth_geometry=None if truth is None else truth.metrics.get("rig_geometry"))
        except PolarstripeError as exc:
            self.log.warning("scan %d (%s): no depth: %s", scan_id, method, exc)
            return {"error": str(exc)} if self.sheets > 1 else {}
        if depth is None:
            return {}
        self.publisher.publish(depth)
        if out:
            write_depth(out, depth)
        return depth.metrics

    def start(self, method: str, stripes: int, sheets: int = 1) -> None:
        self.active = self.geometry is not None and Method(method).striped and stripes > 0
        self.count, self.sheets = stripes, max(1, sheets)
        if self.running is not None:
            self.running.reset()

    def add(self, image: np.ndarray, pattern: str, angle) -> None:
        if not self.active:
            return
        try:
            p = parse(pattern)
        except PatternError:
            return
        if p.kind != "stripe" or p.count != self.count or p.sheets != self.sheets:
            return
        if self.running is None or self.running.shape != image.shape or self.running.dtype != image.dtype:
            self.running = RunningArgmax(image.shape, image.dtype)
        self.running.add(image, p.index, angle)

    def finish(self, method: str, scan_id: int, *, dark: float, saturation: float | None, object_free=None,
               truth_depth: np.ndarray | None = None, truth_geometry: dict | None = None) -> DepthMap | None:
        """The scan's depth, or None when it is not a stripe scan (or there is no geometry)."""
        if not self.active or self.running is None or not self.running.angles:
            return None
        rc = self.running
        h, w = rc.shape
        g, source = self.geometry, self.source or "default tank"
        if not self.source and truth_geometry:  # the simulator's rig as it is now (its source moves)
            g, source = RigGeometry.from_dict(truth_geometry), "simulator/truth"
        if abs(w / h - g.cam_size[0] / g.cam_size[1]) > 0.01:
            raise GeometryError(f"frames are {w}x{h}, the geometry's camera is {g.cam_size[0]}x"
                                f"{g.cam_size[1]}: not the same aspect")
        key = (h, w, *(np.asarray(v, float).tobytes() for v in g.to_dict().values()))
        if self.triangulator is None or self._key != key:  # the per-pixel rays, once per rig and shape
            self.triangulator, self._key = Triangulator(g, (h, w)), key
        angles = rc.angles
        angle = angles[0]
        if len(angles) == 2:  # E_b: less light over the object-free region
            region = roi_slices("object_free", object_free, (h, w))
            angle = min(angles, key=lambda a: float(np.median(rc.result(a).best[region])))
        noise = NoiseModel(dark, self.noise.read_noise_dn, self.noise.dn_per_electron, saturation)
        votes = rc.result(angle)
        if self.sheets > 1:
            votes = self._positions(votes, truth_depth)
        columns = delineate(votes, stripe_edges(self.count, g.proj_size[0]), noise,
                            k_sigma=self.k_sigma, min_contrast=self.min_contrast)
        depth = self.triangulator.depth(columns)
        points = self.triangulator.points(depth)
        valid = int(len(points))
        m = {"stripes": self.count, "sheets": self.sheets, "valid_pixels": valid,
             "valid_fraction": valid / depth.size, **(self.range_used if self.sheets > 1 else {}),
             "analyzer_deg": angle, "geometry": source}
        if truth_depth is not None and truth_depth.shape == depth.shape:
            truth_depth = np.where(truth_depth > 0, truth_depth, np.nan)  # the simulator's 0: no object
            both = np.isfinite(depth) & np.isfinite(truth_depth)
            err = (depth - truth_depth)[both]
            m["depth_rms_mm"] = float(1e3 * np.sqrt(np.mean(err ** 2))) if err.size else None
            m["valid_fraction_of_objects"] = float(both.sum() / max(1, np.isfinite(truth_depth).sum()))
        return DepthMap(depth_m=depth, points_m=points if valid else None, method=method, scan_id=scan_id,
                        metrics=m)


    def _positions(self, votes: SheetVotes, truth_depth) -> SheetVotes:
        """The votes with each pixel's stripe position for its frame index
        (:mod:`polarstripe.imaging.sheets`); SheetsOverlap (an ImagingError) when the sheets can light one
        pixel within the depth range."""
        near_far, source = self.depth_range_m, "depth_range_m"
        if near_far is None and truth_depth is not None and np.any(truth_depth > 0):
            z = truth_depth[truth_depth > 0]
            near_far, source = (0.9 * float(z.min()), 1.1 * float(z.max())), "simulator/truth"
        self.range_used = {"depth_range_m": None if near_far is None else [float(v) for v in near_far],
                           "depth_range_from": source}
        if near_far is None:
            raise GeometryError(f"a scan of {self.sheets} sheets per frame needs the depth range of the "
                                "objects: the compositor's depth_range_m [near, far]")
        tri = self.triangulator
        lo, hi = epipolar_span(tri.geom, tri.rays, near_far)
        width = tri.geom.proj_size[0]
        check_sheets(self.count, self.sheets, width, lo, hi, near_far)
        index = assign_positions(votes.index, self.count, self.sheets, width, lo, hi)
        return SheetVotes(votes.best, votes.second, index, votes.n_frames)


def write_depth(out: str, depth: DepthMap) -> None:
    """``depth_<method>.npy`` and ``depth_<method>.ply`` in folder ``out`` (each written atomically)."""
    path = os.path.join(out, f"depth_{depth.method}")
    with open(path + ".npy.tmp", "wb") as f:
        np.save(f, np.asarray(depth.depth_m, np.float32))
    os.replace(path + ".npy.tmp", path + ".npy")
    write_ply(path + ".ply", depth.points_m)
