"""Pretrain the LunarLander machine: A2C + a Q critic (paper §6.1, Table A1; DESIGN §5).

A2C with GAE over batched TargetLunarLander envs (pad at the centre: the standard task).
The actor is an MLP with dropout (MC dropout samples it later, Eq. 10) that sees the 8
standard values, not the pad. Beside it a Q critic learns Q(s, a) from a replay buffer
by the TD loss of Algorithm 1 — DC-SC's theta update needs Q. Training stops after
``train.episodes`` episodes; every ``train.checkpoint_every`` episodes an atomic
checkpoint is written, and ``--resume`` continues from the last one.

    python recipes/pretrain_a2c_lunarlander.py [--quick] [--resume] [--out DIR] [key=value ...]

Outputs in ``logger.out_dir``: ``train.csv`` (one row per episode), ``checkpoint.pt``,
``learning_curve.png`` and ``eval.csv`` (machine-only greedy episodes, standard and moved pad).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

import pandas as pd
import torch
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import OneHotCategorical, ProbabilisticActor, ValueOperator
from torchrl.objectives import A2CLoss, SoftUpdate, ValueEstimators

from dcsc_torchrl.losses import QCriticLoss
from dcsc_torchrl.networks import LUNAR_QVALUE_DIMS, lunar_actor, lunar_critic
from dcsc_torchrl.tasks import make_lunar_env
from dcsc_torchrl.training import (
    TrainingRun,
    evaluate,
    make_collector,
    parse_recipe_args,
    recipe_config,
)

CONFIG = Path(__file__).with_suffix(".yaml")
COLUMNS = ["episode", "frames", "return", "length", "success",
           "loss_objective", "loss_critic", "loss_entropy", "loss_qvalue"]


def main(argv: Sequence[str] | None = None) -> Path:
    args = parse_recipe_args(argv, __doc__)
    cfg = recipe_config(CONFIG, args)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)

    # --- networks: actor (with dropout), V critic for A2C, Q critic for DC-SC ----------
    actor_net = lunar_actor(cfg.network.hidden, cfg.network.actor_dropout)
    value_net = lunar_critic(cfg.network.hidden, 1)
    qvalue_net = lunar_critic(cfg.network.hidden, 4, obs_dims=LUNAR_QVALUE_DIMS)
    action_spec = make_lunar_env(1).full_action_spec["action"]
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["logits"]),
        in_keys=["logits"],
        spec=action_spec,
        distribution_class=OneHotCategorical,
        return_log_prob=True,
    )
    critic = ValueOperator(value_net, in_keys=["observation"])
    qvalue = TensorDictModule(qvalue_net, in_keys=["observation"], out_keys=["action_value"])

    # --- losses and optimisers ----------------------------------------------------------
    a2c_loss = A2CLoss(actor, critic, entropy_coeff=cfg.loss.entropy_coeff, critic_coeff=cfg.loss.critic_coeff)
    a2c_loss.make_value_estimator(ValueEstimators.GAE, gamma=cfg.loss.gamma, lmbda=cfg.loss.gae_lambda)
    q_loss = QCriticLoss(qvalue, gamma=cfg.loss.gamma)
    q_target = SoftUpdate(q_loss, tau=cfg.qcritic.tau)
    optim = torch.optim.Adam(a2c_loss.parameters(), lr=cfg.optim.lr)
    q_optim = torch.optim.Adam(q_loss.parameters(), lr=cfg.qcritic.lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.qcritic.buffer_size), batch_size=cfg.qcritic.batch_size)

    def update(batch) -> dict[str, float]:
        loss = a2c_loss(batch)
        total = loss["loss_objective"] + loss["loss_critic"] + loss["loss_entropy"]
        optim.zero_grad()
        total.backward()
        torch.nn.utils.clip_grad_norm_(a2c_loss.parameters(), cfg.optim.max_grad_norm)
        optim.step()

        buffer.extend(batch.reshape(-1).select("observation", "action", "next").clone())
        for _ in range(cfg.qcritic.updates_per_batch):
            q = q_loss(buffer.sample())["loss_qvalue"]
            q_optim.zero_grad()
            q.backward()
            q_optim.step()
            q_target.step()
        return {key: loss[key].item() for key in ("loss_objective", "loss_critic", "loss_entropy")} | {
            "loss_qvalue": q.item()
        }

    # --- training, in checkpointed segments ---------------------------------------------
    run = TrainingRun(
        "lunarlander", cfg, COLUMNS,
        stateful={"actor": actor_net, "value": value_net, "qvalue": qvalue_net, "q_loss": q_loss,
                  "optim": optim, "q_optim": q_optim, "buffer": buffer},
    )
    run.start(resume=args.resume)
    frames_per_batch = cfg.env.num_envs * cfg.collector.rollout_length
    run.train(
        lambda seed: make_collector(partial(make_lunar_env, random_pad=cfg.env.random_pad), cfg.env.num_envs,
                                    actor, workers=cfg.collector.workers, seed=seed,
                                    frames_per_batch=frames_per_batch),
        update,
    )
    curve = run.finish("A2C on TargetLunarLander (pad at the centre)")

    # --- machine-only evaluation: the standard pad and the moved pad (0 episodes: skip) --
    rows = []
    for pad, random_pad in (("standard", False), ("moved", True)) if cfg.eval.episodes > 0 else ():
        env = make_lunar_env(cfg.eval.episodes, random_pad=random_pad)
        env.set_seed(cfg.seed + 10_000)
        for row in evaluate(env, actor, 1000, ["success", "crashed", "landed_outside"]):
            rows.append({"pad": pad, **row})
        env.close()
    if rows:
        pd.DataFrame(rows).to_csv(run.out_dir / "eval.csv", index=False)
    return curve


if __name__ == "__main__":
    main()
