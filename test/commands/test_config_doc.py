"""docs/configuration.md is generated from the config dataclasses and must match them."""

from __future__ import annotations

from pathlib import Path

from soma_ros.commands.config import reference

ROOT = Path(__file__).resolve().parents[2]


def test_the_configuration_reference_matches_the_code():
    page = ROOT / "docs" / "configuration.md"
    assert page.read_text() == reference(), (
        "docs/configuration.md differs from the config dataclasses: run "
        "`soma config doc --out docs/configuration.md`")


def test_the_reference_lists_every_key_of_a_section():
    import dataclasses

    from soma_ros.training.config import LossConfig

    text = reference()
    section = text[text.index("### Training: `loss`"):]
    section = section[: section.index("\n### ", 1)]
    for f in dataclasses.fields(LossConfig):
        assert f"| `{f.name}` |" in section
