"""scripts/render_data.sh hands every renderer share of the split CLI to the pools."""

from __future__ import annotations

from pathlib import Path

from signal_light_node.data.split import RENDERER_SHARES

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "render_data.sh"


def test_every_renderer_share_has_its_variable_default_and_flag():
    text = SCRIPT.read_text()
    for key in RENDERER_SHARES:
        var, flag = key.upper(), "--" + key.replace("_", "-")
        assert f"{var}=${{{var}:-0}}" in text, var
        assert f'{flag} "${var}"' in text, flag
