"""Pretrain the UAV machine: DDPG on IIFDS path planning (paper §6.1, Table A2).

A TorchRL ``Collector`` over the batched UAV env (a fresh scenario per episode), DDPG with
target actor and critic soft-updated by polyak averaging, Gaussian exploration noise
annealed from Table A2's initial std. The actor has dropout 0.05 (MC dropout samples it
later, Eq. 10) and outputs (rho0, sigma0, tau) in [0, 3]. Stops after ``train.episodes``
episodes, with atomic checkpoints every ``train.checkpoint_every`` episodes and
``--resume``.

    dcsc pretrain uav [--quick] [--resume] [--out DIR] [key=value ...]    # or: python recipes/pretrain_ddpg_uav.py ...

Outputs in the run folder (``--out``; by default ``<pretrain.out_dir>/seed<seed>/`` of the task's protocol
yaml, where ``dcsc run`` reads the machine): ``train.csv``, ``checkpoint.pt``, ``learning_curve.png``
and ``eval.csv`` (machine-only greedy episodes on the 50 validation scenarios).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import AdditiveGaussianModule, ValueOperator
from torchrl.objectives import DDPGLoss, ValueEstimators

from dcsc_torchrl.batched_envs import UAV_INFO_KEYS, make_uav_env
from dcsc_torchrl.config import to_plain
from dcsc_torchrl.losses import ForeachSoftUpdate
from dcsc_torchrl.networks import uav_actor, uav_critic
from dcsc_torchrl.recipes import pretrain
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.training import (
    TrainingRun,
    greedy_episodes,
    make_collector,
)

CONFIG = CONFIGS["uav"].pretrain
COLUMNS = ["episode", "frames", "return", "steps", "success", "loss_actor", "loss_value"]


def train(cfg: DictConfig, *, resume: bool = False) -> Path:
    """Pretrains the machine of ``cfg`` into ``cfg.logger.out_dir`` (from its last checkpoint with
    ``resume``); returns the learning curve's PNG."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    device = torch.device(cfg.device)

    # --- networks: actor (with dropout) and Q(s, a) critic ------------------------------
    actor_net = uav_actor(cfg.network.hidden, cfg.network.actor_dropout).to(device)
    critic_net = uav_critic(cfg.network.hidden).to(device)
    actor = TensorDictModule(actor_net, in_keys=["observation"], out_keys=["action"])
    critic = ValueOperator(critic_net, in_keys=["observation", "action"])
    action_spec = make_uav_env(1, device=device).full_action_spec["action"]
    exploration = AdditiveGaussianModule(
        action_spec,
        sigma_init=cfg.exploration.sigma_init,
        sigma_end=cfg.exploration.sigma_end,
        annealing_num_steps=cfg.exploration.annealing_frames,
        device=device,
    )
    explorer = TensorDictSequential(actor, exploration)

    # --- loss, target networks, optimisers ----------------------------------------------
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.loss.gamma)
    targets = ForeachSoftUpdate(loss, eps=cfg.loss.polyak)
    actor_optim = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=cfg.optim.actor_lr, foreach=True)
    critic_optim = torch.optim.Adam(loss.value_network_params.values(True, True), lr=cfg.optim.critic_lr, foreach=True)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.optim.buffer_size, device=device),
                          batch_size=cfg.optim.batch_size)

    def step(optim: torch.optim.Optimizer, value: torch.Tensor) -> None:
        optim.zero_grad()
        value.backward()
        torch.nn.utils.clip_grad_norm_([p for group in optim.param_groups for p in group["params"]],
                                       cfg.optim.grad_clip)
        optim.step()

    updates_owed = 0.0

    def update(batch) -> dict[str, float]:
        nonlocal updates_owed
        buffer.extend(batch.reshape(-1).select(*loss.in_keys, strict=False).clone())  # what the loss reads
        exploration.step(batch.numel())
        metrics: dict[str, float] = {}  # no update yet: the loss columns stay empty
        if len(buffer) < cfg.collector.init_random_frames:
            return metrics
        updates_owed += cfg.optim.updates_per_frame * batch.numel()
        while updates_owed >= 1:
            updates_owed -= 1
            sample = buffer.sample()
            loss_value, _ = loss.loss_value(sample)
            step(critic_optim, loss_value)
            loss_actor, _ = loss.loss_actor(sample)
            step(actor_optim, loss_actor)
            targets.step()
            metrics = {"loss_actor": loss_actor.item(), "loss_value": loss_value.item()}
        return metrics

    # --- training, in checkpointed segments ---------------------------------------------
    run = TrainingRun(
        "uav", out_dir=cfg.logger.out_dir, episodes=cfg.train.episodes, checkpoint_every=cfg.train.checkpoint_every,
        seed=cfg.seed, config=to_plain(cfg), columns=COLUMNS,
        stateful={"actor": actor_net, "critic": critic_net, "loss": loss, "exploration": exploration,
                  "actor_optim": actor_optim, "critic_optim": critic_optim, "buffer": buffer},
    )
    run.start(resume=resume)
    frames_per_batch = cfg.env.num_envs * cfg.collector.rollout_length
    run.train(
        lambda seed: make_collector(
            partial(make_uav_env, device=device, collision_reward=cfg.env.collision_reward), cfg.env.num_envs,
            explorer, workers=cfg.collector.workers, seed=seed, frames_per_batch=frames_per_batch,
            init_random_frames=max(0, cfg.collector.init_random_frames - run.frames),
        ),
        update,
    )
    curve = run.finish("DDPG on UAV path planning")

    # --- machine-only evaluation on the validation scenarios (0 scenarios: skip) --------
    if cfg.eval.scenarios > 0:
        env = make_uav_env(cfg.eval.scenarios, scenario_seeds=list(range(cfg.eval.scenarios)), device=device)
        rows = greedy_episodes(env, actor, 501, list(UAV_INFO_KEYS))
        pd.DataFrame(rows).rename(columns={"env": "scenario"}).to_csv(run.out_dir / "eval.csv", index=False)
    return curve


def main(argv: Sequence[str] | None = None) -> Path:
    """``dcsc pretrain uav``'s command line and defaults (:func:`dcsc_torchrl.recipes.pretrain.main`)."""
    return pretrain.main("uav", train, __doc__, argv)


if __name__ == "__main__":
    main()
