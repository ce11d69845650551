"""Projector–camera calibration from coded images of a checkerboard (docs/depth.md "Calibration").

Per pose of a planar checkerboard of ``cols``×``rows`` inner corners (squares ``square_m`` wide):

1. the camera's corners: ``cv2.findChessboardCornersSB`` on the white (flood) image, refined by
   ``cv2.cornerSubPix`` (:func:`refine_corners`);
2. the projector pixel of every camera pixel: the XOR code's images (Gray code XOR a base bit,
   :func:`polarstripe.imaging.structured_light.calibration_code`), each bit from a pattern against its
   inverse (:func:`polarstripe.imaging.structured_light.decode`), kept where white − black exceeds
   ``black_threshold`` (shadow mask);
3. the projector's corners by local maps (after Moreno & Taubin's local homographies): in each window
   (±1 square) a homography (RANSAC at 2 projector pixels) picks the decoded pixels that fit it, and a
   quadratic in the camera pixel, fitted to those by least squares, maps the corner into the projector. A
   plane seen by two pinholes is a homography, but seen through flat ports it is not: there the
   homography's corner is off by ~0.14 px (in simulation, noise-free; the quadratic's by < 0.01 px). The
   window's decoding noise averages down while the pixels whose bits the medium's noise flipped fall out
   as outliers;
4. ``cv2.calibrateCamera`` for the camera (distortion per ``distortion``) and for the projector (no
   distortion: the light sheets of imaging/triangulation.py assume none), ``cv2.stereoCalibrate`` with
   both intrinsics fixed for the pose X_p = R·X_c + T, then (``joint``) one ``stereoCalibrateExtended``
   refining both intrinsics and the pose together (distortion kept): each view's projector pose is then
   the camera's moved by (R, T), which the separate fits ignore, so the projector's focal length, fitted
   alone to a few coarse corners, gains the camera's constraint. Reprojection RMS [px] per device (of the
   final fit) and of the stereo fit.

Pixel coordinates are OpenCV's (pixel centres at integers); decoded projector pixel j is the pattern column
[j, j+1) of msgs/patterns.py, i.e. OpenCV projector coordinate j. Images are any real dtype; the white one
is scaled to 8 bits between ``dark`` and its brightest pixel for the corner finder.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import cv2
import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.structured_light import Decoded, calibration_code, decode
from polarstripe.msgs.patterns import PatternSpec
from polarstripe.sim.filestorage import read_storage

MIN_POSES = 3
MURK_CONTRAST = 0.1  # a code contrast below this: the medium's scattered light, not the optics, failed it
MURK = "the medium scatters nearly all of the projector's light: the murk"
HALF = 1.0   # decoding window: ± HALF squares around a corner (0.5 to 1 gave alike accuracy in simulation)
DISTORTION = {"none": (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST),
              "radial": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
              "full": 0}


class CalibrationError(PolarstripeError, ValueError):
    """Calibration input that gives no calibration: too few poses, a target not seen, patterns the camera
    cannot decode, images or a file of another rig size. The text says which pose and why."""


class PoseError(CalibrationError):
    """One pose gives nothing: ``pose``, ``reason`` and, where its code did not decode, the code's measured
    ``contrast`` on the board (a fraction of the light; None otherwise)."""

    def __init__(self, pose: int, reason: str, contrast: float | None = None):
        super().__init__(f"pose {pose}: {reason}")
        self.pose, self.reason, self.contrast = pose, reason, contrast


def failed_poses(errors: list[PoseError]) -> str:
    """The failed poses in one line: those the murk failed (code contrast below :data:`MURK_CONTRAST`)
    together, with the range of their contrast; each other one with its reason."""
    murk = [e for e in errors if e.contrast is not None and e.contrast < MURK_CONTRAST]
    parts = []
    if murk:
        lo, hi = (100 * f(e.contrast for e in murk) for f in (min, max))
        span = f"{lo:.1f} %" if round(lo, 1) == round(hi, 1) else f"{lo:.1f}-{hi:.1f} %"
        parts.append(f"pose{'s' if len(murk) > 1 else ''} {', '.join(str(e.pose) for e in murk)}: the code's "
                     f"contrast is {span} of the light, too little to find or decode the board ({MURK})")
    parts += [str(e) for e in errors if e not in murk]
    return "; ".join(parts)


@dataclass(frozen=True)
class Board:
    """A checkerboard target: ``cols``×``rows`` inner corners, squares ``square_m`` [m]."""

    cols: int = 8
    rows: int = 6
    square_m: float = 0.02

    def object_points(self) -> np.ndarray:
        """Corner coordinates on the board (n, 3) float32 [m], z = 0, row-major as OpenCV finds them."""
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.hstack([g * self.square_m, np.zeros((len(g), 1))]).astype(np.float32)


@dataclass
class PoseResult:
    """One pose: camera corners (n, 2), projector corners (n, 2) (NaN where the window did not decode), the
    decoded pixels used, and the local maps' derivatives (n, 2, 2) at the corners (None: not measured)."""

    cam: np.ndarray
    proj: np.ndarray
    decoded: int = 0
    proj_jac: np.ndarray | None = None


