"""The command lines of the application's jobs, built in one place (imports no torch).

``dcsc`` (:mod:`dcsc_torchrl.cli`) makes one sub-command of each, and the recipe scripts
that stay runnable (``python recipes/pretrain_a2c_lunarlander.py ...``) parse theirs with
the same options and defaults. ``key=value`` overrides may stand anywhere on the line.
"""

from __future__ import annotations

import argparse
import re
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

OVERRIDE = re.compile(r"^[A-Za-z_][\w.\-\[\]]*=")
"""A ``key=value`` token (a path like ``runs/a=b`` has a ``/`` before its ``=``, an option a ``-``)."""

CHECKPOINT_HELP = (
    "Checkpoints: the machine of pretraining seed s is read from "
    "<pretrain.out_dir>/seed<s>/checkpoint.pt, relative to the current folder "
    "(pretrain.out_dir is runs/pretrain_<task>, runs/quick/pretrain_<task> with --quick); "
    "a missing one is pretrained first, one pretraining per seed of pretrain.seeds (3 by "
    "default, 1 with --quick)."
)


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line: ``prog: error: ... (see prog --help)``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args: Sequence[str] | None = None, namespace: Any = None) -> argparse.Namespace:  # type: ignore[override]
        """Parses ``args``, with every ``key=value`` token collected into ``overrides`` wherever it stands."""
        argv = list(sys.argv[1:] if args is None else args)
        overrides = [a for a in argv if OVERRIDE.match(a)]
        rest = [a for a in argv if not OVERRIDE.match(a)]
        ns = super().parse_args(rest, namespace)
        if hasattr(ns, "overrides"):
            ns.overrides = [*ns.overrides, *overrides]
        elif overrides:
            self.error(f"dcsc {getattr(ns, 'command', '')} takes no key=value overrides, got {' '.join(overrides)}")
        return ns


def description(doc: str | None) -> str:
    """The first paragraph of a docstring (a parser's description)."""
    return (doc or "").strip().split("\n\n")[0]


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """``-v`` and ``--debug``, which every sub-command takes."""
    parser.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="more output: TorchRL's INFO lines")
    parser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="a traceback instead of a one-line error (also DCSC_DEBUG=1)")


def _int_at_least(low: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``low`` (the error names the value)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    return parse


def _name(text: str) -> str:
    """An argparse type: a name for a CSV column (not empty, one line)."""
    if not text.strip() or "\n" in text or "\r" in text:
        raise argparse.ArgumentTypeError(f"expected a name on one line, got {text!r}")
    return text


def _folder_name(text: str) -> str:
    """An argparse type: a name that is also one folder (letters, digits, ``_ . -``; not hidden)."""
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*", text):
        raise argparse.ArgumentTypeError(f"expected letters, digits, '_', '.' or '-' (a folder name), got {text!r}")
    return text


def _overrides(parser: argparse.ArgumentParser, example: str) -> None:
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help=f"config overrides, anywhere on the line, hydra style: {example}")


def _add_training_options(parser: argparse.ArgumentParser, *, out: str, example: str) -> argparse.ArgumentParser:
    """A training run's options: ``[--quick] [--resume] [--out DIR] [key=value ...]`` (``out``: --out's help)."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yaml's quick block (tests)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the run's last checkpoint; refused if the config differs")
    parser.add_argument("--out", type=Path, default=None, help=out)
    _overrides(parser, example)
    return parser


def add_recipe_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a pretraining recipe: ``[--quick] [--resume] [--out DIR] [key=value ...]``."""
    return _add_training_options(
        parser, out="run directory (default: logger.out_dir=... when given, else <pretrain.out_dir>/seed<seed>/ "
                    "of the task's protocol yaml, where dcsc run reads this seed's machine)",
        example="optim.lr=1e-3 train.episodes=100")


def add_copilot_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc copilot`` after the task: ``[--quick] [--resume] [--out DIR] [key=value ...]``."""
    return _add_training_options(
        parser, out="run directory (default: logger.out_dir of recipes/copilot_<task>.yaml); copilot.pt "
                    "there is what reddy.copilots names", example="pool=[noisy,laggy,distracted] train.frames=50000")


def add_arbiter_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc arbiter`` after the task: ``[--quick] [--out DIR] [key=value ...]``."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yaml's quick block (tests)")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder of arbiter.pt, pretraining.csv and fig_state_beta.png (default runs/arbiter_<task>); "
                             "arbiter.pt is what state.arbiters names")
    _overrides(parser, "\"state.pool=[noisy,laggy]\" pretrain.observes=blind")
    return parser


def add_run_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc run`` (and ``python recipes/shared_control.py``) after the task."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yaml's quick block (tests)")
    parser.add_argument("--out", type=Path, default=Path("results"),
                        help="results root: files go to OUT/<task>/ (default results/)")
    parser.add_argument("--methods", "--method", nargs="+", default=None, metavar="METHOD",
                        help="methods to run (default: every method of the protocol, dcsc_torchrl.methods.METHODS)")
    parser.add_argument("--operators", "--operator", nargs="+", default=None, metavar="PRESET",
                        help="operator presets (default: the config's operator.presets)")
    parser.add_argument("--fresh", action="store_true",
                        help="delete the results of an earlier run in OUT/<task>/ and start over "
                             "(needed when its config differs)")
    parser.add_argument("--workers", type=_int_at_least(1), default=1,
                        help="cells (and missing pretrainings) at a time: 1 (default), one after another in this "
                             "process; N > 1, Ray tasks on a local instance of N CPUs (the same rows)")
    _overrides(parser, "online.theta_lr=0.1 pretrain.out_dir=runs/mine")
    return parser


RUN_EPILOG = f"""\
{textwrap.fill(CHECKPOINT_HELP, 88)}

