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


PAGES = [DOCS.parent / "README.md", *sorted(DOCS.rglob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS.parent)))
def test_every_relative_link_and_figure_of_the_docs_exists(page):
    targets = [t for t in LINK.findall(page.read_text()) if "://" not in t]
    missing = [t for t in targets if not (page.parent / t).exists()]
    assert not missing, f"{page.name} links to {missing}"


def dcsc_commands(page: Path) -> list[str]:
    """The ``dcsc ...`` lines of a page's fenced shell blocks (comments cut, continuations joined)."""
    commands = []
    for block in re.findall(r"```(?:bash|sh|shell|console)?\n(.*?)```", page.read_text(), flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = re.sub(r"^\s*(\.venv/bin/)?", "", re.split(r"\s#", line)[0]).strip()
            if line.startswith("dcsc ") and " [" not in line and "{" not in line:  # not a synopsis
                commands.append(line)
    return commands


COMMANDS = [(page, line) for page in PAGES for line in dcsc_commands(page)]


@pytest.mark.parametrize(("page", "line"), COMMANDS, ids=[line for _, line in COMMANDS])
def test_every_dcsc_command_of_the_docs_parses_and_passes_the_config_door(page, line):
    """A command a reader copies runs in bash and zsh (brackets quoted: zsh globs them) and its
    options and ``key=value`` overrides are the command's (checked as ``dcsc`` checks them)."""
    import shlex

    from dcsc_torchrl.cli import build_parser
    from dcsc_torchrl.config import load_config
    from dcsc_torchrl.recipes.configs import CONFIGS, SWEEP_CONFIG
    from dcsc_torchrl.tasks import TASK_NAMES

    unquoted = [token for token in shlex.split(line, posix=False) if "[" in token and token[0] not in "\"'"]
    assert not unquoted, f"{page.name}: quote {unquoted} (zsh expands brackets)"
    args = build_parser().parse_args(shlex.split(line)[1:])
    if args.command in ("run", "pretrain"):
        configs = CONFIGS[args.task]
        load_config(configs.protocol if args.command == "run" else configs.pretrain, args.overrides,
                    quick=args.quick, quiet=True)
    elif args.command == "map":
        from dcsc_torchrl.recipes.map import map_config

        map_config(args.overrides, quick=args.quick)
    elif args.command == "sweep":
        load_config(SWEEP_CONFIG, [o for o in args.overrides if o.partition(".")[0] not in TASK_NAMES],
                    quick=args.quick, quiet=True)
        for task in TASK_NAMES:
            load_config(CONFIGS[task].protocol, [o.partition(".")[2] for o in args.overrides
                                                 if o.partition(".")[0] == task], quick=args.quick, quiet=True)


def test_the_docs_hold_dcsc_commands_to_check():
    assert len(COMMANDS) >= 5
