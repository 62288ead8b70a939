"""The README's env example runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_env_example_runs(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    block = re.search(r"```python\n(.*?)```", README.read_text(), re.S)
    assert block, "README has no python example"
    monkeypatch.chdir(README.parent)
    code = compile(block.group(1), str(README), "exec")
    exec(code, {})
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "['av_0', 'av_1', 'av_2', 'av_3']"
    assert out[1] == "(5, 4, 32, 128)"
    crashed, merged, distance = out[2].split()
    assert crashed in ("True", "False") and merged in ("True", "False") and float(distance) > 0
    exec(code, {})  # the README's "same seed, same episode"
    assert capsys.readouterr().out.splitlines() == out
