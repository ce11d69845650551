"""A polarized Mitsuba 3 truth: the model's Mueller matrix in every scattering, S0–S3 per pixel.

>>> from polarstripe.sim.mitsuba_polarized import render_stokes
>>> from polarstripe.bench.mitsuba_references import reference_scene
>>> s = render_stokes(reference_scene(5.0, False), spp=1024, seed=0)   # doctest: +SKIP
>>> s.shape                                                             # doctest: +SKIP
(4, 32, 32)

Mitsuba's stock phase functions are scalars (volumes depolarize nothing), so the medium gets a phase function
of its own, registered as ``polarstripe_mueller`` in the ``llvm_ad_mono_polarized`` variant: in the
scattering-plane frame (Q = I_∥ − I_⊥, Bohren & Huffman) it is

    M(θ) = P(θ) · M_R(θ) / m11_R(θ)

with P the scene's phase function (docs/physics.md §1: TTHG, HG, isotropic; importance-sampled by its HG
lobes, weight M/pdf) and M_R the depolarized-Rayleigh reduced matrix of docs/physics.md §5
(:func:`polarstripe.sim.polarization.rayleigh_mueller`; m44 = Δ'Δ·(3/2)μ, Δ' = (1 − 2δ)/(1 − δ), Hansen &
Travis 1974), at every angle, forward included. It is rotated into Mitsuba's world Stokes bases
(``mueller.stokes_basis`` of the incident and outgoing directions) as Mitsuba's polarized BSDFs are.
``m12=False`` zeroes m12 only (the intensity is then P whatever the incident polarization).

The source: Mitsuba's emitters are unpolarized, so an isotropic ``point`` emitter of 2·I0 sits behind a small
ideal linear polarizer sheet 1 mm in front of it (a Python BSDF, ``polarstripe_polarizer``, null-flagged so
volpath's shadow rays cross it). Its transmission axis for light along k is the model's (docs/physics.md §0.2,
§5): the source's E-field vector e = cos a·r + sin a·u projected on the plane ⊥ k; Mitsuba's own ``polarizer``
projects the absorbing axis instead (Korger et al. 2013), which differs by up to ~10° off the axes. The sheet
is not seen by the camera and lies outside the medium. With ``polarization.quarter_wave_deg`` an ideal
quarter-wave plate sheet follows 1 mm further (the same BSDF with ``retarder``: Mitsuba's
``linear_retarder(π/2)``, its fast axis the projection of the local axis at that angle), making the light
circular (docs/physics.md §5.1). The sheets' transforms are proper rotations (local x, y, z = projector
right, up, r × u): a mirrored one turns the axis angle a into −a, which no 0° or 90° axis shows. Only
``projector.model = "point"`` sources outside the medium box, with ``polarization.dop`` 0 (no sheet) or 1,
are translated.

The ``stokes`` integrator around ``volpath`` writes S0..S3 in the camera frame: S1 > 0 along image right,
S2 > 0 at 45° from image right toward image up (the model's χ, docs/physics.md §4.1), S3 > 0 as the model's
V > 0 (§5.1: checked by rendering through polarizer and retarder sheets in front of the camera), radiance
W sr⁻¹ m⁻². The m44 of the phase function is Hansen & Travis' Δ·Δ'·(3/2)μ.
"""

from __future__ import annotations

import numpy as np
from polarstripe.sim.geometry import pinhole_frame
from polarstripe.sim.mitsuba_scene import _native, select_variant, to_mitsuba
from polarstripe.sim.phase import tthg_parameters
from polarstripe.sim.scene import Scene, SceneError

VARIANT = "llvm_ad_mono_polarized"
PHASE = "polarstripe_mueller"
POLARIZER = "polarstripe_polarizer"
SHEET_DISTANCE_M = 1e-3           # the polarizer sheet this far in front of the point source (the quarter-
                                  # wave plate, if any, twice as far)
_STOKES_CHANNELS = (1, 4, 7, 10)  # S0.R, S1.R, S2.R, S3.R after the film's luminance channel


