"""The configuration reference (deploy/config_reference.py): every key has a meaning written under its field,
docs/config.md is the current rendering, and `impulse config describe` prints a key, a section, or says what is
near a wrong name."""

from __future__ import annotations

import pytest

from impulse.deploy.cli import main
from impulse.deploy.config_reference import as_markdown, keys
from tests.support.paths import REPO


def test_every_key_says_what_it_means() -> None:
    undocumented = [k.name for k in keys() if not k.meaning]
    assert not undocumented, f"write a docstring under these config fields: {undocumented}"
    assert len(keys()) > 100 and {"ppo.num_envs", "curriculum.sfl_scoring", "bus.hub"} <= {k.name for k in keys()}


def test_docs_config_md_is_current() -> None:
    assert (REPO / "docs" / "config.md").read_text() == as_markdown(), (
        "docs/config.md is stale: python -m impulse.deploy.config_reference > docs/config.md")


def test_describe_prints_a_key_a_section_or_the_nearest_names(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "describe", "ppo.num_envs"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("ppo.num_envs (int) = 2048\n") and "side by side" in out
    assert main(["config", "describe", "ppo"]) == 0
    assert capsys.readouterr().out.count("\nppo.") >= 15
    assert main(["config", "describe", "ppo.num_env"]) == 2
    assert "did you mean ppo.num_envs" in capsys.readouterr().err
