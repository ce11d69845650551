"""Foxglove layouts of the rig, shipped in ``launch/foxglove/`` (``rig.json`` for ``sim.toml``'s namespace
``/rig``, ``rov.json`` for ``/rov``): in the Foxglove app, *Layouts → Import from file*, then open the live
bridge (``ws://…:8765``) or an exported MCAP (``polarstripe bag export --to foxglove``).

Panels: the composite of the newest scan, the raw camera frame (with its camera info), the analyzer angle
and its target, the contrast of each method's composite (one series per method: a message-path filter on
``metrics{method=="…"}``), and the rig's log. The files use the app's layout format (``configById`` and
the ``layout`` split tree); images are 12-bit DN, so the image panels map 0–4095.

Regenerate after a topic or panel change (a test checks the shipped files are current)::

    python -m polarstripe.tools.foxglove_layouts launch/foxglove
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from polarstripe.msgs import METHOD_NAMES

LAYOUTS = {"rig.json": "/rig", "rov.json": "/rov"}
MAX_DN = 4095  # 12-bit sensors


def _image(topic: str, calibration: str = "") -> dict:
    mode = {"imageTopic": topic, "minValue": 0, "maxValue": MAX_DN}
    if calibration:
        mode["calibrationTopic"] = calibration
    return {"imageMode": mode}


def _plot(title: str, series: list[tuple[str, str]]) -> dict:
    return {
        "title": title,
        "paths": [{"value": v, "label": label, "enabled": True, "timestampMethod": "receiveTime"}
                  for v, label in series],
        "showLegend": True,
        "legendDisplay": "floating",
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "isSynced": True,
        "xAxisVal": "timestamp",
    }


def topics(namespace: str) -> dict[str, str]:
    """The topics a layout of ``namespace`` shows, by role."""
    return {
        "composite": f"{namespace}/compositor/composite/composite",
        "frame": f"{namespace}/camera/frame/image",
        "frame_info": f"{namespace}/camera/frame/camera_info",
        "polarizer": f"{namespace}/polarizer/state",
        "metrics": f"{namespace}/compositor/composite/metrics",
        "log": f"{namespace}/log",
    }


def layout(namespace: str) -> dict:
    """The rig's layout for ``namespace`` (module docstring)."""
    t = topics(namespace)
    ids = {"composite": "Image!composite", "frame": "Image!frame", "angle": "Plot!angle",
           "contrast": "Plot!contrast", "log": "RosOut!log"}
    config = {
        ids["composite"]: _image(t["composite"]),
        ids["frame"]: _image(t["frame"], t["frame_info"]),
        ids["angle"]: _plot("analyzer angle [deg]", [(f"{t['polarizer']}.angle_deg", "angle"),
                                                      (f"{t['polarizer']}.target_deg", "target")]),
        ids["contrast"]: _plot("contrast per method", [
            (f'{t["metrics"]}{{method=="{m}"}}.contrast', m) for m in METHOD_NAMES]),
        ids["log"]: {"topicToRender": t["log"], "searchTerms": [], "minLogLevel": 2},
    }
    images = {"direction": "row", "first": ids["composite"], "second": ids["frame"], "splitPercentage": 50}
    plots = {"direction": "column", "first": ids["angle"],
             "second": {"direction": "column", "first": ids["contrast"], "second": ids["log"],
                        "splitPercentage": 60}, "splitPercentage": 35}
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {"direction": "row", "first": images, "second": plots, "splitPercentage": 62},
    }


def render(namespace: str) -> str:
    """The layout file's text."""
    return json.dumps(layout(namespace), indent=2) + "\n"


def write(folder) -> list[Path]:
    """Write every layout into ``folder``; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name, ns in LAYOUTS.items():
        (folder / name).write_text(render(ns))
        out.append(folder / name)
    return out


if __name__ == "__main__":
    for p in write(sys.argv[1] if len(sys.argv) > 1 else "launch/foxglove"):
        print(p)
