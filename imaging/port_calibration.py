"""A refractive camera model fitted by calibration: the flat ports of camera and projector (docs/depth.md
"Calibration through a port"; Agrawal, Ramalingam, Taguchi & Chari, "A theory of multi-layer flat refractive
geometry", CVPR 2012).

Behind a flat port a device is no longer a pinhole (docs/physics.md §11): the pixel of a water point Y (in
the device's OpenCV frame) is that of the air ray a which reaches Y through the port,

    x = π(K, dist, a),   a = the air ray of :func:`polarstripe.sim.port.light_to` (Snell at both faces),

the port being its unit normal N (device frame), the inner face's distance d from the pinhole, the glass
thickness t and the indices n_a, n_g, n_w. t and the indices come from the housing's data sheet, the
camera lens's distortion from a calibration in air (none in the simulator); the fit finds N and d of each
device together with the intrinsics (camera and projector K), the
projector's pose (R, T; X_p = R·X_c + T) and every board pose (R_i, t_i; Y = R_i·X + t_i), by nonlinear
least squares (``scipy.optimize.least_squares``) on the reprojection error of the camera's and the
projector's corners (those :mod:`polarstripe.imaging.calibration` measured). A projector corner is its
camera corner carried into the projector by the decoded map, x_p = M(x_c), so it carries the camera
corner's error e_c as J·e_c (J = dM/dx_c, ~3 times larger at 320 camera to 1024 projector pixels): the
projector's residual is taken as r_p − J·r_c, the map's own (decoding) error, where J is measured with
the corner (``PoseResult.proj_jac``; none: zero). Fitted as independent errors, that shared error put the
simulated camera's d 2.6 mm off (σ 2.1 mm); with it taken out, 0.3 mm (σ 0.4 mm; as one wall 0.13, σ
0.22). A port of indices 1 is the pinhole, and its d and N are then not observable. When both devices look
through one flat wall (``one_wall``: a tank's) the camera's port is the projector's wall seen from the
camera, three parameters fewer. The lens distortion stays fixed: a radial distortion
and the port's distance change the image nearly alike (in simulation, fitting k1, k2 as well took the
camera's d from 18.7 mm to 0 and put 6 mm of bias in the depth).

The start: the pinhole calibration through the port (its K's focal lengths divided by n_w/n_a: the water
narrows the field of view), each board pose from ``cv2.solvePnP`` with that pinhole, the port on the
device's axis; the fit runs from each of :data:`START_DISTANCES_M` and keeps the least cost, then leaves out
the misplaced corners (:data:`OUTLIER`) and fits again. It reports each port's standard errors
(:func:`jackknife_errors`; :func:`standard_errors` below 4 poses): a port square to its device's axis is
nearly a pinhole of longer focal length whose centre moves along the axis with d, which the projector's
pose T takes up, so its d is observed through the port's higher-order bending only (docs/depth.md
"Calibration through a port").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from polarstripe.imaging.calibration import Board, Calibration, CalibrationError
from polarstripe.imaging.refraction import port_of
from polarstripe.sim.port import light_to
from polarstripe.sim.scene_port import PORT_PRESETS
from scipy.optimize import least_squares

START_DISTANCES_M = (0.01, 0.05)  # a start at 5 mm went to d = 0 in simulation; 1 to 8 cm did not
OUTLIER = 5.0        # a corner whose error exceeds this many times its device's median is left out …
OUTLIER_MIN_PX = 0.5  # … and this many pixels
MISS_PX = 1e3        # the residual of a point not beyond the port's outer face (far from any solution)
JACKKNIFE_MIN_POSES = 4  # from this many poses the standard errors are the jackknife's, below: linearized


@dataclass(frozen=True)
class PortSpec:
    """What a housing's data sheet gives: glass ``thickness_m`` [m] and the indices of air, glass, water."""

    thickness_m: float
    n_air: float = 1.0
    n_glass: float = 1.5
    n_water: float = 1.333

    def numbers(self, normal, distance_m: float) -> np.ndarray:
        """The 8 numbers of imaging/refraction.py ``port_of``: normal (3), d, t, n_a, n_g, n_w."""
        n = np.asarray(normal, float)
        return np.array([*(n / np.linalg.norm(n)), distance_m, self.thickness_m, self.n_air, self.n_glass,
                         self.n_water])


