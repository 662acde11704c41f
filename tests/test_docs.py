"""The code in the docs runs, as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


def python_blocks(path: Path) -> list[str]:
    """The ```python fenced blocks of a markdown file, in order."""
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


@pytest.mark.parametrize("doc", ["compose.md"])
def test_doc_examples_run(doc, capsys):
    blocks = python_blocks(DOCS / doc)
    assert blocks, f"{doc} has no python example"
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, f"{doc}", "exec"), namespace)
    out = capsys.readouterr().out
    assert "theta after 500 frames" in out
    assert "validation: ['dcsc_centred', 'hula', 'operator']" in out  # a custom operator ran the whole protocol
