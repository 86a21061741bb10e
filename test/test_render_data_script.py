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



def test_night_negatives_are_family_2_night_scenes_with_bright_glaring_tail_lamps():
    # Rendering even two tracks of every split takes minutes, so the declaration is read.
    text = SCRIPT.read_text()
    assert "NIGHT_NEGATIVE_TRACKS=${NIGHT_NEGATIVE_TRACKS:-0}" in text
    assert 'glare = dict(held_out, tail_glare=1.0, glare_tail_bright=1.0)' in text
    assert ('splits.append(("family_night_negatives", neg_seed, neg_n, test_len, True, glare,\n'
            '                   {"lighting": "night"}))') in text