def parse_port_spec(text: str) -> PortSpec | None:
    """A data sheet as text: ``""`` none (the pinhole), a preset of sim/scene_port.py (``glass_tank``), or
    ``THICKNESS_M,N_AIR,N_GLASS,N_WATER``.

    :raises CalibrationError: anything else (one line)."""
    text = text.strip()
    if not text:
        return None
    if text in PORT_PRESETS:
        p = PORT_PRESETS[text]
        return PortSpec(p.thickness_m, p.n_air, p.n_glass, p.n_water)
    try:
        t, n_a, n_g, n_w = (float(v) for v in text.split(","))
    except ValueError:
        raise CalibrationError(f"port {text!r}: give {', '.join(PORT_PRESETS)} or THICKNESS_M,N_AIR,N_GLASS,"
                               "N_WATER") from None
    if not (np.isfinite(t) and t >= 0 and all(1.0 <= n <= 4.0 for n in (n_a, n_g, n_w)) and n_w >= n_a):
        raise CalibrationError(f"port {text!r}: need a thickness >= 0 m, indices in [1, 4], n_water >= n_air")
    return PortSpec(t, n_a, n_g, n_w)


def parse_distortion(text: str) -> np.ndarray | None:
    """A lens's distortion from a calibration in air as text: ``""`` none, or ``K1,K2[,P1,P2[,K3]]`` (OpenCV's
    order), which :func:`fit_ports` holds fixed.

    :raises CalibrationError: anything else (one line)."""
    text = text.strip()
    if not text:
        return None
    try:
        coeffs = np.array([float(v) for v in text.split(",")])
    except ValueError:
        coeffs = np.array([])
    if coeffs.size not in (2, 4, 5) or not np.isfinite(coeffs).all():
        raise CalibrationError(f"lens distortion {text!r}: give K1,K2 or K1,K2,P1,P2 or K1,K2,P1,P2,K3 "
                               "(OpenCV's, from a calibration in air)")
    return np.concatenate([coeffs, np.zeros(5 - coeffs.size)])


def names_a_wall(text: str) -> bool:
    """Whether a data sheet as text names a tank's wall (``glass_tank``): one flat wall before both devices
    (:func:`fit_ports` ``one_wall``), not a port on each."""
    return text.strip() == "glass_tank"


@dataclass
class PortCalibration:
    """The refractive rig: intrinsics (in the air behind the ports), pose X_p = R·X_c + T, each port's 8
    numbers (``port_cam``, ``port_proj``), reprojection RMS [px] per device and together (``rms_stereo``),
    the corners left out and the ports' standard errors (``sigma``)."""

    K_cam: np.ndarray
    dist_cam: np.ndarray
    K_proj: np.ndarray
    R: np.ndarray
    T: np.ndarray
    port_cam: np.ndarray
    port_proj: np.ndarray
    cam_size: tuple[int, int]
    proj_size: tuple[int, int]
    rms_cam: float
    rms_proj: float
    rms_stereo: float
    dropped: int = 0          # corners left out as misplaced (module docstring)
    sigma: dict = field(default_factory=dict)  # standard errors (:func:`jackknife_errors`)

    def geometry(self) -> dict:
        """The keys of imaging/triangulation.py ``RigGeometry.from_dict`` (with the ports)."""
        return {"K_cam": self.K_cam, "dist_cam": self.dist_cam, "K_proj": self.K_proj, "R": self.R,
                "T": self.T.ravel(), "cam_size": list(self.cam_size), "proj_size": list(self.proj_size),
                "port_cam": self.port_cam, "port_proj": self.port_proj}


def project(K: np.ndarray, dist: np.ndarray | None, port, points: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) (OpenCV coordinates) of device-frame ``points`` (n, 3) [m] seen through ``port`` (8
    numbers, or None: the pinhole), NaN where a point is not beyond the port's outer face."""
    points = np.asarray(points, float).reshape(-1, 3)
    geo = port_of(port)
    a = points if geo is None else light_to(geo, points).air
    ok = np.isfinite(a).all(axis=1) & (a[:, 2] > 0)
    out = np.full((len(points), 2), np.nan)
    if ok.any():
        d = np.zeros(5) if dist is None else np.asarray(dist, float).ravel()
        px, _ = cv2.projectPoints(a[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.asarray(K, float), d)
        out[ok] = px.reshape(-1, 2)
    return out


def _normal(tilt) -> np.ndarray:
    n = np.array([tilt[0], tilt[1], 1.0])
    return n / np.linalg.norm(n)


def _K(v) -> np.ndarray:
    return np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])


