"""The machines that ship with the package: the paper's setting, pretraining seed 0, weights only;
beside LunarLander's machine that sees the pad, a state-dependent arbiter pretrained next to it.

``dcsc_torchrl/pretrained/<task>[_<view>]_seed0.pt`` holds the actor and critic state dicts
of ``dcsc pretrain <task> seed=0`` (500 episodes; LunarLander's in both machine views), the
network config they were built with, the greedy return of one recorded episode and the command that
produced them (also in ``pretrained/README.md``). They load into the recipe's own
networks (:attr:`Task.make_networks`), so ``dcsc run <task> pretrain.shipped=true``,
``dcsc play --assist dcsc`` and a first try work without pretraining; ``make reproduce``
still pretrains from scratch.

``<machine file's stem>_state.pt`` is the state-dependent arbiter ``dcsc arbiter <task>
pretrain.shipped=true`` pretrains next to that shipped machine (its default pool), the
default of ``dcsc play lunarlander --assist state``.

    dcsc ship TASK CHECKPOINT    # re-export a pretraining checkpoint, or a pretrained arbiter (arbiter.pt)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dcsc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from dcsc_torchrl.networks import machine_fingerprint, machine_from_checkpoint, view_recipe_settings
from dcsc_torchrl.task import Task

SHIPPED_DIR = Path(__file__).parent / "pretrained"
SHIPPED_SEED = 0
GREEDY_SEED = 12_345
"""The seed of the recorded greedy episode (standard pad / UAV scenario), apart from every protocol range."""


def shipped_path(task: Task, observes: str | None = None) -> Path:
    """Where ``task``'s shipped machine lies: ``<task>_seed0.pt`` for a task with one machine
    (``observes`` ``None``, the UAV), ``<task>_<observes>_seed0.pt`` for LunarLander's two
    (``target``, the paper's; ``blind``, the goal-blind one)."""
    view = "" if observes is None else f"_{observes}"
    return SHIPPED_DIR / f"{task.name}{view}_seed{SHIPPED_SEED}.pt"


def shipped_arbiter_path(task: Task, observes: str | None = None) -> Path:
    """Where the state-dependent arbiter pretrained next to ``task``'s shipped machine (of
    ``observes``) lies: ``<machine file's stem>_state.pt``."""
    machine = shipped_path(task, observes)
    return machine.with_name(f"{machine.stem}_state.pt")


def greedy_return(task: Task, actor: torch.nn.Module) -> float:
    """The return of one greedy, dropout-free episode of the machine alone on :data:`GREEDY_SEED`.

    LunarLander flies the standard pad (what the machine is pretrained on); the UAV flies
    scenario :data:`GREEDY_SEED`.
    """
    from tensordict.nn import TensorDictModule
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env = task.make_pretraining_envs(1) if task.discrete else task.make_envs([GREEDY_SEED], None, [])
    env.set_seed(GREEDY_SEED)
    out_key = "logits" if task.discrete else "action"
    policy = TensorDictModule(actor.eval(), ["observation"], [out_key])
    if task.discrete:
        from torchrl.modules import OneHotCategorical, ProbabilisticActor

        policy = ProbabilisticActor(policy, ["logits"], spec=env.full_action_spec["action"],
                                    distribution_class=OneHotCategorical)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout = env.rollout(task.max_steps, policy)
    env.close()
    return float(rollout["next", "reward"].sum())


def export_machine(task: Task, checkpoint: str | Path, out: str | Path | None = None) -> Path:
    """Writes the actor and critic of a pretraining ``checkpoint`` as ``task``'s shipped machine."""
    data = load_checkpoint(checkpoint, task=task.name)
    actor, _ = machine_from_checkpoint(data, task)
    observes = data["config"]["network"].get("observes")
    view = "".join(f" {setting}" for setting in view_recipe_settings(observes)) if observes else ""
    names = task.checkpoint_modules
    payload: dict[str, Any] = {
        "state": {name: data["state"][name] for name in names},
        "config": {"network": data["config"]["network"], "seed": data["config"]["seed"]},
        "episodes": data["episodes"],
        "frames": data["frames"],
        "greedy_return": greedy_return(task, actor),
        "command": f"dcsc pretrain {task.name} seed={data['config']['seed']}{view}",
    }
    return save_checkpoint(out or shipped_path(task, observes), task=task.name, payload=payload)


def export_arbiter(task: Task, checkpoint: str | Path, out: str | Path | None = None) -> Path:
    """Writes a pretrained arbiter (``dcsc arbiter``'s ``arbiter.pt``) as the one shipped beside the
    shipped machine it was pretrained next to (:func:`shipped_arbiter_path`).

    Raises:
        ValueError: an arbiter pretrained next to another machine than the shipped one of its
            config's ``pretrain.observes`` (one line).
    """
    from dcsc_torchrl.state_arbiter import load_pretrained_arbiter, state_arbiter_task

    pretrained = load_pretrained_arbiter(checkpoint, task)  # refuses anything but a pretrained arbiter
    data = load_checkpoint(checkpoint, task=state_arbiter_task(task))
    observes = data["config"]["pretrain"].get("observes")
    shipped = machine_fingerprint(shipped_machine(task, observes)[0])
    if pretrained.machine != shipped:
        raise ValueError(f"{checkpoint} was pretrained next to machine {pretrained.machine}, not the shipped one "
                         f"({shipped}): pretrain it with `dcsc arbiter {task.name} pretrain.shipped=true`")
    view = "" if observes is None else f" pretrain.observes={observes}"
    payload = {key: value for key, value in data.items() if key not in ("format_version", "task")}
    payload["command"] = f"dcsc arbiter {task.name} pretrain.shipped=true{view}"
    return save_checkpoint(out or shipped_arbiter_path(task, observes), task=data["task"], payload=payload)


def load_shipped(task: Task, observes: str | None = None) -> dict[str, Any]:
    """The shipped file of ``task`` (that ``observes``: :func:`shipped_path`), as :func:`load_checkpoint` reads it."""
    return load_checkpoint(shipped_path(task, observes), task=task.name)


def shipped_machine(task: Task, observes: str | None = None) -> tuple[torch.nn.Module, torch.nn.Module]:
    """``task``'s shipped actor and critic (that ``observes``), in the recipe's networks, in eval mode."""
    return machine_from_checkpoint(load_shipped(task, observes), task)
