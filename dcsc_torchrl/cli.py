"""The ``dcsc`` command: one entry point for every job of the project (docs/cli.md).

    dcsc pretrain {lunarlander,uav} [--quick] [--resume] [--out DIR] [key=value ...]
    dcsc run {lunarlander,uav} [--quick] [--out DIR] [--methods M ...] [--operators P ...] [--fresh] [key=value ...]
    dcsc sweep [--quick] [--out DIR] [--address ADDR] [--fresh] [key=value ...]
    dcsc reproduce [--quick] [--out DIR] [--fresh] [key=value ...]
    dcsc report [--out DIR]
    dcsc play lunarlander [--assist {dcsc,none}] [--checkpoint PATH] [--episodes N] [--seed S] [--out DIR]

Every parser of the project is built here (the recipes parse their command lines with
these), and this module imports neither torch nor TorchRL: ``--help``, a bad argument and
a bad config key are answered before the libraries load. ``key=value`` overrides may
stand anywhere on the line. A user's mistake ends in one line on stderr and exit code 2,
Ctrl-C in exit code 130; ``--debug`` (or ``DCSC_DEBUG=1``) shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import re
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from dcsc_torchrl.tasks import TASK_NAMES, get_task

OVERRIDE = re.compile(r"^[A-Za-z_][\w.\-\[\]]*=")
"""A ``key=value`` token (a path like ``runs/a=b`` has a ``/`` before its ``=``, an option a ``-``)."""

CHECKPOINT_HELP = (
    "Checkpoints: the machine of pretraining seed s is read from "
    "<pretrain.out_dir>/seed<s>/checkpoint.pt, relative to the current folder "
    "(pretrain.out_dir is runs/pretrain_<task>, runs/quick/pretrain_<task> with --quick); "
    "a missing one is pretrained first, one pretraining per seed of pretrain.seeds (3 by "
    "default, 1 with --quick)."
)


def recipes_dir() -> Path:
    """The ``recipes`` package's folder (its yaml configs), found without importing it."""
    spec = importlib.util.find_spec("recipes")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("the recipes package is not installed (pip install -e .)")
    return Path(next(iter(spec.submodule_search_locations)))


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


def _description(doc: str | None) -> str:
    return (doc or "").strip().split("\n\n")[0]


def _common(parser: argparse.ArgumentParser) -> None:
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


def _overrides(parser: argparse.ArgumentParser, example: str) -> None:
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help=f"config overrides, anywhere on the line, hydra style: {example}")


def add_recipe_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a pretraining recipe: ``[--quick] [--resume] [--out DIR] [key=value ...]``."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yaml's quick block (tests)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the run's last checkpoint; refused if the config differs")
    parser.add_argument("--out", type=Path, default=None,
                        help="run directory (dcsc pretrain's default: <pretrain.out_dir>/seed<seed>/, where "
                             "dcsc run reads it; the recipe script's: logger.out_dir)")
    _overrides(parser, "optim.lr=1e-3 train.episodes=100")
    return parser


def add_run_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc run`` / ``recipes/shared_control.py`` after the task."""
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
    """The options of ``dcsc sweep`` / ``recipes/sweep.py``."""
    parser.add_argument("--quick", action="store_true", help="the tiny setting of the yamls' quick blocks (tests)")
    parser.add_argument("--out", type=Path, default=None,
                        help="results root (default results/, results/quick with --quick)")
    parser.add_argument("--address", default=None,
                        help="join this Ray cluster ('auto', HOST:PORT) instead of starting one")
    parser.add_argument("--fresh", action="store_true",
                        help="delete the results of an earlier run of another config and start over")
    _overrides(parser, "ray.workers=4 tasks=[uav] lunarlander.protocol.max_steps=200")
    return parser


def add_reproduce_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc reproduce`` / ``recipes/reproduce.py``."""
    parser.add_argument("--quick", action="store_true", help="the same at a tiny scale (about a minute)")
    parser.add_argument("--out", type=Path, default=None,
                        help="results root (default results/, results/quick with --quick)")
    parser.add_argument("--fresh", action="store_true",
                        help="delete the results of an earlier run of another config and start over")
    parser.add_argument("--workers", type=_int_at_least(1), default=2,
                        help="pretrainings / cells at a time, as Ray tasks on a local instance (default 2, "
                             "this project's 2-core machine); 1: one after another in this process, no Ray")
    _overrides(parser, "protocol.max_steps=200 (given to both tasks)")
    return parser