class _Layout:
    """The parameter vector: camera K (4), projector K (4), the camera's port (its normal's tilt, 2, and
    log d, 1; not there for ``one_wall``), the projector's port (3), the projector's pose (rvec 3, T 3), and
    6 per board pose (rvec, t)."""

    def __init__(self, n_poses: int, one_wall: bool = False):
        self.n_poses, self.one_wall = n_poses, one_wall
        self.shared = 4 + 4 + (0 if one_wall else 3) + 3 + 6
        self.size = self.shared + 6 * n_poses

    def unpack(self, x):
        """kc, kp, the camera's port's 3 numbers (None for ``one_wall``), the projector's, rt, poses."""
        i = 8 if self.one_wall else 11
        pc = None if self.one_wall else x[8:11]
        return x[:4], x[4:8], pc, x[i:i + 3], x[i + 3:i + 9], x[i + 9:].reshape(-1, 6)

    def ports(self, x, specs) -> tuple[np.ndarray, np.ndarray]:
        """Both ports' 8 numbers. For ``one_wall`` the camera's is the projector's wall seen from the camera:
        with X_p = R·X_c + T the plane N_p·X_p = d_p is N_c·X_c = d_c, N_c = Rᵀ·N_p, d_c = d_p − N_p·T."""
        _, _, pc, pp, rt, _ = self.unpack(x)
        n_p, d_p = _normal(pp[:2]), np.exp(pp[2])
        if pc is None:
            R = cv2.Rodrigues(rt[:3])[0]
            n_c, d_c = R.T @ n_p, d_p - n_p @ rt[3:]
        else:
            n_c, d_c = _normal(pc[:2]), np.exp(pc[2])
        return specs[0].numbers(n_c, d_c), specs[1].numbers(n_p, d_p)


def _residuals(x, layout: _Layout, specs: tuple[PortSpec, PortSpec], data, split: bool = False):
    """Reprojection residuals of parameter vector ``x``: the camera's corners, then the projector's less
    the camera's residual carried by the decoded map's derivative (module docstring)."""
    kc, kp, _, _, rt, poses = layout.unpack(x)
    obj, cam, proj, owner, dist, jac = data
    port_c, port_p = layout.ports(x, specs)
    if port_c[3] < 0:            # a shared wall behind the camera's pinhole: far from any solution
        n = 2 * owner.size
        return (np.full(n, np.nan), np.full(n, np.nan)) if split else np.full(2 * n, MISS_PX)
    R, T = cv2.Rodrigues(rt[:3])[0], rt[3:]
    Rs = np.stack([cv2.Rodrigues(v)[0] for v in poses[:, :3]])[owner]        # each corner's board pose
    Y = np.einsum("nij,nj->ni", Rs, obj) + poses[owner, 3:]
    rc = project(_K(kc), dist, port_c, Y) - cam
    # the projector's corner is the camera's carried by the decoded map: take the camera's error out
    rp = (project(_K(kp), None, port_p, Y @ R.T + T) - proj - np.einsum("nij,nj->ni", jac, rc)).ravel()
    rc = rc.ravel()
    if split:
        return rc, rp
    return np.nan_to_num(np.concatenate([rc, rp]), nan=MISS_PX)


def _jacobian(x, layout: _Layout, specs, data) -> np.ndarray:
    """Central differences, the board poses' columns in 6 groups: a corner depends on its own pose only,
    so one evaluation moves parameter k of every pose at once."""
    owner = data[3]
    n = owner.size
    shared = layout.shared
    point = np.concatenate([np.repeat(np.arange(n), 2)] * 2)            # residual -> corner
    J = np.zeros((4 * n, layout.size))
    steps = 1e-6 * np.maximum(np.abs(x), 1e-2)
    for cols in [[j] for j in range(shared)] + [list(range(shared + k, layout.size, 6)) for k in range(6)]:
        e = np.zeros_like(x)
        e[cols] = steps[cols]
        diff = (_residuals(x + e, layout, specs, data) - _residuals(x - e, layout, specs, data))
        if len(cols) == 1:
            J[:, cols[0]] = diff / (2 * steps[cols[0]])
        else:
            own = np.asarray(cols)[owner[point]]
            J[np.arange(4 * n), own] = diff / (2 * steps[own])
    return J


