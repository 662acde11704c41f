"""What every pretraining recipe shares: the run directory, episode logging, checkpoints, resume.

A recipe (``recipes/*.py``) owns its algorithm; a :class:`TrainingRun` owns the
bookkeeping around it. Training is cut into *segments* of ``checkpoint_every`` episodes:
each segment starts from freshly reset, freshly seeded environments and ends with an
atomic checkpoint. Because nothing in flight crosses a segment boundary, a run resumed
from a checkpoint replays exactly the rows an uninterrupted run writes (same seed).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector, Collector, MultiSyncCollector
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from dcsc_torchrl.checkpoint import (
    load_checkpoint,
    load_module_state,
    load_replay_buffer_state,
    remove_stale_temp_files,
    replay_buffer_state,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from dcsc_torchrl.config import ConfigError, config_diff
from dcsc_torchrl.episodes import in_first_episode
from dcsc_torchrl.runlog import Progress, RunLog, plot_learning_curve


def make_collector(
    make_env: Callable[[int], EnvBase],
    num_envs: int,
    policy: TensorDictModuleBase,
    *,
    workers: int,
    seed: int,
    frames_per_batch: int,
    **kwargs: Any,
) -> BaseCollector:
    """The collector of one training segment: ``num_envs`` envs seeded with ``seed``, in one
    process or split over ``workers`` processes.

    ``workers == 1``: TorchRL's ``Collector`` over ``make_env(num_envs)``. ``workers > 1``:
    TorchRL's ``MultiSyncCollector``, each worker process stepping ``make_env(num_envs //
    workers)`` and the batches concatenated along the env dim, so a batch has the same
    ``[num_envs, time]`` shape either way; the policy's weights are synced to the workers
    before every batch. ``make_env`` is pickled to the (spawned) workers: pass a top-level
    function or a ``functools.partial`` of one.

    Args:
        make_env: builds a batch of ``n`` envs from ``n``.
        num_envs: envs in all, a multiple of ``workers``.
        policy: the collecting policy.
        workers: collector processes (``collector.workers`` of the recipes' configs).
        seed: the envs' seed (workers after the first continue from the seed the previous
            one returns, as TorchRL's multi-process collectors do).
        frames_per_batch: frames of one batch, all workers together.
        **kwargs: passed on to the collector (e.g. ``init_random_frames``).
    """
    if workers < 1 or num_envs % workers:
        raise ValueError(f"collector.workers must be >= 1 and divide env.num_envs={num_envs}, got {workers}")
    if workers == 1:
        env = make_env(num_envs)
        env.set_seed(seed)
        return Collector(env, policy, frames_per_batch=frames_per_batch, total_frames=-1,
                         auto_register_policy_transforms=False, **kwargs)
    collector = MultiSyncCollector(
        [partial(make_env, num_envs // workers)] * workers, policy, frames_per_batch=frames_per_batch,
        total_frames=-1, cat_results=0, update_at_each_batch=True, num_threads=torch.get_num_threads(),
        auto_register_policy_transforms=False, **kwargs,
    )
    collector.set_seed(seed)
    return collector


def finished_episodes(batch: TensorDictBase, extra_keys: Sequence[str] = ()) -> list[dict[str, Any]]:
    """One dict per episode that ended in ``batch`` (``[*envs, time]``).

    Reads ``("next", "episode_reward")`` (TorchRL's ``RewardSum``) and
    ``("next", "step_count")`` (``StepCounter``) on done frames, plus any ``extra_keys``
    under ``"next"`` (e.g. ``success``).
    """
    nxt = batch.get("next")
    done = nxt.get("done").squeeze(-1)
    if not done.any():
        return []
    rows = []
    returns = nxt.get("episode_reward")[done].reshape(-1).tolist()
    steps = nxt.get("step_count")[done].reshape(-1).tolist()
    extras = {key: nxt.get(key)[done].reshape(-1).tolist() for key in extra_keys}
    for i, (ret, length) in enumerate(zip(returns, steps, strict=True)):
        rows.append({"return": float(ret), "steps": int(length), **{k: v[i] for k, v in extras.items()}})
    return rows


def first_episodes(rollout: TensorDictBase, extra_keys: Sequence[str] = ()) -> list[dict[str, Any]]:
    """The first episode of every env of a ``[envs, time]`` rollout (envs that never finished are skipped).

    With autoresetting batched envs a rollout runs on past an env's first episode; the
    evaluation protocol counts exactly one episode per env (one env = one scenario).
    """
    done = rollout.get(("next", "done")).squeeze(-1)
    ends = done & in_first_episode(done)
    rows = []
    for env_index, t in ends.nonzero().tolist():
        nxt = rollout[env_index, t].get("next")
        rows.append({
            "env": env_index,
            "return": float(nxt.get("episode_reward")),
            "steps": int(nxt.get("step_count")),
            **{key: nxt.get(key).item() for key in extra_keys},
        })
    return rows


def greedy_episodes(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int, extra_keys: Sequence[str] = ()
) -> list[dict[str, Any]]:
    """One greedy episode per env: eval mode (no dropout), deterministic actions.

    As TorchRL's sota-implementations evaluate: under
    ``set_exploration_type(ExplorationType.DETERMINISTIC)``, without gradients. The
    rollout stops once every env's first episode is over, and an env whose episode is
    over is not stepped again (TorchRL's partial steps, which both batched envs honour).
    """
    was_training = policy.training
    policy.eval()
    try:
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            rollout = env.rollout(max_steps, policy, break_when_any_done=False, break_when_all_done=True)
    finally:
        policy.train(was_training)
    return first_episodes(rollout, extra_keys)


RESUMABLE_CHANGES = ("logger.out_dir", "threads", "train.episodes", "train.frames", "train.stop_success",
                     "train.stop_eval_episodes", "train.keep_best")
"""Config keys a resumed run may change: where it writes, its threads, its budget (and what it keeps)."""


class TrainingRun:
    """Run directory, CSV log, progress bar, checkpoints and resume of one training run.

    Args:
        task: the task's name (written into every checkpoint, checked on resume).
        out_dir: the run's folder (``train.csv``, ``checkpoint.pt``, ``learning_curve.png``).
        episodes: the episode budget.
        checkpoint_every: episodes per segment (a checkpoint closes each).
        frames: a frame budget besides (0: none): training also ends, mid-segment, once
            this many frames are collected (the budget of a peer that counts frames).
        seed: the run's seed (each segment's env seed derives from it).
        config: the run's whole config as plain data: stored in every checkpoint, and a
            resume with another one is refused (but :data:`RESUMABLE_CHANGES`).
        columns: the CSV's columns; must start with ``episode`` and ``frames``.
        stateful: objects with ``state_dict`` / ``load_state_dict`` saved in each
            checkpoint (networks, optimisers, replay buffers), by name.
    """

    def __init__(
        self,
        task: str,
        *,
        out_dir: str | os.PathLike,
        episodes: int,
        checkpoint_every: int,
        seed: int,
        config: Mapping[str, Any],
        columns: list[str],
        stateful: Mapping[str, Any],
        frames: int = 0,
    ) -> None:
        if columns[:2] != ["episode", "frames"]:
            raise ValueError(f"columns must start with ['episode', 'frames'], got {columns[:2]}")
        self.task = task
        self.config = dict(config)
        self.seed = int(seed)
        self.out_dir = Path(out_dir)
        self.total_episodes = int(episodes)
        self.checkpoint_every = int(checkpoint_every)
        self.total_frames = int(frames)
        if self.total_frames < 0:
            raise ValueError(f"train.frames must be >= 0 (0: no frame budget), got {frames}")
        if self.total_episodes < 1 or self.checkpoint_every < 1:
            raise ValueError(
                f"train.episodes and train.checkpoint_every must be >= 1, got "
                f"{self.total_episodes} and {self.checkpoint_every}"
            )
        self.stateful = dict(stateful)
        self.log = RunLog(self.out_dir / "train.csv", columns)
        self.checkpoint_path = self.out_dir / "checkpoint.pt"
        self.best_path = self.out_dir / "best.pt"
        self.episodes = 0
        self.frames = 0
        self.segment = 0
        self.finished = False  # set by finish(): the checkpoint is the run's result, even short of the budget
        self._progress: Progress | None = None

    # -- resume ---------------------------------------------------------------------
    def start(self, *, resume: bool) -> None:
        """Starts fresh (removing an old log) or resumes from the last checkpoint.

        The temporary files of a checkpoint write that was killed are removed first; a
        fresh start also removes an old ``best.pt`` (:meth:`keep_best`).

        Raises:
            ConfigError: resuming a checkpoint written with another config (the keys
                that differ are named; ``logger.out_dir``, ``threads`` and the budget,
                ``train.episodes`` / ``train.stop_*``, may differ: resuming with a larger
                budget trains the same machine further).
        """
        remove_stale_temp_files(self.checkpoint_path)
        if resume:
            data = load_checkpoint(self.checkpoint_path, task=self.task)
            changed = config_diff(data.get("config", {}), self.config, ignore=RESUMABLE_CHANGES)
            if changed:
                raise ConfigError(
                    f"cannot resume {self.checkpoint_path}: it was written with another config "
                    f"({'; '.join(changed)}); resume with the same settings, or start over without --resume"
                )
            self._restore(data)
            self.log.truncate("episode", self.episodes)
        else:
            self.log.path.unlink(missing_ok=True)
            self.best_path.unlink(missing_ok=True)
        if self.total_frames:  # a frame budget: the bar counts frames
            self._progress = Progress(self.total_frames, f"{self.task} frames", "frame", initial=self.frames)
        else:
            self._progress = Progress(self.total_episodes, f"{self.task} episodes", "ep", initial=self.episodes)

    def _restore(self, data: dict[str, Any]) -> None:
        for name, obj in self.stateful.items():
            if name not in data["state"]:
                raise ValueError(f"checkpoint {self.checkpoint_path} has no state for {name!r}")
            if isinstance(obj, torch.nn.Module):
                load_module_state(obj, data["state"][name], name=name)
            elif isinstance(obj, ReplayBuffer):
                load_replay_buffer_state(obj, data["state"][name])
            else:
                obj.load_state_dict(data["state"][name])
        self.episodes, self.frames, self.segment = data["episodes"], data["frames"], data["segment"]
        self.finished = False  # a resumed run trains on; finish() marks its result again
        set_rng_state(data["rng"])

    # -- the loop -------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self.episodes >= self.total_episodes or 0 < self.total_frames <= self.frames

    @property
    def progress(self) -> float:
        """The share of the budget spent, in [0, 1]: of the episodes, or of the frames when that is further."""
        spent = self.episodes / self.total_episodes
        return min(1.0, max(spent, self.frames / self.total_frames) if self.total_frames else spent)

    def segment_seed(self) -> int:
        """The env seed of the current segment (fresh, distinct per segment)."""
        return self.seed * 100_003 + self.segment

    @property
    def segment_done(self) -> bool:
        return self.done or self.episodes >= (self.segment + 1) * self.checkpoint_every

    def record(self, frames: int, episodes: list[dict[str, Any]], metrics: Mapping[str, float]) -> None:
        """Counts ``frames``, logs one CSV row per finished episode, up to the segment's quota."""
        self.frames += frames
        if self.total_frames:
            self._progress.update(frames)
        for row in episodes:
            if self.segment_done:  # episodes past the segment's quota are not replayed on resume
                break
            self.episodes += 1
            self.log.append({"episode": self.episodes, "frames": self.frames, **row, **metrics})
            if not self.total_frames:
                self._progress.update(1)
        if episodes:
            self._progress.set_postfix(ret=f"{episodes[-1]['return']:.1f}", frames=self.frames)

    def train(
        self,
        segment_collector: Callable[[int], BaseCollector],
        update: Callable[[TensorDictBase], Mapping[str, float]],
        stop: Callable[[int], bool] | None = None,
    ) -> None:
        """The training loop: segment after segment until the episode budget is spent.

        Each segment gets a fresh collector from ``segment_collector(seed)``; every batch
        goes through ``update`` (the algorithm's step, returning its loss metrics) and
        its finished episodes are logged; the segment closes with a checkpoint.

        Args:
            segment_collector: the collector of a segment, from its env seed.
            update: one algorithm step on a batch; returns the loss metrics to log.
            stop: optional check, asked after each segment (the last one included) with
                the number of segments done, once its checkpoint is written (e.g. "does
                the greedy machine land often enough?"); ``True`` ends training before
                the episode budget is spent.
        """
        threads = torch.get_num_threads()
        while not self.done:
            collector = segment_collector(self.segment_seed())
            for batch in collector:
                self.record(batch.numel(), finished_episodes(batch, ["success"]), update(batch))
                if self.segment_done:
                    break
            collector.shutdown()
            torch.set_num_threads(threads)  # a multi-process collector's shutdown changes it
            self.end_segment()
            if stop is not None and stop(self.segment):
                break

    def end_segment(self) -> None:
        """Closes the segment with an atomic checkpoint."""
        self.segment += 1
        self.save()

    def keep_best(self) -> None:
        """Copies the checkpoint just written to ``best.pt`` (atomically), for :meth:`restore_best`.

        The caller decides what is best: e.g. a ``stop`` check of :meth:`train` calls this
        when the checkpointed machine beats every earlier check.
        """
        save_checkpoint(self.best_path, task=self.task, payload=load_checkpoint(self.checkpoint_path, task=self.task))

    def restore_best(self) -> None:
        """Makes ``best.pt`` the run's result: written over ``checkpoint.pt`` and loaded into the
        stateful objects and counters (``train.csv`` keeps every episode trained), so what is
        evaluated next is the kept machine, and ``--resume`` trains on from it.
        """
        data = load_checkpoint(self.best_path, task=self.task)
        save_checkpoint(self.checkpoint_path, task=self.task, payload=data)
        self._restore(data)

    def save(self) -> None:
        state = {
            name: replay_buffer_state(obj) if isinstance(obj, ReplayBuffer) else obj.state_dict()
            for name, obj in self.stateful.items()
        }
        save_checkpoint(
            self.checkpoint_path,
            task=self.task,
            payload={
                "state": state,
                "episodes": self.episodes,
                "frames": self.frames,
                "segment": self.segment,
                "rng": rng_state(),
                "config": self.config,
                "finished": self.finished,
            },
        )

    def finish(self, title: str) -> Path:
        """Marks the checkpoint as the run's result, closes the progress bar and draws the
        learning curve PNG.

        A finished checkpoint is complete even when it holds fewer episodes than the budget
        (a landing check stopped training, or ``keep_best`` kept an earlier machine): the
        protocol loads it as it is instead of resuming it (``--resume`` still trains on).
        """
        self.finished = True
        self.save()
        if self._progress is not None:
            self._progress.close()
        return plot_learning_curve(self.log.path, self.out_dir / "learning_curve.png", title=title)
