"""One scan's composite and its scores: the processing the compositor node and ``polarstripe compare`` share.

:func:`compose` turns the per-pixel reductions of a scan (one :class:`~.composite.CompositeImage`, max and
min, per analyzer angle) into the method's estimate of the signal S = D + A; :func:`score` measures an
estimate (Michelson contrast over a chart's bars, relative error against a ground truth). Both are pure:
arrays in, arrays and numbers out; bad input raises :class:`~.validation.ImagingError`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from polarstripe.imaging.composite import CompositeImage
from polarstripe.imaging.metrics import michelson_contrast, signal_error
from polarstripe.imaging.p_map import P_RULES, PEstimate, global_p, regional_p_map
from polarstripe.imaging.polarization import recover_signal
from polarstripe.imaging.separation import separate_direct_global
from polarstripe.imaging.validation import ImagingError, roi_slices
from polarstripe.msgs.methods import METHOD_NAMES, Method


@dataclass(frozen=True)
class Composition:
    """What :func:`compose` made.

    Attributes
    ----------
    image : numpy.ma.MaskedArray (h, w), float64
        The method's estimate of S, in frame units (DN) above the dark offset; masked where a frame it
        comes from was saturated.
    layers : dict of str to numpy.ma.MaskedArray
        The images it was made from or beside: ``e_b`` and ``e_w`` (polarized methods, offset subtracted,
        E_b the crossed one) or ``global`` (``hf_separation``).
    p : float or None
        The backscatter DOP eq. 6 divided by (polarized methods): the rule's p̂, or a map's median; None
        otherwise or when it could not be estimated (then ``image`` is E_b, unrecovered, and ``note`` says
        why).
    p_backscatter : float or None
        The backscatter's DOP as the medium has it, published as the medium's p; None where ``p`` is.
    note : str
        Why a step was skipped; "" when none was.
    p_estimate : PEstimate or None
        Both, with eq. 6's map, the source and the spread (:class:`~.p_map.PEstimate`); None where ``p`` is.
    """

    image: np.ma.MaskedArray
    layers: dict[str, np.ma.MaskedArray] = field(default_factory=dict)
    p: float | None = None
    note: str = ""
    p_backscatter: float | None = None
    p_estimate: PEstimate | None = None

    @property
    def saturated_pixels(self) -> int:
        """Pixels of ``image`` masked because a frame was saturated there."""
        return int(np.ma.count_masked(self.image))


def compose(method: str, views: Mapping[float | None, CompositeImage], *, dark_offset: float = 0.0,
            saturation: float | None = None, object_free=None, lit_fraction: float = 0.5,
            black_level: float = 0.0, p_min: float = 0.05, p_rule: str = "median",
            p_model: Callable[[np.ndarray, np.ndarray], PEstimate] | None = None) -> Composition:
    r"""The composite of one scan of ``method`` from its per-angle reductions.

    Parameters
    ----------
    method : {"flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation"}
    views : mapping of analyzer angle [deg] (None: no analyzer) to CompositeImage
        Per-pixel max and min over the scan's frames at that angle (masked where saturated), e.g.
        ``{a: rc.result(a) for a in rc.angles}`` of a :class:`~.composite.RunningComposite`. Polarized
        methods need two angles; the others use the first.
    dark_offset : float
        Black level [DN] subtracted from every frame.
    saturation : float, optional
        Saturation level [DN]: pixels at or above it in either polarized frame are left out of p̂.
    object_free : (row0, row1, col0, col1) or bool mask (h, w), optional
        Where S = 0 (no object): p is estimated there, and E_b is the angle darker there. None: the whole
        frame.
    lit_fraction, black_level : float
        α and b of the high-frequency patterns (``hf_separation``).
    p_min : float
        Lower clamp of p̂ (eq. 6 divides by p).
    p_rule : {"median", "upper", "map"}
        Eq. 6's p (polarized methods, docs/physics.md §4.2): one p̂ by that rule of
        :func:`~.polarization.estimate_p`, or ``map`` per pixel: from ``p_model`` when given, else from the
        frames (:func:`~.p_map.regional_p_map`).
    p_model : callable (E_b, E_w) -> PEstimate, optional
        The medium model's map for the pair's raw frames (E_b the crossed one; planning/medium_p.py's
        ``p_map_with_model`` with the rig's scene), used by ``p_rule="map"``.

    Returns
    -------
    Composition

    Raises
    ------
    ImagingError
        An unknown method, no views, a polarized method without exactly two angles, a bad region.

    Notes
    -----
    With SI_k the k-th frame at one analyzer angle and o the dark offset:

    * ``flood``: Ŝ = SI_0 − o (the flood frame: S plus all the backscatter B).
    * ``stripes``: the light-stripe composite of eq. 7, Ŝ = CI − o with CI(x, y) = max_k SI_k(x, y).
    * ``polarized_flood`` / ``polarized_stripes``: the frame (or eq. 7 composite) at each of the two angles.
      Through an analyzer crossed to the backscatter and parallel to it (eqs. 4–5)

      .. math:: E_b = S/2 + B(1 - p)/2, \qquad E_w = S/2 + B(1 + p)/2,

      so E_b is the angle passing less light over the object-free region (median). Eq. 6 recovers the
      signal with p per pixel (``p_rule="map"``) or one p̂:

      .. math:: \hat S = E_b (1 + 1/p) + E_w (1 - 1/p).

      One p̂ is the ratio of medians over the object-free region (``median``: exact with S = 0 there; with
      object light there it reads p·B/(S + B), low, and eq. 6 over-subtracts) or the ``upper`` rule,
      clipped to [p_min, 1]. The map is the DOP the pair sees at each pixel, p(x)·cos 2(χ(x) − ψ), from
      the medium's model, or from the frames per region (:mod:`.p_map`). Without usable pixels p is not
      estimated and Ŝ = E_b (``note`` says why). Beside it, ``p_backscatter`` estimates the medium's own DOP
      (the model's, or the frames' ``upper`` rule).
    * ``hf_separation``: Nayar et al. (2006) with L⁺ = max and L⁻ = min over the complementary checkers,
      α the lit fraction, b the projector's black level (:func:`~.separation.separate_direct_global`):

      .. math:: L_d = \frac{(1 - α + α b) L^+ - (α + b - α b) L^-}{(1 - α)(1 - b^2)}, \qquad
                L_g = \frac{L^- - b L^+}{(1 - α)(1 - b^2)},

      (α = ½, b = 0: L_d = L⁺ − L⁻, L_g = 2 L⁻); Ŝ = L_d, the direct image (in water the global part
      holds A and B together, the paper's eq. 3).
    """
    known = Method.lookup(method)
    if known is None:
        raise ImagingError(f"method: {method!r} is not one of {', '.join(METHOD_NAMES)}")
    angles = list(views)
    if not angles:
        raise ImagingError("views: no frames")
    if known.polarized:
        if p_rule not in P_RULES:
            raise ImagingError(f"p_rule: {p_rule!r} is not one of {', '.join(P_RULES)}")
        return _polarized(method, views, dark_offset, saturation, object_free, p_min, p_rule, p_model)
    view = views[angles[0]]
    if known is Method.HF_SEPARATION:
        direct, glob = separate_direct_global(view.maximum.astype(np.float64) - dark_offset,
                                              view.minimum.astype(np.float64) - dark_offset,
                                              lit_fraction=lit_fraction, black_level=black_level)
        return Composition(direct, {"global": glob})
    return Composition(view.maximum.astype(np.float64) - dark_offset)  # flood: the frame; stripes: eq. 7


def _polarized(method, views, dark_offset, saturation, object_free, p_min, p_rule, p_model) -> Composition:
    angles = list(views)
    if len(angles) != 2:
        raise ImagingError(f"{method} needs frames at two analyzer angles, got {angles}")
    a, b = (views[x].maximum for x in angles)
    region = roi_slices("object_free", object_free, a.shape)
    if np.ma.median(a[region]) > np.ma.median(b[region]):
        a, b = b, a  # E_b passes less backscatter
    e_b, e_w = a.astype(np.float64) - dark_offset, b.astype(np.float64) - dark_offset
    layers = {"e_b": e_b, "e_w": e_w}
    kw = dict(dark_offset=dark_offset, saturation=saturation, p_min=p_min)
    try:
        if p_rule != "map":
            est = global_p(a.data, b.data, object_free, rule=p_rule, **kw)
        elif p_model is not None:
            est = p_model(a.data, b.data)
        else:
            est = regional_p_map(a.data, b.data, object_free, **kw)
    except ImagingError as exc:  # no usable object-free pixels: the crossed frame, unrecovered
        return Composition(e_b, layers, None, f"p not estimated ({exc}): the composite is E_b without eq. 6")
    p = est.summary()["p"]
    return Composition(recover_signal(e_b, e_w, est.eq6), layers, p, est.note, est.p, est)


def score(image, *, bright=None, dark=None, truth=None, region=None, fit_gain: bool = True) -> dict:
    """How good an estimate of S is: contrast of the chart's bars and error against the ground truth.

    Parameters
    ----------
    image : array (h, w), may be masked
        The estimate, masked where saturated: left out of the contrast, lost (all their truth is error) in
        the error (:func:`~.metrics.signal_error`).
    bright, dark : (row0, row1, col0, col1) or bool mask (h, w), optional
        The chart's bright and dark bars; no contrast without them.
    truth : array (h, w), optional
        The true S in the units of ``image`` (up to a gain when ``fit_gain``); no error without it.
    region : (row0, row1, col0, col1) or bool mask (h, w), optional
        Pixels the error is taken over; None: the whole frame.
    fit_gain : bool
        Fit the least-squares gain of the estimate first (:func:`~.metrics.signal_error`).

    Returns
    -------
    dict
        ``contrast``: Michelson contrast (I_bright − I_dark)/(I_bright + I_dark) of the bar means, or None;
        ``error_vs_truth``: ‖g Ŝ − S‖ / ‖S‖ over ``region`` (g = 1 unless ``fit_gain``), or None; and
        ``metrics_error`` (the reasons) when a measure cannot be taken, e.g. every bar pixel saturated: then
        that measure is None rather than wrong, and the other is still taken.
    """
    out: dict = {"contrast": None, "error_vs_truth": None}
    reasons = []
    if bright is not None:
        try:
            out["contrast"] = michelson_contrast(image, bright, dark)
        except ImagingError as exc:
            reasons.append(f"contrast: {exc}")
    if truth is not None:
        try:       # saturated bars leave no contrast, but their pixels still count in the error (lost)
            out["error_vs_truth"] = signal_error(image, truth, region, fit_gain=fit_gain)
        except ImagingError as exc:
            reasons.append(f"error: {exc}")
    if reasons:
        out["metrics_error"] = "; ".join(reasons)
    return out
