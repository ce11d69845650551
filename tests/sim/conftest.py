"""Plain, slow reference code for the sim tests: geometry and integrands written straight from issue 3."""

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


import types  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture
def ref():
    """The plain reference helpers above, as a namespace."""
    return types.SimpleNamespace(frame=frame, ray=ray, hg=hg, tthg_params=tthg_params, tthg=tthg, slab=slab,
                                 projector_pixel=projector_pixel)
