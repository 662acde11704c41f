"""Where a cell's machine comes from: the checkpoint of its pretraining seed, pretrained (or
resumed) first when missing, or the machine shipped with the package; the table of the
recipe that pretrains each task's machine; the expert's Q that ``ida_expert`` reads, the
copilot that ``reddy`` runs and the pretrained arbiter ``dcsc_state`` starts from."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path, load_checkpoint
from dcsc_torchrl.config import ConfigError
from dcsc_torchrl.copilot import TrainedCopilot, load_copilot
from dcsc_torchrl.networks import machine_fingerprint, machine_from_checkpoint, machine_view
from dcsc_torchrl.recipes.settings import pretrain_config
from dcsc_torchrl.state_arbiter import (
    PretrainedArbiter,
    load_pretrained_arbiter,
)
from dcsc_torchrl.tasks import Task


def _train_a2c(cfg: DictConfig, *, resume: bool = False) -> Path:
    from dcsc_torchrl.recipes.pretrain_a2c_lunarlander import train

    return train(cfg, resume=resume)


def _train_ddpg(cfg: DictConfig, *, resume: bool = False) -> Path:
    from dcsc_torchrl.recipes.pretrain_ddpg_uav import train

    return train(cfg, resume=resume)


PRETRAINING: dict[str, Callable[..., Path]] = {"lunarlander": _train_a2c, "uav": _train_ddpg}
"""The recipe that pretrains each task's machine, ``train(cfg, *, resume=False) -> run folder``
(imported on its first call: the recipes load torch and TorchRL)."""


def load_machine_checkpoint(task: Task, cfg: DictConfig, path: Path) -> dict:
    """The checkpoint at ``path``, refused in one line when its machine observes another view
    than ``pretrain.observes`` asks for (both named)."""
    data = load_checkpoint(path, task=task.name, modules=task.checkpoint_modules)
    want = cfg.pretrain.get("observes")
    have = machine_view(data["config"].get("network", {}))
    if want is not None and have != want:
        raise ConfigError(f"{path} holds a machine that observes {have!r}, but pretrain.observes is {want!r}: "
                          f"pretrain one into another pretrain.out_dir, or set pretrain.observes={have}")
    return data


def machine_checkpoint(task: Task, cfg: DictConfig, seed: int) -> Path:
    """Where pretraining seed ``seed``'s machine is read: ``{pretrain.out_dir}/seed{seed}/checkpoint.pt``,
    or with ``pretrain.shipped`` the file shipped with the package (seed 0's)."""
    if cfg.pretrain.shipped:
        from dcsc_torchrl.shipped import shipped_path

        return shipped_path(task, cfg.pretrain.get("observes"))
    return checkpoint_path(cfg.pretrain.out_dir, seed)


def pretrained_machine(task: Task, cfg: DictConfig, seed: int, *, quick: bool) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The machine actor and critic of pretraining seed ``seed``; pretrained first when missing
    (by the task's recipe with the ``pretrain.recipe`` settings: e.g. a converged machine).

    With ``pretrain.shipped`` the machine shipped with the package (seed 0) instead.

    A checkpoint short of its episodes that its run did not finish (a pretraining killed
    halfway) is resumed to the end first; one the run finished early (its landing check
    stopped it, or ``train.keep_best`` kept an earlier machine) is loaded as it is.
    """
    path = machine_checkpoint(task, cfg, seed)
    if cfg.pretrain.shipped:
        return machine_from_checkpoint(load_machine_checkpoint(task, cfg, path), task)
    train = PRETRAINING[task.name]
    if not path.exists():
        print(f"{task.name}: no checkpoint at {path}, pretraining seed {seed} first", file=sys.stderr, flush=True)
        train(pretrain_config(task, cfg, seed, quick=quick))
    data = load_machine_checkpoint(task, cfg, path)
    budget = data["config"].get("train", {}).get("episodes")  # a weights-only file has none
    if budget is not None and not data.get("finished", False) and data.get("episodes", budget) < budget:
        print(f"{task.name}: {path} stopped at episode {data['episodes']}, resuming", file=sys.stderr, flush=True)
        train(pretrain_config(task, cfg, seed, quick=quick), resume=True)
        data = load_machine_checkpoint(task, cfg, path)
    return machine_from_checkpoint(data, task)


def ready_machine(task: Task, cfg: DictConfig, checkpoint: Path | None = None) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The machine a person flies with, never pretrained on the spot (a participant would wait):
    ``checkpoint``; else the first pretraining seed's checkpoint of the config, where ``dcsc run``
    reads it; else, when that was never pretrained, the machine shipped with the package (of the
    config's ``pretrain.observes``).

    Raises:
        ConfigError: ``checkpoint`` is given but is no file, or holds another view's machine (one line).
    """
    if checkpoint is not None and not Path(checkpoint).is_file():
        raise ConfigError(f"--checkpoint: no {task.name} checkpoint at {checkpoint}: run `dcsc pretrain {task.name}` "
                          "first, or leave --checkpoint out for the shipped machine")
    path = Path(checkpoint) if checkpoint is not None else machine_checkpoint(task, cfg, cfg.pretrain.seeds[0])
    if not path.is_file():
        from dcsc_torchrl.shipped import shipped_path

        path = shipped_path(task, cfg.pretrain.get("observes"))
        print(f"no {task.name} checkpoint at {checkpoint_path(cfg.pretrain.out_dir, cfg.pretrain.seeds[0])}: flying "
              f"with the shipped machine ({path.name})", file=sys.stderr, flush=True)
    return machine_from_checkpoint(load_machine_checkpoint(task, cfg, path), task)


def copilot_for(task: Task, cfg: DictConfig, operator: str) -> TrainedCopilot:
    """Method ``reddy``'s copilot of ``task`` next to ``operator``: the first of ``reddy.copilots`` that was
    not trained with it (Reddy's copilot never meets its training pilots in an evaluation).

    Raises:
        ConfigError: ``reddy.copilots`` is not set, names a file that holds no copilot, or every
            copilot was trained with ``operator`` (one line).
    """
    paths = cfg.reddy.copilots
    if not paths:
        raise ConfigError(f"method reddy needs reddy.copilots: trained copilots (dcsc copilot {task.name} writes copilot.pt), "
                          f"e.g. reddy.copilots=[runs/copilot_{task.name}/copilot.pt]")
    pools = []
    for path in paths:
        if not Path(path).is_file():
            raise ConfigError(f"reddy.copilots: no copilot at {path}")
        copilot = load_copilot(path, task)
        if operator not in copilot.operators:
            return copilot
        pools.append(f"{path}: {', '.join(copilot.operators)}")
    raise ConfigError(f"reddy.copilots: every copilot was trained with operator {operator!r} ({'; '.join(pools)}): "
                      f"train one without it (dcsc copilot {task.name} pool=[...])")


def state_arbiter_for(task: Task, cfg: DictConfig, operator: str,
                      machine_net: torch.nn.Module | None = None) -> PretrainedArbiter:
    """Method ``dcsc_state``'s pretrained arbiter next to ``operator``: the first of
    ``state.arbiters`` whose pool lacks it and, given ``machine_net``, that was pretrained next
    to that machine (without it: the first whose pool lacks it, as a check before any cell).

    Raises:
        ConfigError: ``state.arbiters`` is not set or names a file that holds no such arbiter,
            or no arbiter fits (one line naming each file's pool and machine), or the one that fits
            cannot be refitted as ``warmup.refit_state_arbiter`` asks.
    """
    paths = cfg.state.arbiters if "state" in cfg else None
    if not paths:
        raise ConfigError(f"method dcsc_state needs state.arbiters: pretrained arbiters (dcsc arbiter {task.name} "
                          f"writes arbiter.pt), e.g. state.arbiters=[runs/arbiter_{task.name}/arbiter.pt]")
    fingerprint = None if machine_net is None else machine_fingerprint(machine_net)
    seen = []
    for path in paths:
        if not Path(path).is_file():
            raise ConfigError(f"state.arbiters: no pretrained arbiter at {path}")
        pretrained = load_pretrained_arbiter(path, task)
        if operator not in pretrained.operators and fingerprint in (None, pretrained.machine):
            if cfg.warmup.refit_state_arbiter:
                try:
                    pretrained.check_refittable()
                except ValueError as err:
                    raise ConfigError(f"{err} ({path})") from None
            return pretrained
        seen.append(f"{path}: pool {', '.join(pretrained.operators)}, machine {pretrained.machine}")
    machine = "" if fingerprint is None else f" and machine {fingerprint}"
    raise ConfigError(f"state.arbiters: none was pretrained without operator {operator!r}{machine} ({'; '.join(seen)}): "
                      f"pretrain one (dcsc arbiter {task.name} state.pool=[...])")


def expert_q(task: Task, cfg: DictConfig) -> torch.nn.Module:
    """The expert's Q network of method ``ida_expert``: the critic of the pretraining checkpoint
    ``ida.expert`` (of this task; whatever its machine observes: LunarLander's Q critic sees
    the whole state either way).

    Raises:
        ConfigError: ``ida.expert`` is not set, or names no checkpoint of this task (one line).
    """
    path = cfg.ida.expert
    if path is None:
        raise ConfigError("method ida_expert needs ida.expert: a pretraining checkpoint whose critic is the "
                          "expert's Q (e.g. ida.expert=runs/map/target-converged/seed0/checkpoint.pt)")
    if not Path(path).is_file():
        raise ConfigError(f"ida.expert: no checkpoint at {path}")
    return machine_from_checkpoint(load_checkpoint(path, task=task.name, modules=task.checkpoint_modules), task)[1]