def lobes(phase) -> tuple[float, float, float]:
    """(g1, g2, w1): the scene phase function as w1·HG(g1) + (1 − w1)·HG(g2) (isotropic: HG(0))."""
    if phase.model == "isotropic":
        return 0.0, 0.0, 1.0
    if phase.model == "hg":
        return float(phase.g), 0.0, 1.0
    gf, gb, alpha = tthg_parameters(float(phase.g))
    return (0.0, 0.0, 1.0) if alpha == 0.0 else (float(gf), float(-gb), float(alpha))


def mueller_elements(mu, phase_value, depolarization: float, m12: bool = True):
    """(m11, m12, m22, m33, m44) of M = P·M_R/m11_R at μ = cos θ_s for phase values ``phase_value`` [1/sr]."""
    d = float(depolarization)
    big = (1.0 - d) / (1.0 + d / 2.0)
    big2 = (1.0 - 2.0 * d) / (1.0 - d)
    mu = np.asarray(mu, float)
    m22 = big * 0.75 * (1.0 + mu * mu)
    m11 = m22 + 1.0 - big
    s = np.asarray(phase_value, float) / m11
    off = -big * 0.75 * (1.0 - mu * mu) * s if m12 else np.zeros_like(s)
    return s * m11, off, s * m22, s * big * 1.5 * mu, s * big2 * big * 1.5 * mu


_REGISTERED: set[str] = set()