def _board_poses(obj, cam, K, dist) -> np.ndarray:
    out = []
    for o, c in zip(obj, cam, strict=True):
        ok, rvec, tvec = cv2.solvePnP(o, c, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise CalibrationError("the refractive fit found no start pose of a board (cv2.solvePnP)")
        out.append(np.concatenate([rvec.ravel(), tvec.ravel()]))
    return np.array(out)


def fit_ports(cal: Calibration, board: Board, spec_cam: PortSpec, spec_proj: PortSpec, *,
              lens_distortion=None, start_distances_m=START_DISTANCES_M, one_wall: bool = False
              ) -> PortCalibration:
    """The refractive rig from the corners of a pinhole calibration through the ports (module docstring).
    ``lens_distortion``: the camera lens's OpenCV coefficients, from a calibration in air (None: none).
    ``one_wall``: both devices look through one flat wall (a tank's, ``glass_tank``): the camera's port is
    the projector's seen from the camera (:class:`_Layout` ``ports``), which ties the camera's weakly
    observed d to the projector's tilted port and the pose (module docstring).

    :raises CalibrationError: too few poses, a fit that does not converge, or ``one_wall`` with two data
        sheets."""
    if one_wall and spec_cam != spec_proj:
        raise CalibrationError("one wall before both devices needs one data sheet; got two different ones")
    dist = np.zeros(5)
    if lens_distortion is not None:
        coeffs = np.asarray(lens_distortion, float).ravel()
        dist[:coeffs.size] = coeffs[:5]
    full = board.object_points().astype(float)
    obj, cam, proj, jac = [], [], [], []
    for p in cal.poses:
        good = np.isfinite(p.proj).all(axis=1)
        obj.append(full[good])
        cam.append(p.cam[good].astype(float))
        proj.append(p.proj[good].astype(float))
        maps = np.zeros((len(good), 2, 2)) if p.proj_jac is None else np.asarray(p.proj_jac, float)
        jac.append(np.nan_to_num(maps[good]))
    if len(obj) < 3:
        raise CalibrationError(f"{len(obj)} poses: the refractive fit needs at least 3")
    layout = _Layout(len(obj), one_wall)
    owner = np.concatenate([np.full(len(o), k) for k, o in enumerate(obj)])
    data = (np.concatenate(obj), np.concatenate(cam), np.concatenate(proj), owner, dist, np.concatenate(jac))
    scale_c, scale_p = spec_cam.n_air / spec_cam.n_water, spec_proj.n_air / spec_proj.n_water
    Kc, Kp = np.asarray(cal.K_cam, float), np.asarray(cal.K_proj, float)
    kc = np.array([Kc[0, 0] * scale_c, Kc[1, 1] * scale_c, Kc[0, 2], Kc[1, 2]])
    kp = np.array([Kp[0, 0] * scale_p, Kp[1, 1] * scale_p, Kp[0, 2], Kp[1, 2]])
    poses = _board_poses(obj, cam, Kc, np.asarray(cal.dist_cam, float))
    rt = np.concatenate([cv2.Rodrigues(np.asarray(cal.R, float))[0].ravel(), np.ravel(cal.T)])
    specs = (spec_cam, spec_proj)
    starts = [np.concatenate([kc, kp, [0.0, 0.0, np.log(d0)] * (1 if one_wall else 2), rt, poses.ravel()])
              for d0 in start_distances_m]
    x = min((_solve(x0, layout, specs, data) for x0 in starts), key=lambda sol: sol.cost).x
    keep = _inliers(x, layout, specs, data)
    if not keep.all():        # a corner the detector misplaced: drop it, fit again from here
        data = tuple(a[keep] for a in data[:4]) + (dist, data[5][keep])
        x = _solve(x, layout, specs, data).x
    return _result(x, layout, specs, data, cal, int((~keep).sum()))


def _solve(x0, layout, specs, data):
    try:
        return least_squares(_residuals, x0, args=(layout, specs, data), jac=_jacobian, method="lm",
                             x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
    except ValueError as exc:
        raise CalibrationError(f"the refractive fit did not converge: {exc}") from None


def _inliers(x, layout, specs, data) -> np.ndarray:
    """Corners whose error, in the camera and in the projector, is within :data:`OUTLIER` times that
    device's median corner error or :data:`OUTLIER_MIN_PX`."""
    keep = np.ones(data[3].size, bool)
    for r in _residuals(x, layout, specs, data, split=True):
        e = np.hypot(*r.reshape(-1, 2).T)
        keep &= np.nan_to_num(e, nan=np.inf) <= max(OUTLIER * np.nanmedian(e), OUTLIER_MIN_PX)
    return keep


def _result(x, layout, specs, data, cal, dropped: int) -> PortCalibration:
    kc, kp, _, _, rt, _ = layout.unpack(x)
    rc, rp = _residuals(x, layout, specs, data, split=True)
    if not (np.isfinite(rc).all() and np.isfinite(rp).all() and np.isfinite(x).all()):
        raise CalibrationError("the refractive fit did not converge (a corner outside the port)")
    plain = rp + np.einsum("nij,nj->ni", data[5], rc.reshape(-1, 2)).ravel()   # the projector's own error
    rms_c, rms_p = (float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2)) for r in (rc, plain))
    rms = float(np.sqrt(np.mean(np.concatenate([rc, plain]).reshape(-1, 2) ** 2) * 2))
    port_c, port_p = layout.ports(x, specs)
    sigma = (jackknife_errors(x, layout, specs, data) if layout.n_poses >= JACKKNIFE_MIN_POSES
             else standard_errors(x, layout, specs, data, rc, rp))
    return PortCalibration(_K(kc), data[4].copy(), _K(kp), cv2.Rodrigues(rt[:3])[0], rt[3:].copy(), port_c,
                           port_p, tuple(cal.cam_size), tuple(cal.proj_size), rms_c, rms_p, rms, dropped,
                           sigma)


