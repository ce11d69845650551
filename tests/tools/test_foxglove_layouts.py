"""The Foxglove layouts shipped in launch/foxglove/ are current and show topics the bridge and the export
really produce."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from polarstripe.tools import foxglove_layouts as fl
from polarstripe.tools.bag_export import ExportOptions, export

FOLDER = Path(__file__).resolve().parents[2] / "launch" / "foxglove"


@pytest.mark.parametrize("name", sorted(fl.LAYOUTS))
def test_shipped_layout_is_current(name):
    text = (FOLDER / name).read_text()
    assert text == fl.render(fl.LAYOUTS[name]), f"run: python -m polarstripe.tools.foxglove_layouts {FOLDER}"
    data = json.loads(text)
    panels = set(data["configById"])

    def leaves(node):
        return {node} if isinstance(node, str) else leaves(node["first"]) | leaves(node["second"])

    assert leaves(data["layout"]) == panels  # every panel placed, none dangling


def test_layout_topics_exist_in_the_foxglove_export(rig_bag, tmp_path):
    pytest.importorskip("foxglove", reason="CI installs the test extra (foxglove-sdk)")
    res = export(rig_bag.path, tmp_path / "run.foxglove.mcap", "foxglove", ExportOptions(progress=False))
    written = {t: schema for t, schema in res.written}
    cfg = fl.layout("/rig")["configById"]
    used = set()
    for panel in cfg.values():
        mode = panel.get("imageMode", {})
        used |= {mode.get("imageTopic"), mode.get("calibrationTopic"), panel.get("topicToRender")}
        used |= {re.split(r"[.{]", p["value"], maxsplit=1)[0] for p in panel.get("paths", [])}
    used.discard(None)
    assert used <= set(written), used - set(written)
    assert written["/rig/compositor/composite/composite"] == "foxglove.RawImage"
    assert written["/rig/log"] == "foxglove.Log"