Outputs in OUT/<task>/: episodes.csv, trace.csv, theta.csv, summary.md, fig_*.png (all
rewritten after every cell, so they always describe the same cells), each cell's files in
cells/<operator>-seed<s>/, and run_config.yaml (the config the cells were run with).

Resume: run the same command again; finished cells are skipped. A run into a folder
whose run_config.yaml differs is refused (it names the keys) unless --fresh is given."""


def add_sweep_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc sweep``."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yamls' quick blocks (tests)")
    parser.add_argument("--out", type=Path, default=None,
                        help="results root (default results/, results/quick with --quick)")
    parser.add_argument("--address", default=None,
                        help="join this Ray cluster ('auto', HOST:PORT) instead of starting one")
    parser.add_argument("--fresh", action="store_true",
                        help="delete the results of an earlier run of another config and start over")
    _overrides(parser, "ray.workers=4 tasks=[uav] lunarlander.protocol.max_steps=200")
    return parser


def _add_grid_options(parser: argparse.ArgumentParser, *, quick: str, out: str, example: str) -> argparse.ArgumentParser:
    """The options that ``dcsc reproduce`` and ``dcsc map`` share: ``--quick``, ``--out``,
    ``--fresh``, ``--workers`` and the overrides."""
    parser.add_argument("--quick", action="store_true", help=quick)
    parser.add_argument("--out", type=Path, default=None, help=out)
    parser.add_argument("--fresh", action="store_true",
                        help="delete the results of an earlier run of another config and start over")
    parser.add_argument("--workers", type=_int_at_least(1), default=2,
                        help="pretrainings / cells at a time, as Ray tasks on a local instance (default 2, "
                             "this project's 2-core machine); 1: one after another in this process, no Ray")
    _overrides(parser, example)
    return parser


def add_reproduce_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc reproduce``."""
    return _add_grid_options(parser, quick="the same at a tiny scale (about a minute)",
                             out="results root (default results/, results/quick with --quick)",
                             example="protocol.max_steps=200 (given to both tasks)")


def add_map_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc map``."""
    return _add_grid_options(parser, quick="the same code paths at a tiny scale (two machines)",
                             out="the map's folder (default results/map, results/quick/map with --quick)",
                             example="selected=[target-500] operators=[expert,surrogate_noisy]")


def add_report_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc report``."""
    parser.add_argument("--out", type=Path, default=Path("results"),
                        help="results root holding <task>/episodes.csv (default results/)")
    return parser


def add_play_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc play`` (the ones :func:`dcsc_torchrl.recipes.play.run_play` reads)."""
    parser.add_argument("--assist", choices=["dcsc", "state", "ida", "reddy", "none"], default="dcsc",
                        help="share control with the pretrained machine: DC-SC's learned arbiter (dcsc), the "
                             "state-dependent arbiter pretrained in simulation (state) or IDA's intervention on its "
                             "Q critic (ida); with Reddy et al.'s trained copilot (reddy); or fly alone (none)")
    parser.add_argument("--arbiter", type=Path, default=None,
                        help="the pretrained arbiter of --assist state (dcsc arbiter writes one; default: the one "
                             "shipped for the shipped machine)")
    parser.add_argument("--copilot", type=Path, default=Path("runs/copilot_lunarlander/copilot.pt"),
                        help="the copilot of --assist reddy (dcsc copilot writes it; default "
                             "runs/copilot_lunarlander/copilot.pt)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="LunarLander pretraining checkpoint for --assist dcsc / state / ida (default: where dcsc run "
                             "reads seed 0's, <pretrain.out_dir>/seed0/checkpoint.pt of "
                             "recipes/shared_control_lunarlander.yaml)")
    parser.add_argument("--episodes", type=_int_at_least(1), default=3, help="episodes to fly (default 3)")
    parser.add_argument("--seed", type=_int_at_least(0), default=0,
                        help="episode i plays scenario seed + i (default 0)")
    parser.add_argument("--out", type=Path, default=Path("results/play"),
                        help="folder of episodes.csv and trace.csv, appended to (default results/play)")
    parser.add_argument("--participant", type=_name, default="person",
                        help="the operator column of the CSVs (a participant id in a user study)")
    return parser


def add_study_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc study`` after the task (the ones :mod:`dcsc_torchrl.recipes.study` reads)."""
    parser.add_argument("--participant", type=_folder_name, default=None,
                        help="the participant's id: their folder OUT/<task>/<id>/ and the operator column")
    parser.add_argument("--out", type=Path, default=Path("results/study"),
                        help="the study's root (default results/study)")
    parser.add_argument("--short", action="store_true",
                        help="a first try: 5 practice, 5 collaboration and 10 validation scenarios a method "
                             "(the paper's 20 / 20 / 50 otherwise)")
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yaml's quick block (tests)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="the machine's pretraining checkpoint (default: where dcsc run reads seed 0's, else "
                             "the shipped machine)")
    parser.add_argument("--gather", action="store_true",
                        help="fly nothing: write OUT/<task>/study.md, the table over every participant there")
    _overrides(parser, "scenarios.validation_scenarios=20 arbiter.form=paper")
    return parser


def add_ship_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc ship`` after the task."""
    parser.add_argument("checkpoint", type=Path, help="a pretraining checkpoint (checkpoint.pt) of the task, or a "
                        "state-dependent arbiter pretrained next to the shipped machine (dcsc arbiter's arbiter.pt)")
    return parser