def _port_numbers(layout: _Layout, x, specs) -> np.ndarray:
    """Both ports' unit normal and d, 8 numbers (camera, projector)."""
    return np.concatenate([np.r_[p[:3] / np.linalg.norm(p[:3]), p[3]] for p in layout.ports(x, specs)])


def _sigmas(var: np.ndarray) -> dict:
    """Each port's d [m] and normal [deg] standard errors from the variances of :func:`_port_numbers`
    (the normal's angle: the square root of its three components' summed variance)."""
    return {k: v for i, name in enumerate(("port_cam", "port_proj"))
            for k, v in ((f"{name}_d_sigma_m", float(np.sqrt(max(var[4 * i + 3], 0.0)))),
                         (f"{name}_tilt_sigma_deg", float(np.degrees(np.sqrt(max(var[4 * i:4 * i + 3].sum(),
                                                                                 0.0))))))}


def jackknife_errors(x, layout: _Layout, specs, data) -> dict:
    """Each port's d [m] and normal [deg] standard errors by the jackknife over the board poses: θ_i, the
    ports fitted again without pose i (from the whole fit's solution), and σ² = (m−1)/m·Σᵢ(θ_i − θ̄)². Unlike
    the linearized covariance (:func:`standard_errors`) it holds what a pose's corners share, which their
    residuals do not show: on corners found by decoding, the linearized σ was 1.4–1.8 times too small, the
    jackknife's within 0.8–1.2 (docs/depth.md "Calibration through a port")."""
    m, owner = layout.n_poses, data[3]
    smaller = _Layout(m - 1, layout.one_wall)
    thetas = []
    for i in range(m):
        keep = owner != i
        sub = (data[0][keep], data[1][keep], data[2][keep], owner[keep] - (owner[keep] > i), data[4],
               data[5][keep])
        cols = np.r_[0:layout.shared + 6 * i, layout.shared + 6 * (i + 1):layout.size]
        thetas.append(_port_numbers(smaller, _solve(x[cols], smaller, specs, sub).x, specs))
    t = np.array(thetas)
    return _sigmas((m - 1) / m * ((t - t.mean(axis=0)) ** 2).sum(axis=0))


def standard_errors(x, layout, specs, data, rc, rp) -> dict:
    """Each port's d [m] and normal [deg] standard errors from the fit: the covariance C = (JᵀWJ)⁻¹ of the
    parameters with each device's residuals weighted by its own RMS (W = 1/σ²), carried to each port's d and
    unit normal N by their derivatives G in the shared parameters (σ_d² = G_d·C·G_dᵀ, the normal's angle
    σ = √trace(G_N·C·G_Nᵀ))."""
    w = np.concatenate([np.full(rc.size, 1.0 / max(np.sqrt(np.mean(rc ** 2)), 1e-12)),
                        np.full(rp.size, 1.0 / max(np.sqrt(np.mean(rp ** 2)), 1e-12))])
    Jw = _jacobian(x, layout, specs, data) * w[:, None]
    cov = np.linalg.pinv(Jw.T @ Jw)[:layout.shared, :layout.shared]
    G = np.zeros((8, layout.shared))        # d(port numbers)/d(parameter)
    for j in range(layout.shared):
        h = 1e-7 * max(abs(x[j]), 1.0)
        e = np.zeros_like(x)
        e[j] = h
        G[:, j] = (_port_numbers(layout, x + e, specs) - _port_numbers(layout, x - e, specs)) / (2 * h)
    return _sigmas(np.einsum("ij,jk,ik->i", G, cov, G))
