"""The ``dcsc`` command: one entry point for every job of the project.

    dcsc pretrain {lunarlander,uav} [--quick] [--resume] [--out DIR] [key=value ...]
    dcsc run {lunarlander,uav} [--methods M ...] [--operators P ...] [--quick] [key=value ...]
    dcsc evaluate [--results DIR]
    dcsc reproduce [--quick] [--results DIR]
    dcsc sweep [--quick] [--out DIR] [--address ADDR] [key=value ...]
    dcsc play lunarlander [--assist {dcsc,none}] [--checkpoint PATH]

Each sub-command hands its remaining arguments to the module that owns the job.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

PRETRAIN_RECIPES = {
    "lunarlander": "recipes.pretrain_a2c_lunarlander",
    "uav": "recipes.pretrain_ddpg_uav",
}


def _pretrain(args: argparse.Namespace, rest: list[str]) -> None:
    importlib.import_module(PRETRAIN_RECIPES[args.task]).main(rest)


def _run(args: argparse.Namespace, rest: list[str]) -> None:
    from recipes.shared_control import main as shared_control

    shared_control([args.task, *rest])


def _evaluate(args: argparse.Namespace, rest: list[str]) -> None:
    from recipes.reproduce import evaluate

    evaluate(args.results)


def _reproduce(args: argparse.Namespace, rest: list[str]) -> None:
    from recipes.reproduce import reproduce

    reproduce(args.results, quick=args.quick, overrides=rest)


def _sweep(args: argparse.Namespace, rest: list[str]) -> None:
    from recipes.sweep import main as sweep

    sweep(rest)


def _play(args: argparse.Namespace, rest: list[str]) -> None:
    from dcsc_torchrl.humans.play import main as play_main

    play_main([args.task, *rest])


def build_parser() -> argparse.ArgumentParser:
    """The ``dcsc`` parser; sub-commands that hand over to a recipe leave ``--help`` to it."""
    parser = argparse.ArgumentParser(prog="dcsc", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    pretrain = commands.add_parser("pretrain", help="pretrain a machine policy (A2C / DDPG)", add_help=False)
    pretrain.add_argument("task", choices=sorted(PRETRAIN_RECIPES))
    pretrain.set_defaults(run=_pretrain)
    run = commands.add_parser("run", help="the shared-control protocol for one task (recipes/shared_control.py)", add_help=False)
    run.add_argument("task", choices=sorted(PRETRAIN_RECIPES))
    run.set_defaults(run=_run)
    evaluate = commands.add_parser("evaluate", help="redraw summaries and figures from results/*.csv")
    evaluate.add_argument("--results", type=Path, default=Path("results"))
    evaluate.set_defaults(run=_evaluate)
    reproduce = commands.add_parser("reproduce", help="pretrain, run both experiments, write the report")
    reproduce.add_argument("--quick", action="store_true", help="the same at a tiny scale (about a minute)")
    reproduce.add_argument("--results", type=Path, default=None, help="default results/ (results/quick with --quick)")
    reproduce.set_defaults(run=_reproduce)
    sweep = commands.add_parser("sweep", help="the protocol's grid of cells as Ray tasks (recipes/sweep.py)", add_help=False)
    sweep.set_defaults(run=_sweep)
    play = commands.add_parser("play", help="fly TargetLunarLander yourself, alone or with DC-SC", add_help=False)
    play.add_argument("task", choices=["lunarlander"])
    play.set_defaults(run=_play)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    args, rest = build_parser().parse_known_args(sys.argv[1:] if argv is None else argv)
    args.run(args, rest)


if __name__ == "__main__":
    main()