@dataclass
class Calibration:
    """The result: intrinsics, distortion, pose (X_p = R·X_c + T), sizes [w, h], RMS [px]."""

    K_cam: np.ndarray
    dist_cam: np.ndarray
    K_proj: np.ndarray
    dist_proj: np.ndarray
    R: np.ndarray
    T: np.ndarray
    cam_size: tuple[int, int]
    proj_size: tuple[int, int]
    rms_cam: float
    rms_proj: float
    rms_stereo: float
    poses: list[PoseResult] = field(default_factory=list)

    def geometry(self) -> dict:
        """The keys of imaging/triangulation.py ``RigGeometry.from_dict``."""
        return {"K_cam": self.K_cam, "dist_cam": self.dist_cam, "K_proj": self.K_proj, "R": self.R,
                "T": self.T.ravel(), "cam_size": list(self.cam_size), "proj_size": list(self.proj_size)}


def to8bit(image: np.ndarray, dark: float, bright: float) -> np.ndarray:
    """uint8 = clip(255·(image − dark)/(bright − dark))."""
    scale = 255.0 / max(float(bright) - float(dark), 1e-12)
    return np.clip((np.asarray(image, float) - dark) * scale, 0, 255).astype(np.uint8)


def find_corners(white8: np.ndarray, board: Board) -> np.ndarray | None:
    """Checkerboard corners (n, 2) float64 in the camera (``cv2.findChessboardCornersSB``), or None."""
    ok, corners = cv2.findChessboardCornersSB(white8, (board.cols, board.rows),
                                              flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    return corners.reshape(-1, 2).astype(float) if ok else None


def refine_corners(white8: np.ndarray, corners: np.ndarray, spacing: float) -> np.ndarray:
    """``cv2.cornerSubPix`` (gradients ⟂ to the edges through the saddle) in a window of ±0.35 square:
    the detector's own estimate is pulled toward the less foreshortened side of a tilted board (in the
    simulator, +0.9 % in the focal length; after this step −0.2 %)."""
    win = int(np.clip(round(0.35 * spacing), 2, 15))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    out = cv2.cornerSubPix(white8, corners.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1), crit)
    return out.reshape(-1, 2).astype(float)


def projector_corners(corners: np.ndarray, decoded: Decoded, *, half: int, min_points: int = 12,
                      ransac_px: float = 2.0) -> tuple[np.ndarray, int, np.ndarray]:
    """Projector corners (n, 2) by local maps (module docstring, step 3), NaN where a window has fewer than
    ``min_points`` decoded pixels; the number of pixels the homographies kept (inliers); and each local
    map's derivative at its corner (n, 2, 2), d(projector pixel)/d(camera pixel): a projector corner carries
    its camera corner's error multiplied by it (imaging/port_calibration.py takes it out)."""
    h, w = decoded.valid.shape
    out, total = np.full((len(corners), 2), np.nan), 0
    jac = np.full((len(corners), 2, 2), np.nan)
    for k, (x, y) in enumerate(corners):
        x0, x1 = max(int(round(x)) - half, 0), min(int(round(x)) + half + 1, w)
        y0, y1 = max(int(round(y)) - half, 0), min(int(round(y)) + half + 1, h)
        vv, uu = np.mgrid[y0:y1, x0:x1]
        m = decoded.valid[y0:y1, x0:x1]
        if m.sum() < min_points:
            continue
        cam = np.column_stack([uu[m], vv[m]]).astype(np.float64)
        proj = np.column_stack([decoded.col[y0:y1, x0:x1][m], decoded.row[y0:y1, x0:x1][m]]).astype(float)
        H, inl = cv2.findHomography(cam, proj, cv2.RANSAC, ransac_px)
        if H is None:
            continue
        inl = inl.ravel().astype(bool)
        if inl.sum() < min_points:
            continue
        total += int(inl.sum())
        out[k], jac[k] = _local_quadratic(cam[inl] - (x, y), proj[inl], half)
    return out, total, jac


