"""A scan's frames rendered together: the same components as one frame after another, for less.

A scan renders one scene many times with only the pattern changing. :func:`render_scan` runs each frame's
computation (:func:`polarstripe.sim.render.component_steps`, a generator) side by side: every frame runs
up to its next grid solve of the higher orders (:class:`~polarstripe.sim.multiple.GridSolve`), the solves
the frames ask for at the same step go through :func:`~polarstripe.sim.multiple.solve_each` as one batch
along a leading axis (one chain of batched transforms instead of one per frame; the map is the same, the
frames independent), and each frame goes on with its own answer. What the frames share is computed once
per scene (:mod:`polarstripe.sim.geometry_cache`): the camera's rays and hits, the view table, the shadow
rays, D at every hit, the source's beams into the grid and their ends. Every frame comes out as
:func:`~polarstripe.sim.render.render_components` makes it on its own, to the bit (the solves of a batch are
the same transforms line by line; ``tests/sim/test_scan_render.py``).
"""

from __future__ import annotations

from collections import defaultdict

from polarstripe.sim.multiple import solve_each
from polarstripe.sim.render import Components, Fidelity, component_steps
from polarstripe.sim.scene import Scene
from polarstripe.sim.threads import each_frame, threads

PIXELS_IN_FLIGHT = 2_000_000     # frames stepped together hold about this many pixels (memory)


def render_scan(scene: Scene, patterns, fidelity: str | Fidelity = "standard", *, rank_tol: float = 0.0,
                **kwargs) -> list[Components]:
    """``[render_components(scene, p, fidelity, **kwargs) for p in patterns]``, the frames stepped together
    (module docstring). With more than one model thread (:func:`polarstripe.sim.threads.threads`) the scan
    is cut into that many chunks, each rendered together on a frame worker. ``rank_tol`` > 0: the grid
    solves of a batch in low rank (:func:`polarstripe.sim.multiple.propagate`; the frames then differ from
    their own renders by about that fraction of the orders' light, docs/physics.md §10.6)."""
    patterns = list(patterns)
    w, h = scene.camera.resolution
    pixels = kwargs.get("pixels")
    size = w * h if pixels is None else max(len(pixels), 1)
    per = max(1, min(len(patterns), PIXELS_IN_FLIGHT // size))
    workers = threads()
    if workers > 1 and len(patterns) > 1:
        per = min(per, -(-len(patterns) // workers))
    chunks = [patterns[a:a + per] for a in range(0, len(patterns), per)]

    def together(chunk):
        return step_together([component_steps(scene, p, fidelity, **kwargs) for p in chunk], rank_tol)

    done = each_frame(together, chunks) if workers > 1 and len(chunks) > 1 else [together(c) for c in chunks]
    return [c for chunk in done for c in chunk]


def step_together(frames: list, rank_tol: float = 0.0) -> list:
    """Run generators that yield :class:`~polarstripe.sim.multiple.GridSolve` side by side: the requests of
    one step with the same key are answered as one batch. Returns what each returns, in order."""
    out: list = [None] * len(frames)
    pending = {}
    for k in range(len(frames)):
        _advance(frames, k, None, pending, out, first=True)
    while pending:
        groups = defaultdict(list)
        for k, request in pending.items():
            groups[request.key()].append(k)
        answers = {}
        for ks in groups.values():
            for k, a in zip(ks, solve_each([pending[k] for k in ks], rank_tol), strict=True):
                answers[k] = a
        pending = {}
        for k, a in answers.items():
            _advance(frames, k, a, pending, out)
    return out


def _advance(frames, k, value, pending, out, first=False):
    try:
        pending[k] = next(frames[k]) if first else frames[k].send(value)
    except StopIteration as done:
        out[k] = done.value
