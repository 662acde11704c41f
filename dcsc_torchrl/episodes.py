"""Episodes of a batch of scenarios: one recorded episode per env, and its trace.

With autoresetting batched envs a rollout runs on past an env's first episode; the
protocol counts exactly one episode per env (one env = one scenario), its first.
:func:`in_first_episode` is the one home of that rule: the protocol's
:func:`run_scenarios`, the pretraining recipes' greedy evaluation
(:func:`dcsc_torchrl.training.first_episodes`) and the operator-alone benchmark all use it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from dcsc_torchrl.checks import flush_frame_checks
from dcsc_torchrl.task import Task

FRAME_KEYS = ("observation", "action", "machine_probs", "machine_action", "machine_uncertainty",
              "machine_confidence", "human_confidence", "human_action", "confidence_ratio", "beta")
"""The keys of a recorded frame (what the protocol reads after a run)."""
TRACE_KEYS = ("knowledge", "human_confidence", "machine_uncertainty", "machine_confidence", "confidence_ratio")
"""The scalar keys of a trace row (beta and the actions are per action dimension)."""


def in_first_episode(done: torch.Tensor, running: torch.Tensor | None = None) -> torch.Tensor:
    """Which frames of a ``[envs, time]`` batch belong to each env's first episode, its done frame included.

    ``done`` is ``[envs, time]`` (bool); ``running`` (``[envs]``, default all) marks the envs
    whose first episode has not ended in an earlier batch.

    Examples:
        >>> done = torch.tensor([[False, True, False], [False, False, False]])
        >>> in_first_episode(done)
        tensor([[ True,  True, False],
                [ True,  True,  True]])
    """
    before = (done.long().cumsum(-1) - done.long()) == 0
    return before if running is None else before & running.unsqueeze(-1)


@dataclass
class EpisodeBatch:
    """What :func:`run_scenarios` returns: one row per scenario, the trace of the first,
    and every recorded frame (the first episode of each env; only :data:`FRAME_KEYS`)."""

    rows: list[dict[str, Any]]
    trace: list[dict[str, Any]] = field(default_factory=list)
    frames: TensorDictBase | None = None

    @property
    def uncertainty(self) -> torch.Tensor:
        """The machine's uncertainty ``c_t`` over the recorded frames."""
        return self.frames["machine_uncertainty"].reshape(-1)


def trace_rows(frames: TensorDictBase, task: Task) -> list[dict[str, Any]]:
    """One row per frame of ``[time]`` frames: confidences, authority, the three actions (Figs. 3, 5, 6).

    A discrete task's actions are key indices (the machine's most likely key); a
    continuous task's are one column per :attr:`Task.action_names` component, as are
    beta and the :attr:`Task.trace_vectors`.
    """
    rows = []
    for step in range(frames.shape[0]):
        frame = frames[step]
        row = {"step": step + 1, "reward": frame["next", "reward"].item(), "human_rt": frame["human_rt"].item()}
        row.update({key: frame[key].item() for key in TRACE_KEYS})
        if task.discrete:
            row["beta"] = frame["beta"].item()
            row["machine_action"] = int(frame["machine_probs"].argmax())
            row["operator_action"] = int(frame["human_action"].argmax())
            row["shared_action"] = int(frame["action"].argmax())
        else:
            names = task.action_names
            row.update({f"beta_{d}": v for d, v in zip(names, frame["beta"].tolist(), strict=True)})
            for who, key in (("machine", "machine_action"), ("operator", "human_action"), ("shared", "action")):
                row.update({f"{who}_{d}": v for d, v in zip(names, frame[key].tolist(), strict=True)})
        for key, components in task.trace_vectors.items():
            row.update({f"{key}_{c}": v for c, v in zip(components, frame["next", key].tolist(), strict=True)})
        rows.append(row)
    return rows


def run_scenarios(
    env: EnvBase,
    policy: TensorDictModuleBase,
    task: Task,
    *,
    rollout_length: int,
    update: Callable[[TensorDictBase], None] | None = None,
    trace: bool = False,
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> EpisodeBatch:
    """Plays the first episode of every env (scenario) of ``env`` under ``policy``.

    Envs that finish early keep running (their frames still go to ``update``) until every
    scenario of the batch is done.

    Args:
        env: a batch of scenarios (:attr:`Task.make_envs` with the operator's transforms).
        policy: the shared policy (any arbiter).
        task: which episode values and trace columns exist.
        rollout_length: frames per env between two calls of ``update``.
        update: called on every collected batch ``[envs, rollout_length]`` (DC-SC's
            online learning); ``None`` for the fixed methods.
        trace: record every frame of scenario 0's episode.
        exploration_type: how the policy's probabilistic modules act (the collector's):
            ``RANDOM`` samples the discrete shared action, ``MODE`` takes its mode.

    Returns:
        The rows (``return``, ``steps``, :attr:`Task.episode_keys`, ``mean_beta``), the trace
        and the frames, tagged with ``env_index`` and ``frame_index``.
    """
    n_envs = env.batch_size[0]
    collector = Collector(env, policy, frames_per_batch=n_envs * rollout_length, total_frames=-1,
                          auto_register_policy_transforms=False, exploration_type=exploration_type)
    running = torch.ones(n_envs, dtype=torch.bool)
    rows: list[dict[str, Any] | None] = [None] * n_envs
    beta_sum, frame_count = torch.zeros(n_envs), torch.zeros(n_envs)
    traced: list[TensorDictBase] = []
    frames: list[TensorDictBase] = []
    keys = [*FRAME_KEYS, *(("next", key) for key in (*FRAME_KEYS, "reward", "done", "terminated"))]
    for batch in collector:
        done = batch["next", "done"].squeeze(-1)
        first = in_first_episode(done, running)
        selected = batch.select(*keys, strict=False)
        selected["env_index"] = torch.arange(n_envs).unsqueeze(-1).expand(done.shape)
        selected["frame_index"] = (len(frames) * rollout_length + torch.arange(done.shape[-1])).expand(done.shape)
        frames.append(selected[first])
        beta_sum += (batch["beta"].detach().mean(-1) * first).sum(-1)
        frame_count += first.sum(-1)
        if trace and first[0].any():
            traced.append(batch[0][first[0]])
        for i in (running & done.any(-1)).nonzero().reshape(-1).tolist():
            nxt = batch[i, int(done[i].nonzero()[0])]["next"]
            rows[i] = {"return": nxt["episode_reward"].item(), "steps": int(nxt["step_count"].item()),
                       **{key: nxt[key].item() for key in task.episode_keys},
                       "mean_beta": (beta_sum[i] / frame_count[i]).item()}
        running &= ~done.any(-1)
        if update is not None:
            update(batch)
        if not running.any():
            break
    collector.shutdown()
    flush_frame_checks()  # on a device, the frames' deferred checks (a no-op on the host)
    return EpisodeBatch(rows, trace_rows(torch.cat(traced), task) if traced else [], torch.cat(frames))


def concat_runs(*frames: TensorDictBase) -> TensorDictBase:
    """The frames of several runs (:attr:`EpisodeBatch.frames`) as one, each episode its own ``env_index``.

    Every run numbers its envs from 0, so run ``k``'s envs are shifted past those of the
    runs before it: :func:`dcsc_torchrl.online.returns_to_go` then never chains two runs'
    episodes into one.
    """
    parts, offset = [], 0
    for run in frames:
        run = run.clone(False)
        run["env_index"] = run["env_index"] + offset
        offset = int(run["env_index"].max()) + 1 if run.numel() else offset
        parts.append(run)
    return torch.cat(parts)