def _local_quadratic(offsets: np.ndarray, proj: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """The value (2,) and derivative (2, 2) at offset 0 of the least-squares quadratic x_p = a + B·u + u·C·u
    in u = offset/``half`` (each projector coordinate; 6 coefficients)."""
    u, v = (offsets / half).T
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    coef, *_ = np.linalg.lstsq(A, proj, rcond=None)
    return coef[0], coef[1:3].T / half


def camera_corners(white: np.ndarray, black: np.ndarray, board: Board, *, pose: int = 0):
    """Step 1: the camera's corners (n, 2), the decoding window's half size [px] (one square), and the 8-bit
    scaling (dark, bright, white8, black8).

    :raises CalibrationError: the white frame is dark, or the board is not found in it."""
    dark = float(np.median(black))
    bright = float(np.percentile(white, 99.5))
    if bright - dark <= 0:
        raise PoseError(pose, "the white frame is no brighter than the black one")
    w8, b8 = to8bit(white, dark, bright), to8bit(black, dark, bright)
    corners = find_corners(w8, board)
    if corners is None:
        raise PoseError(pose, f"the {board.cols}x{board.rows} checkerboard is not seen in the white frame")
    spacing = float(np.median(np.linalg.norm(np.diff(corners.reshape(board.rows, board.cols, 2), axis=1),
                                             axis=2)))
    return refine_corners(w8, corners, spacing), max(3, int(round(HALF * spacing))), (dark, bright, w8, b8)


def decode_pose(white: np.ndarray, black: np.ndarray, frames: list[np.ndarray], board: Board,
                proj_size: tuple[int, int], *, pose: int = 0, code: list[PatternSpec] | None = None,
                black_threshold: int = 10) -> PoseResult:
    """Steps 1–3 for one pose. ``frames``: those of ``code`` (default
    :func:`~polarstripe.imaging.structured_light.calibration_code` of ``proj_size``) in order;
    ``white``/``black``: the flood and off frames; a pixel is decoded where white − black exceeds
    ``black_threshold`` of 255 of the white frame's range.

    :raises CalibrationError: the board is not found, or too few of its corners decode in the projector
        (the text gives the code's contrast there: the murk's signature is a contrast of a few per cent)."""
    code = calibration_code(*proj_size) if code is None else code
    if len(frames) != len(code):
        raise CalibrationError(f"pose {pose}: {len(frames)} code frames, a {proj_size[0]}x{proj_size[1]} "
                               f"projector needs {len(code)}")
    shapes = {np.shape(a) for a in (white, black, *frames)}
    if len(shapes) != 1:
        raise CalibrationError(f"pose {pose}: frames of different sizes {sorted(shapes)}")
    dark, bright = float(np.median(black)), float(np.percentile(white, 99.5))
    decoded = decode(frames, code, proj_size, white, black,
                     lit_threshold=black_threshold * max(bright - dark, 0.0) / 255)
    try:
        corners, half, _ = camera_corners(white, black, board, pose=pose)
    except PoseError as exc:      # in the murk the board's own contrast goes with the code's
        c = float(np.nanmedian(decoded.contrast)) if decoded.valid.any() else None
        if c is None or c >= MURK_CONTRAST:
            raise
        raise PoseError(pose, f"{exc.reason}: the code's contrast over the lit image is {100 * c:.1f} % of "
                              f"the light ({MURK})", c) from None
    proj, total, jac = projector_corners(corners, decoded, half=half)
    good = np.isfinite(proj).all(axis=1)
    if good.mean() < 0.9:
        head = f"only {int(good.sum())} of {len(corners)} corners decode in the projector"
        h, w = decoded.valid.shape
        x0, y0 = np.maximum(np.floor(corners.min(axis=0)).astype(int) - half, 0)
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + half + 1
        region = decoded.contrast[y0:min(y1, h), x0:min(x1, w)]
        if not np.isfinite(region).any():
            raise PoseError(pose, f"{head}: the projector does not light the board "
                                  "(a shadow, or out of view?)")
        c = float(np.nanmedian(region))
        why = MURK if c < MURK_CONTRAST else "saturated or out of focus?"
        raise PoseError(pose, f"{head}: the code's contrast on the board is {100 * c:.1f} % of the light "
                              f"({why})", c)
    return PoseResult(corners, proj, total, jac)


def calibrate(poses: list[PoseResult], board: Board, cam_size: tuple[int, int], proj_size: tuple[int, int],
              *, distortion: str = "radial", joint: bool = True) -> Calibration:
    """Step 4: both intrinsics and the projector's pose from the decoded poses (module docstring).

    :raises CalibrationError: fewer than :data:`MIN_POSES` poses, or a calibration that does not converge."""
    if len(poses) < MIN_POSES:
        raise CalibrationError(f"{len(poses)} usable poses: a calibration needs at least {MIN_POSES}")
    if distortion not in DISTORTION:
        raise CalibrationError(f"distortion {distortion!r} is not one of {', '.join(DISTORTION)}")
    obj, cam, proj = [], [], []
    full = board.object_points()
    for p in poses:
        good = np.isfinite(p.proj).all(axis=1)
        obj.append(full[good])
        cam.append(p.cam[good].astype(np.float32).reshape(-1, 1, 2))
        proj.append(p.proj[good].astype(np.float32).reshape(-1, 1, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms_c, Kc, dc, _, _ = cv2.calibrateCamera(obj, cam, tuple(cam_size), None, None,
                                                  flags=DISTORTION[distortion], criteria=crit)
        rms_p, Kp, dp, _, _ = cv2.calibrateCamera(obj, proj, tuple(proj_size), None, None,
                                                  flags=DISTORTION["none"], criteria=crit)
        _, *_, R, T, _, _ = cv2.stereoCalibrate(obj, cam, proj, Kc, dc, Kp, dp, tuple(cam_size),
                                                flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
        if joint:  # both intrinsics again, with every view's projector pose tied to its camera pose
            fix = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_TANGENT_DIST
            rms_s, Kc, dc, Kp, dp, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
                obj, cam, proj, Kc, dc, Kp, dp, tuple(cam_size), R, T,
                flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_USE_EXTRINSIC_GUESS | fix, criteria=crit)
            n = np.array([len(o) for o in obj], float)
            rms_c, rms_p = (float(np.sqrt(np.sum(per_view[:, i] ** 2 * n) / n.sum())) for i in (0, 1))
        else:
            rms_s = float(np.sqrt((rms_c ** 2 + rms_p ** 2) / 2))
    except cv2.error as exc:
        raise CalibrationError(f"calibration did not converge: {exc.err}") from None
    if not all(np.isfinite(v).all() for v in (Kc, Kp, R, T)):
        raise CalibrationError("calibration did not converge (non-finite result)")
    return Calibration(Kc, dc.ravel(), Kp, dp.ravel(), R, T.ravel(), tuple(cam_size), tuple(proj_size),
                       float(rms_c), float(rms_p), float(rms_s), list(poses))


def coverage_image(poses: list[PoseResult], proj_size: tuple[int, int], *, width: int = 640) -> np.ndarray:
    """The projector plane (BGR uint8, ``width`` wide) with every pose's projector corners and board outline:
    where the calibration has data."""
    pw, ph = proj_size
    s = width / pw
    img = np.full((max(1, int(round(ph * s))), width, 3), 32, np.uint8)
    for k, p in enumerate(poses):
        hue = int(180 * k / max(1, len(poses)))
        color = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2BGR)[0, 0].tolist()
        good = np.isfinite(p.proj).all(axis=1)
        pts = p.proj[good] * s
        if len(pts) >= 3:
            hull = cv2.convexHull(pts.astype(np.float32)).astype(np.int32)
            cv2.polylines(img, [hull], True, color, 1, cv2.LINE_AA)
        for x, y in pts:
            cv2.circle(img, (int(round(x)), int(round(y))), 2, color, -1, cv2.LINE_AA)
    return img


# ---------------------------------------------------------------------------------------------- the file

FILE_KEYS = ("K_cam", "dist_cam", "K_proj", "dist_proj", "R", "T", "cam_size", "proj_size")
PORT_KEYS = ("port_cam", "port_proj")  # behind flat ports: 8 numbers each (imaging/port_calibration.py)
_COLUMNS = ("T", "dist_cam", "dist_proj", "cam_size", "proj_size", *PORT_KEYS)
_SIZES = {"K_cam": 9, "K_proj": 9, "R": 9, "T": 3, "cam_size": 2, "proj_size": 2, "port_cam": 8,
          "port_proj": 8}  # numbers per key


def save(path: str, geom: dict, extra: dict | None = None) -> None:
    """Write a calibration as OpenCV ``FileStorage`` YAML (XML/JSON by the name's extension) atomically: a
    temporary file beside ``path``, then a rename, so a failed run leaves the previous file whole.
    ``geom``: the :data:`FILE_KEYS` (``dist_*`` optional) and, for a rig behind flat ports, the
    :data:`PORT_KEYS`; ``extra``: numbers or strings (RMS, poses…)."""
    base, ext = os.path.splitext(path)
    tmp = f"{base}.tmp{os.getpid()}{ext or '.yaml'}"
    fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
    try:
        for key in FILE_KEYS + PORT_KEYS:
            if geom.get(key) is None:
                continue
            a = np.asarray(geom[key], np.float64)
            fs.write(key, a.reshape((-1, 1) if key in _COLUMNS else (3, 3)))
        for key, value in (extra or {}).items():
            fs.write(key, value)
    finally:
        fs.release()
    os.replace(tmp, path)


def load(path: str, *, cam_size=None, proj_size=None) -> dict:
    """The matrices of a calibration file (``dist_*`` zeros when absent, ``port_*`` only when present: a
    rig behind flat ports, imaging/refraction.py). With ``cam_size``/``proj_size``
    ([w, h]) a file of another rig size is an error (a camera binned by an integer factor is the same rig).

    :raises CalibrationError: no such file, not a FileStorage file, a key missing, another rig size."""
    try:
        out = read_storage(path, FILE_KEYS + PORT_KEYS, optional=("dist_cam", "dist_proj", *PORT_KEYS))
    except ValueError as exc:
        raise CalibrationError(f"calibration {path!r}: {exc}") from None
    for key in PORT_KEYS:
        if out[key] is None:  # a pinhole rig
            del out[key]
        else:
            out[key] = out[key].ravel()
    for key, value in out.items():
        if value is None:  # no distortion
            out[key] = np.zeros(5)
        elif key in _SIZES and (value.size != _SIZES[key] or not np.all(np.isfinite(value))):
            raise CalibrationError(f"calibration {path!r}: {key} must be {_SIZES[key]} finite numbers, "
                                   f"got {value.size}{'' if np.all(np.isfinite(value)) else ' (NaN or inf)'}")
    check_rig_size(out, path, cam_size=cam_size, proj_size=proj_size)
    return out


def check_rig_size(geom: dict, name: str, *, cam_size=None, proj_size=None) -> None:
    """Raise :class:`CalibrationError` unless the calibration's sizes are the rig's: the projector exactly,
    the camera up to an integer binning factor (same aspect)."""
    fc = [int(v) for v in np.ravel(geom["cam_size"])]
    fp = [int(v) for v in np.ravel(geom["proj_size"])]
    if proj_size is not None and fp != [int(v) for v in proj_size]:
        raise CalibrationError(f"calibration {name!r} is for a {fp[0]}x{fp[1]} projector, the rig's is "
                               f"{int(proj_size[0])}x{int(proj_size[1])}: calibrate this rig")
    if cam_size is not None:
        w, h = (int(v) for v in cam_size)
        ok = (fc[0] % w == 0 and fc[1] % h == 0 and fc[0] // w == fc[1] // h) or \
             (w % fc[0] == 0 and h % fc[1] == 0 and w // fc[0] == h // fc[1])
        if not ok:
            raise CalibrationError(f"calibration {name!r} is for a {fc[0]}x{fc[1]} camera, the rig's is "
                                   f"{w}x{h}: calibrate this rig")
