"""Train Reddy et al.'s copilot on TargetLunarLander: DQN with surrogate pilots in the loop.

The copilot (:mod:`dcsc_torchrl.copilot`) is a Q network on the goal-masked observation and the
pilot's one-hot key. It learns by TorchRL's ``DQNLoss`` (hard target updates) from the frames of
TargetLunarLanders with a random pad, flown by the shared action: the pilot's key where it is
within ``dqn.train_alpha`` of the copilot's best, else the copilot's epsilon-greedy key. The pilots
are ``pool``'s operator presets, one per segment of ``train.checkpoint_every`` episodes in turn.
The settings are RL-Zoo's DQN for LunarLander, fixed before any run. Then the tolerance
``alpha`` is chosen on development scenarios (``alpha.first_seed``, never the validation seeds)
with the pool's pilots: the alpha of the highest mean success (ties: the larger, the pilot
keeping more control). The copilot checkpoint records its pool, and a cell next to one of
those operators refuses it.

    dcsc copilot [--quick] [--resume] [--out DIR] [key=value ...]

Outputs in the run folder (``--out``; default ``logger.out_dir``): ``train.csv`` (one row per
episode), ``checkpoint.pt`` (the training run's, resumable), ``learning_curve.png``,
``alpha.csv`` (development success per alpha and pilot) and ``copilot.pt``, what ``dcsc run``
reads (``reddy.copilot``).
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

from dcsc_torchrl.batched_envs import make_lunar_env
from dcsc_torchrl.config import ConfigError, load_config, to_plain, writable_folder
from dcsc_torchrl.copilot import CopilotQNetwork, TrainedCopilot, keeps_pilot, save_copilot
from dcsc_torchrl.episodes import run_scenarios
from dcsc_torchrl.humans import PRESETS
from dcsc_torchrl.recipes.configs import COPILOT_CONFIG
from dcsc_torchrl.recipes.options import Parser, add_copilot_options, description
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.tasks import get_task
from dcsc_torchrl.training import TrainingRun, make_collector
from dcsc_torchrl.transforms import (
    FirstEpisodeOnly,
    HumanConfidenceTransform,
    HumanOperatorTransform,
)

COLUMNS = ["episode", "frames", "return", "steps", "success", "pilot", "epsilon", "loss"]
TASK = get_task("lunarlander")


class ExploringCopilot(TensorDictModuleBase):
    """The training run's shared action: the pilot's key within ``alpha`` of the copilot's best
    (:func:`~dcsc_torchrl.copilot.keeps_pilot`), else the copilot's key, uniformly random with
    probability ``epsilon``."""

    def __init__(self, network: CopilotQNetwork, alpha: float) -> None:
        super().__init__()
        self.network, self.alpha, self.epsilon = network, alpha, 1.0
        self.in_keys, self.out_keys = ["observation", "human_action"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation, pilot = tensordict.get("observation"), tensordict.get("human_action")
        with torch.no_grad():
            q_values = self.network(observation, pilot)
        best = q_values.argmax(-1)
        explore = torch.rand(best.shape) < self.epsilon
        keys = torch.where(explore, torch.randint(0, q_values.shape[-1], best.shape), best)
        copilot = torch.nn.functional.one_hot(keys, q_values.shape[-1]).to(pilot.dtype)
        tensordict.set("action", torch.where(keeps_pilot(q_values, pilot, self.alpha), pilot, copilot))
        return tensordict


def check(cfg: DictConfig) -> None:
    """Refuses a pool naming an unknown preset, naming it (the ranges are the config's LIMITS)."""
    unknown = [name for name in cfg.pool if name not in PRESETS]
    if unknown:
        raise ConfigError(f"pool: unknown operator preset(s) {unknown}: expected names of {', '.join(PRESETS)}")


def pilot_envs(pilot: str, num_envs: int, *, seed: int) -> TransformedEnv:
    """``num_envs`` TargetLunarLanders with a random pad and preset ``pilot`` in the loop (its
    noise seeded with ``seed``)."""
    return make_lunar_env(num_envs, random_pad=True,
                          transforms=[HumanOperatorTransform(TASK.make_operator(pilot), seed=seed)])


def development_success(copilot: CopilotQNetwork, alpha: float, pilot: str, cfg: DictConfig,
                        settings: dict[str, Any]) -> float:
    """The success of the copilot at tolerance ``alpha`` next to ``pilot`` on the development scenarios
    (``settings``: the protocol's cell settings, whose confidence and rollout the runs use)."""
    seeds = list(range(cfg.alpha.first_seed, cfg.alpha.first_seed + cfg.alpha.scenarios))
    transforms = [FirstEpisodeOnly(), HumanOperatorTransform(TASK.make_operator(pilot), seed=cfg.alpha.first_seed),
                  HumanConfidenceTransform(**settings["human"])]
    env = TASK.make_envs(seeds, None, transforms)
    policy = TrainedCopilot(copilot, alpha, ()).policy(env.full_action_spec["action"])
    result = run_scenarios(env, policy, TASK, rollout_length=settings["protocol"].rollout_length,
                           exploration_type=ExplorationType.MODE)
    env.close()
    return sum(row["success"] for row in result.rows) / len(result.rows)


def train(cfg: DictConfig, *, resume: bool = False) -> Path:
    """Trains the copilot of ``cfg`` (:func:`copilot_config`'s, checked) into ``cfg.logger.out_dir``,
    chooses its alpha; returns ``copilot.pt``."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    start = time.perf_counter()
    network = CopilotQNetwork(cfg.network.hidden)
    value = TensorDictSequential(
        TensorDictModule(network, in_keys=["observation", "human_action"], out_keys=["action_value"]),
        QValueModule(action_space="one_hot"),
    )
    loss = DQNLoss(value, action_space="one_hot", delay_value=True)
    loss.make_value_estimator(gamma=cfg.dqn.gamma)
    target = HardUpdate(loss, value_network_update_interval=cfg.dqn.target_update_interval)
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.dqn.lr, foreach=True)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.dqn.buffer_size), batch_size=cfg.dqn.batch_size)
    explorer = ExploringCopilot(network, cfg.dqn.train_alpha)
    run = TrainingRun("lunarlander-copilot", out_dir=cfg.logger.out_dir, episodes=cfg.train.episodes,
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
    run.train(lambda seed: make_collector(partial(pilot_envs, pilot_of(run.segment), seed=seed), cfg.env.num_envs,
                                          explorer, workers=1, seed=seed, frames_per_batch=frames_per_batch),
              update)
    run.finish(f"Reddy et al.'s copilot: DQN with {', '.join(cfg.pool)} in the loop")
    train_seconds = time.perf_counter() - start

    network.eval()
    settings = cell_settings(task_config(TASK))
    rows = [{"alpha": float(alpha), "pilot": pilot,
             "success": development_success(network, float(alpha), pilot, cfg, settings)}
            for alpha in cfg.alpha.grid for pilot in cfg.pool]
    table = pd.DataFrame(rows)
    table.to_csv(Path(cfg.logger.out_dir) / "alpha.csv", index=False)
    means = table.groupby("alpha")["success"].mean()
    alpha = float(means[means == means.max()].index.max())
    copilot = TrainedCopilot(network.requires_grad_(False), alpha, tuple(cfg.pool))
    return save_copilot(Path(cfg.logger.out_dir) / "copilot.pt", copilot, to_plain(cfg),
                        frames=run.frames, episodes=run.episodes, train_seconds=train_seconds,
                        seconds=time.perf_counter() - start, alpha_table=rows)


def copilot_config(overrides: Sequence[str] = (), *, quick: bool = False, out: Path | None = None) -> DictConfig:
    """The copilot recipe's config with ``overrides``, checked, writing to ``out`` (default ``logger.out_dir``)."""
    cfg = load_config(COPILOT_CONFIG, overrides, quick=quick)
    check(cfg)
    cfg.logger.out_dir = str(writable_folder(out or Path(cfg.logger.out_dir)))
    return cfg


def main(argv: Sequence[str] | None = None) -> Path:
    """``dcsc copilot``'s command line (``python recipes/copilot_lunarlander.py`` takes the same)."""
    args = add_copilot_options(Parser(description=description(__doc__))).parse_args(argv)
    return train(copilot_config(args.overrides, quick=args.quick, out=args.out), resume=args.resume)


if __name__ == "__main__":
    main()
