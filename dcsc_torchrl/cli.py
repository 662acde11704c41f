"""The ``dcsc`` command: one entry point for every job of the project (docs/cli.md).

    dcsc pretrain {lunarlander,uav} [--quick] [--resume] [--out DIR] [key=value ...]
    dcsc copilot TASK [--quick] [--resume] [--out DIR] [key=value ...]
    dcsc arbiter lunarlander [--quick] [--out DIR] [key=value ...]
    dcsc run {lunarlander,uav} [--quick] [--out DIR] [--methods M ...] [--operators P ...] [--fresh] [key=value ...]
    dcsc sweep [--quick] [--out DIR] [--address ADDR] [--fresh] [key=value ...]
    dcsc reproduce [--quick] [--out DIR] [--fresh] [key=value ...]
    dcsc map [--quick] [--out DIR] [--fresh] [--workers N] [key=value ...]
    dcsc report [--out DIR]
    dcsc play lunarlander [--assist {dcsc,ida,none}] [--checkpoint PATH] [--episodes N] [--seed S] [--out DIR]
    dcsc ship {lunarlander,uav} CHECKPOINT

The top of the package: it parses and dispatches, and nothing imports it. The options of
each job are the application's (:mod:`dcsc_torchrl.recipes.options`), the work too
(:mod:`dcsc_torchrl.recipes`); this module imports neither torch nor TorchRL, so
``--help``, a bad argument and a bad config key are answered before the libraries load. A
user's mistake ends in one line on stderr and exit code 2, Ctrl-C in exit code 130;
``--debug`` (or ``DCSC_DEBUG=1``) shows the traceback instead.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dcsc_torchrl.recipes.configs import CONFIGS, MAP_CONFIG, SWEEP_CONFIG
from dcsc_torchrl.recipes.options import (
    RUN_EPILOG,
    Parser,
    add_arbiter_options,
    add_common_options,
    add_copilot_options,
    add_map_options,
    add_play_options,
    add_recipe_options,
    add_report_options,
    add_reproduce_options,
    add_run_options,
    add_ship_options,
    add_study_options,
    add_sweep_options,
    description,
)
from dcsc_torchrl.tasks import COPILOT_TASK_NAMES, TASK_NAMES, get_task


# -- the sub-commands' work: every heavy import is inside ------------------------------
def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _pretrain(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    # the config checked before torch loads, as in _run
    load_config(CONFIGS[args.task].pretrain, args.overrides, quick=args.quick, quiet=True)
    from dcsc_torchrl.recipes.machines import PRETRAINING
    from dcsc_torchrl.recipes.pretrain import pretrain

    out = pretrain(args.task, PRETRAINING[args.task], args.overrides, quick=args.quick, resume=args.resume,
                   out=args.out)
    _say(f"checkpoint in {out / 'checkpoint.pt'}")
    return out


def _copilot(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    load_config(CONFIGS[args.task].copilot, args.overrides, quick=args.quick, quiet=True)  # before torch loads
    from dcsc_torchrl.recipes.copilot import copilot_config, train

    path = train(copilot_config(get_task(args.task), args.overrides, quick=args.quick, out=args.out),
                 resume=args.resume)
    _say(f"copilot in {path}")
    return path


def _arbiter(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    load_config(CONFIGS[args.task].protocol, args.overrides, quick=args.quick, quiet=True)  # before torch loads
    from dcsc_torchrl.recipes.arbiter import main

    path = main(get_task(args.task), args.overrides, quick=args.quick, out=args.out)
    _say(f"arbiter in {path}")
    return path


def _run(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    # the config checked before torch loads: a typo is answered at once (run checks it again, and warns)
    load_config(CONFIGS[args.task].protocol, args.overrides, quick=args.quick, quiet=True)
    from dcsc_torchrl.recipes.shared_control import run

    return run(args)


def _report(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.recipes.reproduce import report

    path = report(args.out)
    _say(f"results in {path.parent}")
    return path


def _reproduce(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.recipes.reproduce import reproduce

    path = reproduce(args.out, quick=args.quick, overrides=args.overrides, fresh=args.fresh, workers=args.workers)
    _say(f"results in {path.parent}")
    return path


def _sweep(args: argparse.Namespace) -> Any:
    from dcsc_torchrl.config import load_config

    sweep_overrides = [item for item in args.overrides if item.partition(".")[0] not in TASK_NAMES]
    load_config(SWEEP_CONFIG, sweep_overrides, quick=args.quick, quiet=True)  # before Ray loads
    for task in TASK_NAMES:
        prefix = f"{task}."
        load_config(CONFIGS[task].protocol,
                    [item[len(prefix):] for item in args.overrides if item.startswith(prefix)], quick=args.quick,
                    quiet=True)
    from dcsc_torchrl.recipes.sweep import sweep

    return sweep(args)


def _map(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    load_config(MAP_CONFIG, args.overrides, quick=args.quick, quiet=True)  # before torch loads
    from dcsc_torchrl.recipes.map import run_map

    path = run_map(args.out, quick=args.quick, overrides=args.overrides, fresh=args.fresh, workers=args.workers)
    _say(f"map in {path}")
    return path


def _play(args: argparse.Namespace) -> None:
    from dcsc_torchrl.config import UsageError
    from dcsc_torchrl.recipes.play import run_play

    try:
        run_play(args)
    except SystemExit as stop:  # play's own message (no checkpoint, no display): a usage error
        if isinstance(stop.code, str):
            raise UsageError(stop.code.removeprefix("dcsc play: ")) from None
        raise


def _study(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import UsageError, load_config

    task = get_task(args.task)
    if args.gather:
        from dcsc_torchrl.recipes.study import gather_participants

        path = gather_participants(task, args.out)
        _say(f"the study's table in {path}")
        return path
    if args.participant is None:
        raise UsageError("dcsc study: name the participant with --participant ID (or --gather the study's table)")
    load_config(CONFIGS[args.task].protocol, args.overrides, quick=args.quick, quiet=True)  # before torch loads
    from dcsc_torchrl.recipes.study import run_study

    return run_study(task, args.participant, out=args.out, overrides=args.overrides, short=args.short,
                     quick=args.quick, checkpoint=args.checkpoint)


def _ship(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.checkpoint import load_checkpoint
    from dcsc_torchrl.shipped import export_arbiter, export_machine
    from dcsc_torchrl.state_arbiter import state_arbiter_task

    task = get_task(args.task)
    if load_checkpoint(args.checkpoint, task=None)["task"] == state_arbiter_task(task):
        path = export_arbiter(task, args.checkpoint)
        _say(f"shipped arbiter in {path}")
    else:
        path = export_machine(task, args.checkpoint)
        _say(f"shipped machine in {path}")
    return path


COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], Any], Callable[[argparse.Namespace], Any]]] = {
    "pretrain": ("pretrain a machine policy (A2C for lunarlander, DDPG for uav)", add_recipe_options, _pretrain),
    "copilot": ("train Reddy et al.'s copilot of a task: DQN with surrogate pilots in the loop",
                add_copilot_options, _copilot),
    "arbiter": ("pretrain the state-dependent arbiter in simulation, next to a cell's machine", add_arbiter_options,
                _arbiter),
    "run": ("the shared-control protocol of one task, every cell, resumable", add_run_options, _run),
    "sweep": ("the protocol's grid of cells as Ray tasks, here or on a cluster", add_sweep_options, _sweep),
    "reproduce": ("pretrain, run both experiments, write the report", add_reproduce_options, _reproduce),
    "map": ("where sharing pays: the protocol over operators x machines, against the better partner",
            add_map_options, _map),
    "report": ("redraw summaries and figures from <results>/<task>/*.csv", add_report_options, _report),
    "play": ("fly TargetLunarLander yourself, alone or with DC-SC", add_play_options, _play),
    "study": ("a person through the paper's protocol: practice, collaboration, validation", add_study_options,
              _study),
    "ship": ("export a pretraining checkpoint (or a pretrained arbiter) as the one shipped with the package",
             add_ship_options, _ship),
}


def build_parser() -> Parser:
    """The ``dcsc`` parser: a sub-command per job, each with its own ``--help``."""
    parser = Parser(prog="dcsc", description=description(__doc__),
                    epilog="Run `dcsc COMMAND --help` for a command's options; docs/cli.md for the whole story.")
    parser.add_argument("-v", "--verbose", action="store_true", help="more output: TorchRL's INFO lines")
    parser.add_argument("--debug", action="store_true",
                        help="a traceback instead of a one-line error (also DCSC_DEBUG=1)")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for name, (summary, add_options, handler) in COMMANDS.items():
        sub = commands.add_parser(name, help=summary, description=summary, prog=f"dcsc {name}",
                                  epilog=RUN_EPILOG if name == "run" else None)
        if name in ("pretrain", "run", "ship", "study", "arbiter"):
            sub.add_argument("task", choices=TASK_NAMES, help="the task")
        elif name == "copilot":
            sub.add_argument("task", choices=COPILOT_TASK_NAMES, help="the task")
        elif name == "play":
            sub.add_argument("task", choices=["lunarlander"], help="the task (LunarLander only)")
        add_options(sub)
        add_common_options(sub)
        sub.set_defaults(handler=handler)
    return parser


def _one_line(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    if isinstance(err, KeyError):  # str(KeyError('x')) is "'x'"
        text = f"missing key {text}"
    elif isinstance(err, OSError) and err.strerror and err.filename:  # not "[Errno 28] ...: '/path'"
        text = f"cannot use {err.filename}: {err.strerror}"
    return " ".join(text.split())


def main(argv: Sequence[str] | None = None) -> int:
    """Runs ``dcsc``; returns the exit code (0, 2 for a user's mistake, 130 for Ctrl-C, 1 otherwise)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("DCSC_DEBUG", "") not in ("", "0")
    try:
        args = build_parser().parse_args(argv)
        if not args.verbose:
            os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # read once, when TorchRL is imported
        args.handler(args)
    except KeyboardInterrupt:
        if debug:
            raise
        _say("dcsc: interrupted")
        return 130
    except (ValueError, OSError) as err:  # a user's mistake, a missing or unwritable file, a full disk
        if debug:
            raise
        _say(f"dcsc: error: {_one_line(err)}")
        return 2
    except Exception as err:  # a bug, not a mistake: still one line, the traceback on request
        if debug:
            raise
        if isinstance(err.__context__, KeyboardInterrupt):
            # raised while a Ctrl-C unwound: TorchRL's DDPGLoss swaps its critic's parameters in
            # with TensorDict's to_module, whose __exit__ turns a KeyboardInterrupt into "RuntimeError:
            # Converting a tensordict to boolean value" (our losses avoid it: losses.call_with_params)
            _say("dcsc: interrupted")
            return 130
        _say(f"dcsc: error: {type(err).__name__}: {_one_line(err)} (run with --debug for the traceback)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
