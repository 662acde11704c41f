"""``dcsc pretrain TASK``: one pretraining run of a task's machine, into the folder where
``dcsc run`` reads it (docs/pretraining.md).

The recipe scripts (``python recipes/pretrain_a2c_lunarlander.py ...``) are thin mains of
:func:`pretrain` with the same options and defaults, so a machine pretrained either way is
found by ``dcsc run``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path
from dcsc_torchrl.config import load_config, writable_folder
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.options import Parser, add_recipe_options, description

Train = Callable[..., Path]
"""A pretraining recipe's ``train(cfg: DictConfig, *, resume: bool = False) -> run folder``."""


def pretrain_run_config(task_name: str, overrides: Sequence[str] = (), *, quick: bool = False,
                        out: Path | None = None) -> DictConfig:
    """The pretraining config of ``task_name`` with ``overrides``, checked, writing to ``out``, else to a
    ``logger.out_dir=`` of ``overrides``, else to ``<pretrain.out_dir>/seed<seed>/`` of the task's
    protocol yaml (same ``--quick``), where ``dcsc run`` reads the seed's machine."""
    configs = CONFIGS[task_name]
    cfg = load_config(configs.pretrain, overrides, quick=quick)
    if out is None and not any(item.partition("=")[0] == "logger.out_dir" for item in overrides):
        out = checkpoint_path(load_config(configs.protocol, quick=quick).pretrain.out_dir, cfg.seed).parent
    cfg.logger.out_dir = str(writable_folder(out or cfg.logger.out_dir))
    return cfg


def pretrain(task_name: str, train: Train, overrides: Sequence[str] = (), *, quick: bool = False,
             resume: bool = False, out: Path | None = None) -> Path:
    """Pretrains (or, with ``resume``, continues) ``task_name``'s machine with its recipe's ``train``;
    returns the run folder, which holds ``checkpoint.pt``."""
    cfg = pretrain_run_config(task_name, overrides, quick=quick, out=out)
    train(cfg, resume=resume)
    return Path(cfg.logger.out_dir)


def main(task_name: str, train: Train, doc: str | None, argv: Sequence[str] | None = None) -> Path:
    """A recipe script's command line, ``[--quick] [--resume] [--out DIR] [key=value ...]``, as
    ``dcsc pretrain TASK`` takes it."""
    args = add_recipe_options(Parser(description=description(doc))).parse_args(argv)
    return pretrain(task_name, train, args.overrides, quick=args.quick, resume=args.resume, out=args.out)
