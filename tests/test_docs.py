"""The documentation's promises: its examples are valid and its commands exist."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from gateway import config

ROOT = Path(__file__).resolve().parents[1]


def _toml_blocks(text: str) -> list[str]:
    return re.findall(r"```toml\n(.*?)```", text, flags=re.S)


def test_example_config_file_is_valid_and_lists_every_key() -> None:
    cfg = config.load(ROOT / "examples" / "gateway.toml")
    assert [p.type for p in cfg.sources] == ["serial", "sim"]
    text = (ROOT / "examples" / "gateway.toml").read_text()
    for key in config.GATEWAY_SCHEMA.keys:
        assert re.search(rf"^{key} = ", text, re.M), f"examples/gateway.toml misses {key}"
    for part in (*cfg.sources, *cfg.backends):
        for key in part.cls.CONFIG.keys:
            assert re.search(rf"^#? ?{key} = ", text, re.M), f"examples misses {part.type}.{key}"


@pytest.mark.parametrize("block", _toml_blocks((ROOT / "README.md").read_text()))
def test_readme_toml_examples_are_valid(block: str) -> None:
    config.parse(tomllib.loads(block))


def test_readme_set_up_commands_are_make_targets() -> None:
    readme = (ROOT / "README.md").read_text()
    makefile = (ROOT / "Makefile").read_text()
    for target in ("run", "test"):
        assert f"make {target}" in readme
        assert re.search(rf"^{target}:", makefile, re.M), f"Makefile has no {target} target"
    assert "make test" in (ROOT / ".ci" / "run").read_text()
