"""The sequencer's words on a scan's result: one line per composite, and the results table at the end."""

from __future__ import annotations


def summary(results: dict) -> str:
    """One line per method that reached a composite: frames, sheets, contrast, error vs truth and a
    stripe scan's depth (valid fraction of the objects' pixels, else of the frame; RMS [mm])."""
    rows = [f"{'method':<18} {'frames':>6} {'sheets':>6} {'contrast':>9} {'error vs truth':>15} "
            f"{'depth valid':>11} {'RMS mm':>7}"]
    for method, r in results.items():
        m = r.get("metrics", {})
        rows.append(f"{method:<18} {m.get('frames', '-'):>6} {m.get('sheets', '-'):>6} "
                    f"{_num(m.get('contrast')):>9} {_num(m.get('error_vs_truth')):>15} "
                    f"{_num(m.get('depth_valid_fraction')):>11} {_num(m.get('depth_rms_mm'), 2):>7}")
        if m.get("depth_error"):
            rows.append(f"  {method}: no depth: {m['depth_error']}")
    return "\n".join(rows)


def scores(metrics: dict) -> str:
    return f"contrast {_num(metrics.get('contrast'))}, error vs truth {_num(metrics.get('error_vs_truth'))}"


def _num(value, digits: int = 3) -> str:
    return f"{value:.{digits}f}" if isinstance(value, int | float) else "-"
