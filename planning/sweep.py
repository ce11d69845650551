"""Design studies at scale: the planner over a grid of scenes, on all local cores or on a Dask cluster.

:func:`run_sweep` evaluates every scene of a :class:`~polarstripe.planning.sweep_spec.SweepSpec` (one full
plan each, :func:`evaluate_scene`) and returns a :class:`SweepResult`; :func:`write_table` writes it as one
CSV table, one row per scene and separation (docs/planning.md §4).

* Local (``scheduler=None``): ``jobs`` worker processes from joblib's process pool (loky); each worker loads
  the compiled numba kernels from their on-disk cache once, at start (:func:`warm_worker`).
* Dask (``scheduler="tcp://host:port"`` or an in-process address): the same :func:`evaluate_scene` as
  tasks on a ``distributed`` cluster (the optional ``dask`` extra); :func:`warm_worker` runs once on every
  worker first.
* ``jobs=0``: in this process, one scene after another (tests, debugging).

A Python error in a scene is reported at once (``failed: <error>``). A worker that dies takes the scenes it
was running with it: locally each of them then runs alone in a fresh worker, where a death is surely its
own, is retried once after one, and is reported failed after a second; on Dask the scheduler retries a task
whose worker died (its ``allowed-failures``), then it is submitted once more and reported failed if that
dies too. Ctrl-C stops the sweep and keeps every finished scene; the others are marked missing.
"""

from __future__ import annotations

import csv
import math
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from joblib.externals.loky import get_reusable_executor
from polarstripe.errors import PolarstripeError
from polarstripe.planning.planner import plan
from polarstripe.planning.scene_model import SceneModel
from polarstripe.planning.sweep_spec import AXES, SweepSpec, scene_for
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Scene
from tqdm import tqdm

PARAMS = AXES
STATUS_OK = "ok"


@dataclass(frozen=True)
class SceneJob:
    """One scene of the grid: its index, its axis values, and what every plan shares."""

    index: int
    params: dict[str, Any]
    spec: SweepSpec


@dataclass
class SweepResult:
    """Per scene index: its result (:func:`evaluate_scene`), or why it has none (``failed``, ``missing``)."""

    spec: SweepSpec
    jobs: list[SceneJob]
    results: dict[int, dict] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)
    interrupted: bool = False
    seconds: float = 0.0
    workers: int = 0

    @property
    def missing(self) -> list[int]:
        return [j.index for j in self.jobs if j.index not in self.results and j.index not in self.failed]


def curve_columns(spec: SweepSpec) -> list[str]:
    """The objective columns: ``flood`` (E), ``flood_E_b``, ``flood_S_hat``, ``stripes`` (E),
    ``stripes_E_b``."""
    cols = []
    if "flood" in spec.modalities:
        cols += ["flood", "flood_E_b", "flood_S_hat"]
    if "stripes" in spec.modalities:
        cols += ["stripes", "stripes_E_b"]
    return cols


def evaluate_scene(job: SceneJob) -> dict:
    """One full plan for one scene: per objective column the curve over the separations and its best
    separation; the recommended polarized flood reading; the stripe scans' winners."""
    spec, params = job.spec, job.params
    scene = scene_for(spec.base, params)
    exposure = "auto" if params.get("exposure") == "auto" else "scene"
    model = SceneModel(scene, fidelity=spec.fidelity, n_stripes=int(params["stripes"]), edge=spec.edge,
                       orders=spec.orders)
    plans = plan(model, spec.separations, modalities=spec.modalities, k_detect=spec.k_detect,
                 exposure=exposure)
    curves, out = {}, {}
    if "flood" in plans:
        curves["flood"] = plans["flood"].curve
        for r, c in plans["flood_polarized"].readings.items():
            curves[f"flood_{r}"] = c
        out["flood_reading"] = plans["flood_polarized"].reading
    if "stripes" in plans:
        curves["stripes"], curves["stripes_E_b"] = plans["stripes"].curve, plans["stripes_polarized"].curve
        out["scan_stripes"] = plans["stripes"].scan["winner"]
        out["scan_stripes_E_b"] = plans["stripes_polarized"].scan["winner"]
    out["objective"] = {k: c.objective.tolist() for k, c in curves.items()}
    out["best"] = {k: c.best_separation_m for k, c in curves.items()}
    return out


