"""The READMEs' Python examples run as written (FElupe's `test_readme.py` convention).

Every fenced block tagged `python` in README.md and solver/README.md is executed in a fresh
namespace inside a temporary working folder, so an example that drifts from the API fails here.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
READMES = ["README.md", "solver/README.md"]


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


CASES = [(name, i, code) for name in READMES for i, code in enumerate(_python_blocks(ROOT / name))]


def test_the_readmes_have_examples():
    assert CASES, "no ```python block found in the READMEs"


@pytest.mark.parametrize("name,index,code", CASES, ids=[f"{n}#{i}" for n, i, _ in CASES])
def test_readme_example_runs(name, index, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"{name}[block {index}]", "exec"), {"__name__": "__readme__"})