def register() -> None:
    """Register the Mueller phase function and the model's polarizer sheet (in the polarized variant)."""
    import drjit as dr
    import mitsuba as mi

    if mi.variant() in _REGISTERED:
        return

    def hg(mu, g):
        t = 1.0 + g * g - 2.0 * g * mu
        return (1.0 - g * g) / (4.0 * dr.pi * t * dr.sqrt(t))

    def mueller(k_in, k_out, p, big, big2, m12):
        """M(θ) [P-scaled] from the frame of k_in to that of k_out, in Mitsuba's Stokes bases."""
        mu = dr.clip(dr.dot(k_in, k_out), -1.0, 1.0)
        m22r = big * 0.75 * (1.0 + mu * mu)
        s = p / (m22r + 1.0 - big)
        off = -big * 0.75 * (1.0 - mu * mu) * s * m12
        a, c, e = s * m22r, s * big * 1.5 * mu, s * big2 * big * 1.5 * mu
        z = dr.zeros(mi.Float, dr.width(mu))
        m = mi.Spectrum(p, off, z, z, off, a, z, z, z, z, c, z, z, z, z, e)
        n = dr.cross(k_in, k_out)
        n = dr.select(dr.squared_norm(n) > 1e-10, dr.normalize(n), mi.mueller.stokes_basis(k_in))
        e_in, e_out = dr.normalize(dr.cross(n, k_in)), dr.normalize(dr.cross(n, k_out))
        return mi.mueller.rotate_mueller_basis(m, k_in, e_in, mi.mueller.stokes_basis(k_in),
                                               k_out, e_out, mi.mueller.stokes_basis(k_out))

    class MuellerPhase(mi.PhaseFunction):
        """P·M_R/m11_R; wi points to the camera side, light arrives along −wo and leaves along wi."""

        def __init__(self, props):
            mi.PhaseFunction.__init__(self, props)
            self.g1, self.g2 = props.get("g1", 0.0), props.get("g2", 0.0)
            self.w1 = props.get("w1", 1.0)
            d = props.get("depolarization", 0.2)
            self.big, self.big2 = (1.0 - d) / (1.0 + d / 2.0), (1.0 - 2.0 * d) / (1.0 - d)
            self.m12 = 1.0 if props.get("m12", True) else 0.0
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic

        def _p(self, mu):
            return self.w1 * hg(mu, self.g1) + (1.0 - self.w1) * hg(mu, self.g2)

        def sample(self, ctx, mei, sample1, sample2, active=True):
            g = dr.select(sample1 < self.w1, self.g1, self.g2)
            x = sample2.x
            sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * x)
            cos_t = dr.select(dr.abs(g) < 1e-4, 1.0 - 2.0 * x, (1.0 + g * g - sq * sq) / (2.0 * g))
            cos_t = dr.clip(cos_t, -1.0, 1.0)
            sin_t = dr.safe_sqrt(1.0 - cos_t * cos_t)
            sp, cp = dr.sincos(2.0 * dr.pi * sample2.y)
            wo = mei.to_world(mi.Vector3f(sin_t * cp, sin_t * sp, -cos_t))
            pdf = self._p(dr.dot(-wo, mei.wi))
            m = mueller(-wo, mei.wi, pdf, self.big, self.big2, self.m12)
            return wo, m * dr.select(pdf > 0, dr.rcp(pdf), 0.0), pdf

        def eval_pdf(self, ctx, mei, wo, active=True):
            pdf = self._p(dr.dot(-wo, mei.wi))
            return mueller(-wo, mei.wi, pdf, self.big, self.big2, self.m12), pdf

        def to_string(self):
            return f"MuellerPhase[g1={self.g1}, g2={self.g2}, w1={self.w1}]"

    class ModelPolarizer(mi.BSDF):
        """Ideal linear polarizer passing the projection of the local axis ``axis`` on the plane ⊥ the
        light's direction (the model's source polarization, docs/physics.md §0.2); with ``retarder`` set,
        an ideal quarter-wave plate whose fast axis is that projection instead (docs/physics.md §5.1)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            a = np.radians(props.get("angle_deg", 90.0))
            self.axis = (float(np.cos(a)), float(np.sin(a)))
            self.element = (mi.mueller.linear_retarder(0.5 * dr.pi) if props.get("retarder", False)
                            else mi.mueller.linear_polarizer(1.0))
            self.m_flags = mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide | mi.BSDFFlags.Null
            self.m_components = [self.m_flags]

        def _m(self, fwd):
            e = mi.Vector3f(self.axis[0], self.axis[1], 0.0)
            t = dr.normalize(e - dr.dot(e, fwd) * fwd)
            return mi.mueller.rotate_mueller_basis_collinear(self.element, fwd, t,
                                                             mi.mueller.stokes_basis(fwd))

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            bs.wo, bs.pdf, bs.eta = -si.wi, 1.0, 1.0
            bs.sampled_type, bs.sampled_component = mi.UInt32(+mi.BSDFFlags.Null), mi.UInt32(0)
            fwd = si.wi if ctx.mode == mi.TransportMode.Radiance else -si.wi
            return bs, self._m(fwd)

        def eval(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return mi.Float(0.0)

        def eval_null_transmission(self, si, active=True):
            return self._m(si.wi)

        def to_string(self):
            return f"ModelPolarizer[axis={self.axis}]"

    mi.register_phase(PHASE, lambda props: MuellerPhase(props))
    mi.register_bsdf(POLARIZER, lambda props: ModelPolarizer(props))
    _REGISTERED.add(mi.variant())


def _sheet(scene: Scene, distance: float = SHEET_DISTANCE_M, retarder: bool = False) -> dict:
    """The polarizer sheet (``retarder``: the quarter-wave plate, its fast axis at
    ``polarization.quarter_wave_deg``): a rectangle ⊥ the source's axis, ``distance`` ahead, local x/y =
    projector right/up, large enough that every ray from the source into the medium box crosses it."""
    pr, ext = scene.projector, scene.medium.extent
    fr = pinhole_frame(pr.position, pr.look_at, pr.up, 60.0, (2, 2))
    lo, hi = np.asarray(ext.min, float), np.asarray(ext.max, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    v = corners - np.asarray(pr.position, float)
    depth = v @ fr.f
    if np.any(depth <= 0):
        raise SceneError("projector: the polarized truth needs the whole medium box in front of the source")
    d = float(distance)
    half_r = 1.05 * d * float(np.max(np.abs(v @ fr.r) / depth))
    half_u = 1.05 * d * float(np.max(np.abs(v @ fr.u) / depth))
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = half_r * fr.r, half_u * fr.u, np.cross(fr.r, fr.u)   # proper: r × u = −f
    m[:3, 3] = np.asarray(pr.position, float) + d * fr.f
    pol = pr.polarization
    bsdf = {"type": POLARIZER, "angle_deg": float(pol.quarter_wave_deg if retarder else pol.angle_deg)}
    if retarder:
        bsdf["retarder"] = True
    return {"type": "rectangle", "to_world": m, "bsdf": bsdf}


def to_mitsuba_polarized(scene: Scene, *, max_depth: int = -1, spp: int = 1024, seed: int = 0,
                         rr_depth: int = 100000, m12: bool = True, native: bool = True) -> dict:
    """The scene of :func:`polarstripe.sim.mitsuba_scene.to_mitsuba` (flood) with the Mueller phase function,
    the polarized source and the ``stokes`` integrator (module docstring). ``native=False`` keeps numpy
    matrices and imports no Mitsuba."""
    pr, med = scene.projector, scene.medium
    if pr.model != "point":
        raise SceneError("the polarized truth translates projector.model = 'point' only")
    if pr.polarization.dop not in (0.0, 1.0):
        raise SceneError(f"projector.polarization.dop must be 0 or 1 for the polarized truth, got "
                         f"{pr.polarization.dop!r}")
    if med.dop.model != "rayleigh":
        raise SceneError("the polarized truth needs medium.dop.model = 'rayleigh'")
    lo, hi = np.asarray(med.extent.min, float), np.asarray(med.extent.max, float)
    if np.all(np.asarray(pr.position) >= lo - SHEET_DISTANCE_M) and \
            np.all(np.asarray(pr.position) <= hi + SHEET_DISTANCE_M):
        raise SceneError("the polarized truth needs the point source outside the medium box")
    out = to_mitsuba(scene, "flood", max_depth=max_depth, spp=spp, seed=seed, rr_depth=rr_depth, native=False)
    out["integrator"] = {"type": "stokes", "integrator": out["integrator"]}
    g1, g2, w1 = lobes(med.phase)
    out["water"]["phase"] = {"type": PHASE, "g1": g1, "g2": g2, "w1": w1,
                             "depolarization": float(med.dop.depolarization), "m12": bool(m12)}
    if pr.polarization.dop == 1.0:
        out["light"]["intensity"]["value"] = 2.0 * float(pr.intensity_w_sr)   # the sheet passes half
        out["polarizer"] = _sheet(scene)
        if pr.polarization.quarter_wave_deg is not None:          # after the polarizer on the light's way
            out["retarder"] = _sheet(scene, 2.0 * SHEET_DISTANCE_M, retarder=True)
    if not native:
        return out
    select_variant(VARIANT)
    register()
    return _native(out)


def render_stokes(scene: Scene, *, max_depth: int = -1, spp: int = 4096, seed: int = 0, pass_spp: int = 1024,
                  rr_depth: int = 100000, m12: bool = True) -> np.ndarray:
    """Mitsuba's polarized Monte Carlo image of a scene lit by its (point) source, flood.

    Returns float64 (4, h, w): S0..S3 [W sr⁻¹ m⁻²] in the camera frame (module docstring), row 0 at the top,
    averaged over ``spp`` samples per pixel in passes of ``pass_spp``; pass k uses seed ``seed·65537 + k``.
    Through an ideal analyzer at φ: I(φ) = ½(S0 + S1 cos 2φ + S2 sin 2φ).
    """
    import mitsuba as mi

    spec = to_mitsuba_polarized(scene, max_depth=max_depth, spp=min(spp, pass_spp), seed=seed,
                                rr_depth=rr_depth, m12=m12)
    mscene = mi.load_dict(spec)
    w, h = scene.camera.resolution
    acc, done, k = np.zeros((4, h, w)), 0, 0
    while done < spp:
        n = min(pass_spp, spp - done)
        img = np.array(mi.render(mscene, spp=n, seed=int(seed) * 65537 + k), dtype=np.float64)
        acc += n * np.moveaxis(img[..., list(_STOKES_CHANNELS)], -1, 0)
        done, k = done + n, k + 1
    return acc / spp