def _run_one(evaluate: Callable, job: SceneJob) -> tuple[int, str, Any]:
    """In a worker: (index, "ok", result) or (index, "error", message) for a Python error."""
    try:
        return job.index, STATUS_OK, evaluate(job)
    except Exception as exc:  # noqa: BLE001 - reported per scene; a worker that dies is handled outside
        return job.index, "error", f"{type(exc).__name__}: {exc}"


def warm_worker() -> None:
    """Load the compiled kernels once in this process (numba's on-disk cache): one tiny flood and stripe."""

    scene = Scene()
    w, h = scene.camera.resolution
    for pattern in ("flood", "stripe:15/30"):
        render_components(scene, pattern, "preview", np.array([[h // 2, w // 2]]))


def _bar(total: int, show: bool):
    return tqdm(total=total, unit="scene", disable=not show, file=sys.stderr, dynamic_ncols=True,
                desc="sweep")


def _serial(result: SweepResult, evaluate, bar) -> None:
    for job in result.jobs:
        idx, status, value = _run_one(evaluate, job)
        if status == STATUS_OK:
            result.results[idx] = value
        else:
            result.failed[idx] = value
        bar.update()


def _local(result: SweepResult, evaluate, bar, jobs: int) -> None:
    """joblib's loky pool; scenes in flight when a worker dies are each retried once, alone."""
    queue = list(result.jobs)
    suspects: list[SceneJob] = []
    executor = get_reusable_executor(max_workers=jobs, initializer=warm_worker)
    in_flight: dict = {}
    try:
        while queue or in_flight:
            while queue and len(in_flight) < 2 * jobs:
                job = queue.pop(0)
                in_flight[executor.submit(_run_one, evaluate, job)] = job
            done, _ = wait(list(in_flight), timeout=0.5, return_when=FIRST_COMPLETED)
            broken = False
            for fut in done:
                job = in_flight.pop(fut)
                try:
                    idx, status, value = fut.result()
                except (BrokenProcessPool, OSError, EOFError):
                    broken = True
                    suspects.append(job)
                    continue
                (result.results if status == STATUS_OK else result.failed)[idx] = value
                bar.update()
            if broken:  # the pool is gone: everything in flight went with it
                suspects += list(in_flight.values())
                in_flight.clear()
                executor = get_reusable_executor(max_workers=jobs, initializer=warm_worker)
        for job in suspects:  # each alone in a fresh worker; only a death there is surely its own
            for attempt in (1, 2):
                executor = get_reusable_executor(max_workers=1, initializer=warm_worker)
                fut = executor.submit(_run_one, evaluate, job)
                in_flight = {fut: job}
                try:
                    idx, status, value = fut.result()
                except (BrokenProcessPool, OSError, EOFError):
                    if attempt == 2:
                        result.failed[job.index] = "the worker died twice (retried once, alone)"
                    continue
                (result.results if status == STATUS_OK else result.failed)[idx] = value
                break
            in_flight = {}
            bar.update()
    except KeyboardInterrupt:
        result.interrupted = True
        for fut in in_flight:
            fut.cancel()
        executor.shutdown(wait=False, kill_workers=True)


def _dask(result: SweepResult, evaluate, bar, scheduler: str) -> None:
    try:
        from distributed import Client, as_completed
        from distributed.scheduler import KilledWorker
    except ImportError:
        raise PolarstripeError("--scheduler needs Dask: pip install 'polarstripe[dask]'") from None
    try:
        client = Client(scheduler, timeout="10s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise PolarstripeError(f"cannot reach the Dask scheduler at {scheduler!r}: {exc}") from None
    futures = {}
    try:
        client.run(warm_worker)
        result.workers = len(client.scheduler_info().get("workers", {}))
        futures = {client.submit(_run_one, evaluate, job, pure=False): job for job in result.jobs}
        retried: set[int] = set()
        pending = as_completed(list(futures), loop=client.loop)
        for fut in pending:
            job = futures[fut]
            try:
                idx, status, value = fut.result()
            except KilledWorker:
                if job.index in retried:
                    result.failed[job.index] = "the worker died (retried by the scheduler, then once more)"
                    bar.update()
                else:
                    retried.add(job.index)
                    again = client.submit(_run_one, evaluate, job, pure=False)
                    futures[again] = job
                    pending.add(again)
                continue
            (result.results if status == STATUS_OK else result.failed)[idx] = value
            bar.update()
    except KeyboardInterrupt:
        result.interrupted = True
        client.cancel(list(futures))
    finally:
        client.close()


def run_sweep(spec: SweepSpec, *, jobs: int | None = None, scheduler: str | None = None,
              progress: bool = False, evaluate: Callable[[SceneJob], dict] = evaluate_scene) -> SweepResult:
    """Evaluate every scene of ``spec`` (module docstring). ``jobs``: local worker processes (None: all
    cores; 0: in this process). ``scheduler``: a Dask scheduler address instead. ``evaluate`` must be a
    picklable function of a :class:`SceneJob` (tests replace it)."""
    jobs_list = [SceneJob(i, p, spec) for i, p in enumerate(spec.scenes())]
    result = SweepResult(spec, jobs_list)
    t0 = time.perf_counter()
    with _bar(len(jobs_list), progress) as bar:
        if scheduler is not None:
            _dask(result, evaluate, bar, scheduler)
        elif jobs == 0:
            result.workers = 0
            try:
                _serial(result, evaluate, bar)
            except KeyboardInterrupt:
                result.interrupted = True
        else:
            n = (os.cpu_count() or 1) if jobs is None else int(jobs)
            result.workers = n
            _local(result, evaluate, bar, n)
    result.seconds = time.perf_counter() - t0
    return result


def table_rows(result: SweepResult) -> tuple[list[str], list[dict]]:
    """(header, rows) of the table: per finished scene one row per separation, per failed or missing scene
    one row saying so (its separation and objectives empty)."""
    spec = result.spec
    cols = curve_columns(spec)
    extra = (["flood_reading"] if "flood" in spec.modalities else []) + \
        (["scan_stripes", "scan_stripes_E_b"] if "stripes" in spec.modalities else [])
    header = ["scene", "status", *spec.axes, "separation_m", *[f"objective_{c}" for c in cols],
              *[f"best_{c}_m" for c in cols], *extra]
    rows = []
    missing = set(result.missing)
    for job in result.jobs:
        base = {"scene": job.index, **{k: job.params[k] for k in spec.axes}}
        res = result.results.get(job.index)
        if res is None:
            why = f"failed: {result.failed[job.index]}" if job.index in result.failed else \
                "missing: interrupted" if job.index in missing and result.interrupted else "missing"
            rows.append({**base, "status": why})
            continue
        for k, d in enumerate(spec.separations):
            row = {**base, "status": STATUS_OK, "separation_m": float(d)}
            for c in cols:
                row[f"objective_{c}"] = res["objective"][c][k]
                row[f"best_{c}_m"] = res["best"][c]
            for e in extra:
                row[e] = res[e]
            rows.append(row)
    return header, rows


def write_table(result: SweepResult, path: str | Path) -> Path:
    """Write the table as CSV (floats as Python's shortest round-trip repr; empty cells for none)."""
    header, rows = table_rows(result)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=header, restval="", lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: repr(v) if isinstance(v, float) else v for k, v in row.items()})
    os.replace(tmp, path)
    return path


def read_table(path: str | Path) -> list[dict]:
    """The CSV back as dicts: numbers as float (empty cells as NaN), words as str."""
    out = []
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            conv = {}
            for k, v in row.items():
                try:
                    conv[k] = float(v) if v != "" else math.nan
                except ValueError:
                    conv[k] = v
            out.append(conv)
    return out