def add_report_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc report``."""
    parser.add_argument("--out", type=Path, default=Path("results"),
                        help="results root holding <task>/episodes.csv (default results/)")
    return parser


def add_play_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``dcsc play`` (the ones ``dcsc_torchrl.humans.play`` reads)."""
    parser.add_argument("--assist", choices=["dcsc", "none"], default="dcsc",
                        help="share control with the pretrained machine (dcsc) or fly alone")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="LunarLander pretraining checkpoint for --assist dcsc (default: where dcsc run "
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


# -- the sub-commands' work: every heavy import is inside ------------------------------
def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _pretrain(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.checkpoint import checkpoint_path
    from dcsc_torchrl.config import load_config, writable_folder

    task = get_task(args.task)
    module = task.pretrain_recipe
    cfg = load_config(recipes_dir() / f"{module.rsplit('.', 1)[1]}.yaml", args.overrides, quick=args.quick)
    # by default where `dcsc run` (same --quick) reads this seed's machine
    protocol = load_config(recipes_dir() / task.config, quick=args.quick)
    out = writable_folder(args.out or checkpoint_path(protocol.pretrain.out_dir, cfg.seed).parent)
    cfg.logger.out_dir = str(out)
    importlib.import_module(module).train(cfg, resume=args.resume)
    _say(f"checkpoint in {out / 'checkpoint.pt'}")
    return out


def _run(args: argparse.Namespace) -> Path:
    from dcsc_torchrl.config import load_config

    # the config checked before torch loads: a typo is answered at once (run checks it again, and warns)
    load_config(recipes_dir() / get_task(args.task).config, args.overrides, quick=args.quick, quiet=True)
    from recipes.shared_control import run

    return run(args)


def _report(args: argparse.Namespace) -> Path:
    from recipes.reproduce import report

    path = report(args.out)
    _say(f"results in {path.parent}")
    return path


def _reproduce(args: argparse.Namespace) -> Path:
    from recipes.reproduce import reproduce

    path = reproduce(args.out, quick=args.quick, overrides=args.overrides, fresh=args.fresh, workers=args.workers)
    _say(f"results in {path.parent}")
    return path


def _sweep(args: argparse.Namespace) -> Any:
    from dcsc_torchrl.config import load_config

    sweep_overrides = [item for item in args.overrides if item.partition(".")[0] not in TASK_NAMES]
    load_config(recipes_dir() / "sweep.yaml", sweep_overrides, quick=args.quick, quiet=True)  # before Ray loads
    for task in TASK_NAMES:
        prefix = f"{task}."
        load_config(recipes_dir() / get_task(task).config,
                    [item[len(prefix):] for item in args.overrides if item.startswith(prefix)], quick=args.quick,
                    quiet=True)
    from recipes.sweep import sweep

    return sweep(args)


def _play(args: argparse.Namespace) -> None:
    from dcsc_torchrl.config import UsageError
    from dcsc_torchrl.humans.play import run_play

    try:
        run_play(args)
    except SystemExit as stop:  # play's own message (no checkpoint, no display): a usage error
        if isinstance(stop.code, str):
            raise UsageError(stop.code.removeprefix("dcsc play: ")) from None
        raise


COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], Any], Callable[[argparse.Namespace], Any]]] = {
    "pretrain": ("pretrain a machine policy (A2C for lunarlander, DDPG for uav)", add_recipe_options, _pretrain),
    "run": ("the shared-control protocol of one task, every cell, resumable", add_run_options, _run),
    "sweep": ("the protocol's grid of cells as Ray tasks, here or on a cluster", add_sweep_options, _sweep),
    "reproduce": ("pretrain, run both experiments, write the report", add_reproduce_options, _reproduce),
    "report": ("redraw summaries and figures from <results>/<task>/*.csv", add_report_options, _report),
    "play": ("fly TargetLunarLander yourself, alone or with DC-SC", add_play_options, _play),
}


def build_parser() -> Parser:
    """The ``dcsc`` parser: a sub-command per job, each with its own ``--help``."""
    parser = Parser(prog="dcsc", description=_description(__doc__),
                    epilog="Run `dcsc COMMAND --help` for a command's options; docs/cli.md for the whole story.")
    parser.add_argument("-v", "--verbose", action="store_true", help="more output: TorchRL's INFO lines")
    parser.add_argument("--debug", action="store_true",
                        help="a traceback instead of a one-line error (also DCSC_DEBUG=1)")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for name, (summary, add_options, handler) in COMMANDS.items():
        sub = commands.add_parser(name, help=summary, description=summary, prog=f"dcsc {name}",
                                  epilog=RUN_EPILOG if name == "run" else None)
        if name in ("pretrain", "run"):
            sub.add_argument("task", choices=TASK_NAMES, help="the task")
        elif name == "play":
            sub.add_argument("task", choices=["lunarlander"], help="the task (LunarLander only)")
        add_options(sub)
        _common(sub)
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
