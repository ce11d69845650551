"""The soak's report as a table for people (``polarstripe bench soak`` without ``--json``; bench/soak.py)."""

from __future__ import annotations

import json

WARM_SCANS = 15  # the soak's warm-up: three passes over the methods, every code path run, caches in


def table(r: dict) -> str:
    s = r["scans"]
    lines = [f"soak: {r['minutes']:g} min, {r['resolution']}, {r['stripes']} stripes, "
             + (f"chaos: a node killed every {r['chaos_s']:g} s (seed {r['seed']})" if r["chaos_s"] else
                "no chaos"),
             f"warm-up: {_f(r['warmup_s'])} s from start to {WARM_SCANS} scans; then the soak's minutes",
             f"scans: {s['completed']} completed, {s['failed_clear']} failed with a clear fault, "
             f"{s['failed_unclear']} failed without one, {s['unended']} unended at the end",
             f"frames lost on all-mode topics: {r['frames_lost']['outside']} outside kills, "
             f"{r['frames_lost']['within']} within a kill's window"
             + (f" ({', '.join(f'{t} {n}' for t, n in r['frames_lost']['by_topic'].items())})"
                if r["frames_lost"]["by_topic"] else "")]
    if r["kills"]:
        lines += ["", f"{'kill at [s]':>11}  {'node':<11} {'respawned [s]':>13} {'first scan [s]':>14} "
                      f"{'recovered [s]':>13}"]
        for k in r["kills"]:
            lines.append(f"{k['t_s']:>11.1f}  {k['node']:<11} {_f(k['respawned_s']):>13} "
                         f"{_f(k['first_scan_s']):>14} {_f(k['recovered_s']):>13}")
        rec = r["recovery_s"]
        lines.append(f"recovery: median {_f(rec['median'])} s, max {_f(rec['max'])} s")
    lines += ["", f"{'node':<11} {'RSS start':>9} {'end [MB]':>9} {'growth':>7} {'bound':>6} processes"]
    for name, m in r["memory"].items():
        if m["ok"] is None:
            lines.append(f"{name:<11} {'-':>9} {'-':>9} {'-':>7} {'-':>6} {m['processes']:>9}"
                         "  not warm: killed")
            continue
        lines.append(f"{name:<11} {m['start_mb']:>9.1f} {m['end_mb']:>9.1f} {m['growth_mb']:>+7.1f} "
                     f"{m['bound_mb']:>6.0f} {m['processes']:>9}" + ("" if m["ok"] else "  GROWTH"))
    sd = r["shutdown"]
    lines += ["", "shutdown (SIGINT): " + ("every node stopped by itself" if not sd["unclean"] else
                                           f"not clean: {json.dumps(sd['unclean'])}")
              + f", launcher exit {sd['launcher_status']}"]
    if r["faults"]:
        lines += ["", "faults:"] + [f"  {f}" for f in r["faults"][:20]]
        if len(r["faults"]) > 20:
            lines.append(f"  … {len(r['faults']) - 20} more")
    failed = [k for k, v in r["checks"].items() if not v]
    lines.append("" if not failed else f"\nFAILED: {', '.join(failed)}")
    return "\n".join(lines).rstrip()


def _f(v) -> str:
    return "-" if v is None else f"{v:.1f}"
