"""Pretrain the LunarLander machine: A2C + a Q critic (paper §6.1, Table A1).

A2C with GAE over batched TargetLunarLander envs (pad at the centre: the standard task; with
``env.random_pad`` a pad drawn per episode); ``loss.algorithm=ppo`` trains the same networks
with TorchRL's clipped PPO instead (several epochs of minibatches per batch), the way to a
converged machine (docs/pretraining.md). The actor is an MLP with dropout (MC dropout samples
it later, Eq. 10) that sees what ``network.observes`` says: the 8 standard values
(``blind``) or all 9, the pad included (``target``, the paper's state); A2C's V critic sees
the same. Beside them a Q critic learns Q(s, a) from a replay buffer
by the TD loss of Algorithm 1 — DC-SC's theta update needs Q; it reads all 9 values, the
pad included. Training stops after ``train.episodes`` episodes (or, with
``train.stop_success``, once the greedy machine lands that often); every ``train.checkpoint_every`` episodes an atomic
checkpoint is written, and ``--resume`` continues from the last one. With ``train.keep_best``
the run's result is the checkpoint of its best landing check (``best.pt``), not its last.

    dcsc pretrain lunarlander [--quick] [--resume] [--out DIR] [key=value ...]    # or: python recipes/pretrain_a2c_lunarlander.py ...

Outputs in the run folder (``--out``; by default ``<pretrain.out_dir>/seed<seed>/`` of the task's protocol
yaml, where ``dcsc run`` reads the machine): ``train.csv`` (one row per episode), ``checkpoint.pt``,
``learning_curve.png``, ``eval.csv`` (machine-only greedy episodes, standard and moved pad)
and, with ``train.stop_success > 0`` or ``train.keep_best``, ``stop_checks.csv`` (the landing
check after each segment) and, with ``train.keep_best``, ``best.pt``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorSpec
from torchrl.modules import OneHotCategorical, ProbabilisticActor, ValueOperator
from torchrl.objectives import A2CLoss, ClipPPOLoss, ValueEstimators

from dcsc_torchrl.batched_envs import make_lunar_env
from dcsc_torchrl.config import ConfigError, to_plain
from dcsc_torchrl.losses import ForeachSoftUpdate, QCriticLoss
from dcsc_torchrl.networks import (
    LUNAR_QVALUE_DIMS,
    lunar_actor,
    lunar_critic,
    lunar_machine_dims,
    orthogonal_init_,
)
from dcsc_torchrl.recipes import pretrain
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.training import (
    TrainingRun,
    greedy_episodes,
    make_collector,
)

CONFIG = CONFIGS["lunarlander"].pretrain
COLUMNS = ["episode", "frames", "return", "steps", "success",
           "loss_objective", "loss_critic", "loss_entropy", "loss_qvalue"]
LR_SCHEDULES = ("constant", "linear")  # optim.lr_schedule: Table A1's constant lr, or linear to 0 over the budget
OPTIMIZERS = ("adam", "rmsprop")  # optim.name: Adam, or RMSprop as Stable-Baselines3's A2C (alpha 0.99, eps optim.eps)
NETWORK_INITS = ("default", "orthogonal")  # network.init: PyTorch's, or orthogonal (small policy head)
ALGORITHMS = ("a2c", "ppo")  # loss.algorithm: Table A1's A2C, or clipped PPO on the same networks


def make_actor_critic(cfg: DictConfig, actor_net: torch.nn.Module, value_net: torch.nn.Module,
             action_spec: TensorSpec) -> tuple[ProbabilisticActor, A2CLoss | ClipPPOLoss, torch.optim.Optimizer]:
    """The actor-critic part of the recipe: the sampling actor, its loss with GAE, and its optimiser.

    ``cfg.loss`` and ``cfg.optim`` are read (Table A1's values plus what it leaves open);
    ``loss.algorithm`` picks ``A2CLoss`` or ``ClipPPOLoss`` (clip ``ppo.clip_epsilon``),
    with the same entropy and value terms.
    """
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["logits"]),
        in_keys=["logits"],
        spec=action_spec,
        distribution_class=OneHotCategorical,
        return_log_prob=True,
    )
    critic = ValueOperator(value_net, in_keys=["observation"])
    terms = {"entropy_coeff": cfg.loss.entropy_coeff, "critic_coeff": cfg.loss.critic_coeff,
             "loss_critic_type": cfg.loss.critic_loss}
    if cfg.loss.algorithm == "ppo":
        loss = ClipPPOLoss(actor, critic, clip_epsilon=cfg.ppo.clip_epsilon, **terms)
    else:
        loss = A2CLoss(actor, critic, **terms)
    loss.make_value_estimator(ValueEstimators.GAE, gamma=cfg.loss.gamma, lmbda=cfg.loss.gae_lambda)
    if cfg.optim.name == "rmsprop":
        optim = torch.optim.RMSprop(loss.parameters(), lr=cfg.optim.lr, alpha=0.99, eps=cfg.optim.eps, foreach=True)
    else:
        optim = torch.optim.Adam(loss.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps, foreach=True)
    return actor, loss, optim


def actor_critic_step(cfg: DictConfig, loss: A2CLoss | ClipPPOLoss, optim: torch.optim.Optimizer,
             batch: TensorDictBase) -> dict[str, float]:
    """The actor-critic update on a ``[envs, time]`` batch; returns the three loss terms
    (A2C: of its one step; PPO: averaged over its steps).

    The rewards are scaled by ``loss.reward_scale`` in ``batch`` (in place) and GAE
    advantages computed once. A2C takes one gradient step on the whole batch; PPO
    (``loss.algorithm=ppo``) ``ppo.epochs`` passes over the batch in shuffled minibatches
    of ``ppo.minibatch_size`` frames. With ``loss.normalize_advantage`` the advantages are
    standardised over what one step sees; each step's gradient of the summed loss is
    clipped to ``optim.max_grad_norm``.
    """
    if cfg.loss.reward_scale != 1.0:
        batch.set(("next", "reward"), batch.get(("next", "reward")) * cfg.loss.reward_scale)
    with torch.no_grad():
        loss.value_estimator(batch)  # GAE: "advantage" and "value_target"
    if cfg.loss.algorithm == "ppo":
        frames = batch.reshape(-1)
        steps = [frames[index] for _ in range(cfg.ppo.epochs)
                 for index in torch.randperm(frames.numel()).split(cfg.ppo.minibatch_size)]
    else:
        steps = [batch]
    sums = dict.fromkeys(("loss_objective", "loss_critic", "loss_entropy"), 0.0)
    for step in steps:
        if cfg.loss.normalize_advantage:
            adv = step.get("advantage")
            step.set("advantage", (adv - adv.mean()) / (adv.std() + 1e-8))
        terms = loss(step)
        if "loss_entropy" not in terms.keys():  # entropy_coeff 0: TorchRL leaves the term out
            terms.set("loss_entropy", torch.zeros(()))
        total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
        optim.zero_grad()
        total.backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.optim.max_grad_norm)
        optim.step()
        for key in sums:
            sums[key] += terms[key].item() / len(steps)
    return sums


def train(cfg: DictConfig, *, resume: bool = False) -> Path:
    """Pretrains the machine of ``cfg`` into ``cfg.logger.out_dir`` (from its last checkpoint with
    ``resume``); returns the learning curve's PNG."""
    if cfg.optim.lr_schedule not in LR_SCHEDULES:
        raise ConfigError(f"optim.lr_schedule: expected one of {', '.join(LR_SCHEDULES)}, got {cfg.optim.lr_schedule!r}")
    if cfg.optim.name not in OPTIMIZERS:
        raise ConfigError(f"optim.name: expected one of {', '.join(OPTIMIZERS)}, got {cfg.optim.name!r}")
    try:
        lunar_machine_dims(cfg.network.observes)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if cfg.network.init not in NETWORK_INITS:
        raise ConfigError(f"network.init: expected one of {', '.join(NETWORK_INITS)}, got {cfg.network.init!r}")
    if cfg.loss.algorithm not in ALGORITHMS:
        raise ConfigError(f"loss.algorithm: expected one of {', '.join(ALGORITHMS)}, got {cfg.loss.algorithm!r}")
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)

    # --- networks: actor (with dropout), V critic for A2C, Q critic for DC-SC ----------
    obs_dims = lunar_machine_dims(cfg.network.observes)  # the actor and V see the same values
    actor_net = lunar_actor(cfg.network.hidden, cfg.network.actor_dropout, obs_dims=obs_dims)
    value_net = lunar_critic(cfg.network.hidden, 1, obs_dims=obs_dims)
    if cfg.network.init == "orthogonal":
        orthogonal_init_(actor_net, out_gain=0.01)
        orthogonal_init_(value_net, out_gain=1.0)
    qvalue_net = lunar_critic(cfg.network.hidden, 4, obs_dims=LUNAR_QVALUE_DIMS)
    actor, actor_critic_loss, optim = make_actor_critic(cfg, actor_net, value_net, make_lunar_env(1).full_action_spec["action"])
    qvalue = TensorDictModule(qvalue_net, in_keys=["observation"], out_keys=["action_value"])

    # --- the Q critic's loss, optimiser and replay buffer -------------------------------
    q_loss = QCriticLoss(qvalue, gamma=cfg.loss.gamma)
    q_target = ForeachSoftUpdate(q_loss, tau=cfg.qcritic.tau)
    q_optim = torch.optim.Adam(q_loss.parameters(), lr=cfg.qcritic.lr, foreach=True)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.qcritic.buffer_size), batch_size=cfg.qcritic.batch_size)

    def update(batch) -> dict[str, float]:
        if cfg.optim.lr_schedule == "linear":  # to 0 over the budget (resumes from the run's count)
            for group in optim.param_groups:
                group["lr"] = cfg.optim.lr * (1.0 - run.progress)
        buffer.extend(batch.reshape(-1).select(*q_loss.in_keys, strict=False).clone())  # what the Q loss reads; env-scale rewards
        metrics = actor_critic_step(cfg, actor_critic_loss, optim, batch)
        for _ in range(cfg.qcritic.updates_per_batch):  # >= 1 (dcsc_torchrl.config.LIMITS)
            q = q_loss(buffer.sample())["loss_qvalue"]
            q_optim.zero_grad()
            q.backward()
            q_optim.step()
            q_target.step()
        return metrics | {"loss_qvalue": q.item()}

    # --- training, in checkpointed segments ---------------------------------------------
    run = TrainingRun(
        "lunarlander", out_dir=cfg.logger.out_dir, episodes=cfg.train.episodes, frames=cfg.train.frames,
        checkpoint_every=cfg.train.checkpoint_every,
        seed=cfg.seed, config=to_plain(cfg), columns=COLUMNS,
        stateful={"actor": actor_net, "value": value_net, "qvalue": qvalue_net, "q_loss": q_loss,
                  "optim": optim, "q_optim": q_optim, "buffer": buffer},
    )
    def greedy(episodes: int, random_pad: bool, seed: int) -> list[dict]:
        """``episodes`` greedy machine-only episodes (one per env), seeded."""
        env = make_lunar_env(episodes, random_pad=random_pad)
        env.set_seed(seed)
        rows = greedy_episodes(env, actor, 1000, ["success", "crashed", "landed_outside"])
        env.close()
        return rows

    stop_log = run.out_dir / "stop_checks.csv"

    def landed_enough(segment: int) -> bool:
        """``train.stop_success``: the greedy machine's success on the pads it trains on (the
        standard pad, or random pads with ``env.random_pad``), checked after each segment on
        ``train.stop_eval_episodes`` episodes (seeds apart from eval's).
        With ``train.keep_best`` a check above every earlier one keeps its checkpoint."""
        rows = greedy(cfg.train.stop_eval_episodes, cfg.env.random_pad, cfg.seed + 20_000 + segment)
        success = sum(row["success"] for row in rows) / len(rows)
        if cfg.train.keep_best and (not stop_log.exists() or success > pd.read_csv(stop_log)["success"].max()):
            run.keep_best()
        pd.DataFrame([{"episode": run.episodes, "frames": run.frames, "success": success}]).to_csv(
            stop_log, mode="a", header=not stop_log.exists(), index=False)
        return cfg.train.stop_success > 0 and success >= cfg.train.stop_success

    run.start(resume=resume)
    if not resume:
        stop_log.unlink(missing_ok=True)
    frames_per_batch = cfg.env.num_envs * cfg.collector.rollout_length
    run.train(
        lambda seed: make_collector(partial(make_lunar_env, random_pad=cfg.env.random_pad), cfg.env.num_envs,
                                    actor, workers=cfg.collector.workers, seed=seed,
                                    frames_per_batch=frames_per_batch),
        update,
        stop=landed_enough if cfg.train.stop_success > 0 or cfg.train.keep_best else None,
    )
    if cfg.train.keep_best:  # the result (checkpoint.pt, eval.csv) is the best check's machine
        run.restore_best()
    pads = "a random pad" if cfg.env.random_pad else "pad at the centre"
    curve = run.finish(f"{cfg.loss.algorithm.upper()} on TargetLunarLander ({pads}; sees {cfg.network.observes})")

    # --- machine-only evaluation: the standard pad and the moved pad (0 episodes: skip) --
    rows = []
    for pad, random_pad in (("standard", False), ("moved", True)) if cfg.eval.episodes > 0 else ():
        rows += [{"pad": pad, **row} for row in greedy(cfg.eval.episodes, random_pad, cfg.seed + 10_000)]
    if rows:
        pd.DataFrame(rows).to_csv(run.out_dir / "eval.csv", index=False)
    return curve


def main(argv: Sequence[str] | None = None) -> Path:
    """``dcsc pretrain lunarlander``'s command line and defaults (:func:`dcsc_torchrl.recipes.pretrain.main`)."""
    return pretrain.main("lunarlander", train, __doc__, argv)


if __name__ == "__main__":
    main()
