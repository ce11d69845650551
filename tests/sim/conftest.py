"""Plain, slow reference code for the sim tests: geometry and integrands written straight from docs/physics.md
and docs/scene-format.md."""

import numpy as np
from scipy.optimize import brentq


def frame(position, look_at, up, fov_deg, w, h):
    p = np.array(position, float)
    f = np.array(look_at, float) - p
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    u = np.cross(r, f)
    s = 2 * np.tan(np.radians(fov_deg) / 2) / w
    return p, f, r, u, s, w, h


def ray(cam, i, j):
    p, f, r, u, s, w, h = cam
    d = f + ((j + 0.5) - w / 2) * s * r - ((i + 0.5) - h / 2) * s * u
    return d / np.linalg.norm(d)


def hg(mu, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5)


def tthg_params(g):
    def gb(gf):
        return -0.30614 + 1.0006 * gf - 0.01826 * gf ** 2 + 0.03644 * gf ** 3

    gf = brentq(lambda x: x * gb(x) / (1 + gb(x) - x) - g, 0.31, 0.9999999, xtol=1e-15)
    b = gb(gf)
    return gf, b, b * (1 + b) / ((gf + b) * (1 + b - gf))


def tthg(mu, g):
    gf, gb, a = tthg_params(g)
    return a * hg(mu, gf) + (1 - a) * hg(mu, -gb)


def slab(o, d, lo, hi):
    t0, t1 = 0.0, np.inf
    for k in range(3):
        if d[k] == 0:
            if not lo[k] <= o[k] <= hi[k]:
                return 0.0, -1.0
            continue
        a, b = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return t0, t1


def projector_pixel(proj, y):
    p, f, r, u, s, w, h = proj
    v = np.asarray(y) - p
    vf = v @ f
    if vf <= 0:
        return None
    return w / 2 + (v @ r / vf) / s, h / 2 - (v @ u / vf) / s


def mueller_intensity(scene):
    """f(k_in, k_out): intensity of light scattered from the scene's polarized source along k_in into k_out,
    per unit of the phase function: 1 + (m12/m11)·Q_in with the depolarized-Rayleigh reduced matrix (Hansen &
    Travis) and Q_in = DOP_L cos 2ψ, ψ the angle between the source's E-field and the scattering plane."""
    pr, dop = scene.projector, scene.medium.dop
    if dop.model != "rayleigh" or pr.polarization.dop == 0:
        return lambda k_in, k_out: 1.0
    _, _, r, u, *_ = frame(pr.position, pr.look_at, pr.up, 60.0, 2, 2)
    a = np.radians(pr.polarization.angle_deg)
    e = np.cos(a) * r + np.sin(a) * u
    big = (1 - dop.depolarization) / (1 + dop.depolarization / 2)
    dop_l = pr.polarization.dop

    def f(k_in, k_out):
        """k_in, k_out: (..., 3) unit vectors."""
        k_in, k_out = np.asarray(k_in, float), np.asarray(k_out, float)
        n = np.cross(k_in, k_out)
        nn = np.linalg.norm(n, axis=-1)
        n = n / np.maximum(nn, 1e-300)[..., None]
        e_par, e_perp = np.cross(n, k_in) @ e, n @ e
        cos2psi = (e_par ** 2 - e_perp ** 2) / np.maximum(e_par ** 2 + e_perp ** 2, 1e-300)
        mu = (k_in * k_out).sum(-1)
        m11, m12 = big * 0.75 * (1 + mu * mu) + 1 - big, -big * 0.75 * (1 - mu * mu)
        # straight forward or back (no scattering plane): m12 = 0
        return np.where(nn < 1e-12, 1.0, 1 + m12 / m11 * dop_l * cos2psi)
    return f


import types  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture
def ref():
    """The plain reference helpers above, as a namespace."""
    return types.SimpleNamespace(frame=frame, ray=ray, hg=hg, tthg_params=tthg_params, tthg=tthg, slab=slab,
                                 projector_pixel=projector_pixel,
                                 mueller_intensity=mueller_intensity)
