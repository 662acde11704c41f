"""Train Reddy et al.'s copilot of a task: DQN with surrogate pilots in the loop.

The copilot (:mod:`dcsc_torchrl.copilot`) is a Q network on what the task lets it see and the
pilot's action (:attr:`~dcsc_torchrl.task.Task.make_copilot_network`: on LunarLander the 4 keys,
the pad's x masked; on the UAV the operator's 27 grid points). It learns by TorchRL's
``DQNLoss`` (hard target updates) from fresh scenarios (:attr:`~dcsc_torchrl.task.Task.make_copilot_envs`)
flown by the shared action: the pilot's where it is within ``dqn.train_alpha`` of the copilot's
best, else the copilot's epsilon-greedy action (:func:`~dcsc_torchrl.copilot.tolerant_choice`).
The pilots are ``pool``'s operator presets, one per segment of ``train.checkpoint_every``
episodes in turn. The settings are RL-Zoo's DQN for LunarLander, fixed before any run. Then
the tolerance ``alpha`` is chosen on development scenarios (``alpha.first_seed``, never the
validation seeds) with the pool's pilots: the alpha of the highest mean success (ties: the
larger, the pilot keeping more control). The copilot checkpoint records its pool, and a cell
next to one of those operators refuses it.

    dcsc copilot TASK [--quick] [--resume] [--out DIR] [key=value ...]

Outputs in the run folder (``--out``; default ``logger.out_dir`` of recipes/copilot_<task>.yaml):
``train.csv`` (one row per episode), ``checkpoint.pt`` (the training run's, resumable),
``learning_curve.png``, ``alpha.csv`` (development success per alpha and pilot) and
``copilot.pt``, what ``dcsc run`` reads (``reddy.copilots``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType
from torchrl.modules import QValueModule
from torchrl.objectives import DQNLoss, HardUpdate

from dcsc_torchrl.config import ConfigError, load_config, to_plain, writable_folder
from dcsc_torchrl.copilot import (
    CopilotQNetwork,
    TrainedCopilot,
    copilot_task,
    nearest_action,
    save_copilot,
    tolerant_choice,
)
from dcsc_torchrl.episodes import run_scenarios
from dcsc_torchrl.humans import PRESETS
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.options import Parser, add_copilot_options, description
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.tasks import COPILOT_TASK_NAMES, Task, get_task
from dcsc_torchrl.training import TrainingRun, make_collector
from dcsc_torchrl.transforms import (
    FirstEpisodeOnly,
    HumanConfidenceTransform,
    HumanOperatorTransform,
)

COLUMNS = ["episode", "frames", "return", "steps", "success", "pilot", "epsilon", "loss"]
CHOICE_KEY = "copilot_action"
"""Where the training run writes the copilot's choice, one-hot over its actions (DQN's action;
the env's ``action`` is that action's value)."""


class ExploringCopilot(TensorDictModuleBase):
    """The training run's shared action: the pilot's where it is within ``alpha`` of the copilot's
    best, else the copilot's (:func:`~dcsc_torchrl.copilot.tolerant_choice`), a uniformly random
    one of its actions with probability ``epsilon``. Writes the choice one-hot (``copilot_action``,
    what DQN learns) and its value (``action``, what the env takes)."""

    def __init__(self, network: CopilotQNetwork, alpha: float) -> None:
        super().__init__()
        self.network, self.alpha, self.epsilon = network, alpha, 1.0
        self.in_keys, self.out_keys = ["observation", "human_action"], [CHOICE_KEY, "action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation, pilot = tensordict.get("observation"), tensordict.get("human_action")
        actions = self.network.actions
        with torch.no_grad():
            q_values = self.network(observation, pilot)
        copilot, kept = tolerant_choice(q_values, actions, pilot, self.alpha)
        explore = torch.rand(copilot.shape[:-1]) < self.epsilon
        drawn = torch.randint(0, len(actions), copilot.shape[:-1])
        copilot = torch.where(explore, drawn, copilot.squeeze(-1)).unsqueeze(-1)
        choice = torch.where(kept, nearest_action(actions, pilot), copilot).squeeze(-1)
        tensordict.set(CHOICE_KEY, torch.nn.functional.one_hot(choice, len(actions)).to(observation.dtype))
        tensordict.set("action", actions[choice].to(pilot.dtype))
        return tensordict


def check(cfg: DictConfig) -> None:
    """Refuses a pool naming an unknown preset, naming it (the ranges are the config's LIMITS)."""
    unknown = [name for name in cfg.pool if name not in PRESETS]
    if unknown:
        raise ConfigError(f"pool: unknown operator preset(s) {unknown}: expected names of {', '.join(PRESETS)}")


def pilot_envs(task: Task, pilot: str, num_envs: int, *, seed: int) -> TransformedEnv:
    """``num_envs`` fresh scenarios of ``task`` with preset ``pilot`` in the loop (its noise
    seeded with ``seed``)."""
    return task.make_copilot_envs(num_envs, [HumanOperatorTransform(task.make_operator(pilot), seed=seed)])


def development_success(task: Task, copilot: CopilotQNetwork, alpha: float, pilot: str, cfg: DictConfig,
                        settings: dict[str, Any]) -> float:
    """The success of the copilot at tolerance ``alpha`` next to ``pilot`` on the development scenarios
    (``settings``: the protocol's cell settings, whose confidence and rollout the runs use)."""
    seeds = list(range(cfg.alpha.first_seed, cfg.alpha.first_seed + cfg.alpha.scenarios))
    transforms = [FirstEpisodeOnly(), HumanOperatorTransform(task.make_operator(pilot), seed=cfg.alpha.first_seed),
                  HumanConfidenceTransform(**settings["human"])]
    env = task.make_envs(seeds, None, transforms)
    policy = TrainedCopilot(copilot, alpha, ()).policy(env.full_action_spec["action"])
    result = run_scenarios(env, policy, task, rollout_length=settings["protocol"].rollout_length,
                           exploration_type=ExplorationType.MODE)
    env.close()
    return sum(row["success"] for row in result.rows) / len(result.rows)


def train(cfg: DictConfig, *, resume: bool = False) -> Path:
    """Trains the copilot of ``cfg`` (:func:`copilot_config`'s, checked: its ``task``) into
    ``cfg.logger.out_dir``, chooses its alpha; returns ``copilot.pt``."""
    task = get_task(cfg.task)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    start = time.perf_counter()
    network = task.make_copilot_network(cfg.network.hidden)
    value = TensorDictSequential(
        TensorDictModule(network, in_keys=["observation", "human_action"], out_keys=["action_value"]),
        QValueModule(action_space="one_hot", out_keys=[CHOICE_KEY, "action_value", "chosen_action_value"]),
    )
    loss = DQNLoss(value, action_space="one_hot", delay_value=True)
    loss.set_keys(action=CHOICE_KEY)
    loss.make_value_estimator(gamma=cfg.dqn.gamma)
    target = HardUpdate(loss, value_network_update_interval=cfg.dqn.target_update_interval)
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.dqn.lr, foreach=True)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.dqn.buffer_size), batch_size=cfg.dqn.batch_size)
    explorer = ExploringCopilot(network, cfg.dqn.train_alpha)
    run = TrainingRun(copilot_task(task), out_dir=cfg.logger.out_dir, episodes=cfg.train.episodes,
                      frames=cfg.train.frames, checkpoint_every=cfg.train.checkpoint_every, seed=cfg.seed,
                      config=to_plain(cfg), columns=COLUMNS,
                      stateful={"copilot": network, "loss": loss, "optim": optim, "buffer": buffer})
    pending = 0.0  # gradient steps owed (updates_per_frame may give a fraction per batch)

    def update(batch: TensorDictBase) -> dict[str, float]:
        nonlocal pending
        explorer.epsilon = max(cfg.dqn.exploration_final_eps,
                               1.0 - run.progress / cfg.dqn.exploration_fraction * (1.0 - cfg.dqn.exploration_final_eps))
        buffer.extend(batch.reshape(-1).select(*loss.in_keys, strict=False).clone())
        pending += cfg.dqn.updates_per_frame * batch.numel()
        total = torch.zeros(())
        steps = 0
        while pending >= 1.0 and len(buffer) >= cfg.dqn.batch_size:
            value_loss = loss(buffer.sample())["loss"]
            optim.zero_grad()
            value_loss.backward()
            optim.step()
            target.step()
            total, steps, pending = total + value_loss.detach(), steps + 1, pending - 1.0
        return {"pilot": pilot_of(run.segment), "epsilon": explorer.epsilon, "loss": (total / max(steps, 1)).item()}

    def pilot_of(segment: int) -> str:
        return cfg.pool[segment % len(cfg.pool)]

    run.start(resume=resume)
    frames_per_batch = cfg.env.num_envs * cfg.env.rollout_length
    run.train(lambda seed: make_collector(partial(pilot_envs, task, pilot_of(run.segment), seed=seed), cfg.env.num_envs,
                                          explorer, workers=1, seed=seed, frames_per_batch=frames_per_batch),
              update)
    run.finish(f"Reddy et al.'s copilot: DQN with {', '.join(cfg.pool)} in the loop")
    train_seconds = time.perf_counter() - start

    network.eval()
    settings = cell_settings(task_config(task))
    rows = [{"alpha": float(alpha), "pilot": pilot,
             "success": development_success(task, network, float(alpha), pilot, cfg, settings)}
            for alpha in cfg.alpha.grid for pilot in cfg.pool]
    table = pd.DataFrame(rows)
    table.to_csv(Path(cfg.logger.out_dir) / "alpha.csv", index=False)
    means = table.groupby("alpha")["success"].mean()
    alpha = float(means[means == means.max()].index.max())
    copilot = TrainedCopilot(network.requires_grad_(False), alpha, tuple(cfg.pool))
    return save_copilot(Path(cfg.logger.out_dir) / "copilot.pt", task, copilot, to_plain(cfg),
                        frames=run.frames, episodes=run.episodes, train_seconds=train_seconds,
                        seconds=time.perf_counter() - start, alpha_table=rows)


def copilot_config(task: Task, overrides: Sequence[str] = (), *, quick: bool = False,
                   out: Path | None = None) -> DictConfig:
    """``task``'s copilot config (recipes/copilot_<task>.yaml) with ``overrides``, checked, writing
    to ``out`` (default ``logger.out_dir``)."""
    cfg = load_config(CONFIGS[task.name].copilot, overrides, quick=quick)
    check(cfg)
    cfg.logger.out_dir = str(writable_folder(out or Path(cfg.logger.out_dir)))
    return cfg


def main(argv: Sequence[str] | None = None) -> Path:
    """``dcsc copilot``'s command line (``python recipes/copilot.py`` takes the same)."""
    parser = Parser(description=description(__doc__))
    parser.add_argument("task", choices=COPILOT_TASK_NAMES, help="the task")
    args = add_copilot_options(parser).parse_args(argv)
    return train(copilot_config(get_task(args.task), args.overrides, quick=args.quick, out=args.out),
                 resume=args.resume)


if __name__ == "__main__":
    main()
