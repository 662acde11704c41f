"""``dcsc play lunarlander``: fly TargetLunarLander yourself, alone or with DC-SC.

    dcsc play lunarlander [--assist dcsc|state|ida|reddy|none] [--checkpoint PATH] [--copilot PATH]
                          [--arbiter PATH] [--episodes N] [--seed S] [--out DIR]

The frames of a ``render_mode="rgb_array"`` TargetLunarLander go to the
:class:`~dcsc_torchrl.humans.KeyboardPilot`'s window. With ``--assist dcsc`` the
pretrained machine (MC dropout, Eqs. 10, 13) shares control with you through the learned
arbiter of the simulated runs (``arbiter.form`` of ``recipes/shared_control_lunarlander.yaml``),
and theta (and the Q critic, unless the yaml's ``online.critic_lr`` is 0) learn online as
in Algorithm 1, once every ``protocol.rollout_length`` frames; b_h, b_m and beta are drawn live on screen. With
``--assist state`` the state-dependent arbiter pretrained in simulation next to that machine
(``--arbiter``; by default the one shipped for the shipped machine) shares control, its
authority a function of the frame, fine-tuned online as in a cell (:mod:`dcsc_torchrl.state_arbiter`). With
``--assist ida`` the machine takes a frame exactly where its pretrained Q critic rates the
machine's key above yours (IDA's intervention, :class:`~dcsc_torchrl.arbiters.InterventionArbiter`),
nothing learning. With ``--assist reddy`` Reddy et al.'s trained copilot (``dcsc copilot``,
``--copilot``) keeps your key where it is within its tolerance of the copilot's best and
presses its own otherwise (:mod:`dcsc_torchrl.copilot`). Alone, your b_h (Eqs. 6, 9) and last RT are.

Every play writes what the simulated runs write, into ``--out`` (default
``results/play/``): ``episodes.csv`` (one row per finished episode: method, phase
``play``, seed, success, steps, return, theta after it, ...) and ``trace.csv`` (one row per
frame: the actions of both partners, human_rt, knowledge, b_h, c_t, b_m, beta). Rows are
appended, every few frames and on Ctrl-C, so a user study is a folder of CSVs, one
``session`` per play.
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import Compose, GymWrapper, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.libs.gym import default_info_dict_reader
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from dcsc_torchrl.batched_envs import LUNAR_ID, LUNAR_INFO_KEYS
from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.config import writable_folder
from dcsc_torchrl.copilot import TrainedCopilot, load_copilot
from dcsc_torchrl.humans.keyboard import KeyboardPilot, NoDisplayError
from dcsc_torchrl.humans.operator_alone import operator_only_policy
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.protocol import ProtocolSettings
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.recipes.machines import ready_machine
from dcsc_torchrl.runlog import RunLog
from dcsc_torchrl.state_arbiter import PretrainedArbiter, load_pretrained_arbiter
from dcsc_torchrl.tasks import get_task
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

TASK = get_task("lunarlander")
"""The task a person plays at the keyboard (its four keys)."""
PHASE = "play"
_STATUS_KEYS = (
    ("human_confidence", "b_h (you)"),
    ("machine_confidence", "b_m (machine)"),
    ("beta", "beta (machine share)"),
    ("human_rt", "your last RT [s]"),
)
EPISODE_COLUMNS = ["task", "operator", "pretrain_seed", "method", "phase", "group", "seed", "path_length",
                   "return", "steps", "success", "hula_threshold", "session", "episode", "theta", "updates"]
"""``episodes.csv``'s columns: those of the simulated runs, then the play's own."""
_MACHINE_KEYS = ("machine_uncertainty", "machine_confidence", "confidence_ratio")


def play_config() -> DictConfig:
    """The parameters of the simulated LunarLander runs (confidences, machine, arbiter, Algorithm 1)."""
    from dcsc_torchrl.config import load_config

    return load_config(CONFIGS[TASK.name].protocol)


def load_play_copilot(path: Path) -> TrainedCopilot:
    """The copilot of ``--assist reddy``, or a FileNotFoundError that says how to get one."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"no copilot at {path}: train one with `dcsc copilot lunarlander`, or pass --copilot PATH")
    return load_copilot(path, TASK)


def load_play_arbiter(path: Path | None, cfg: DictConfig) -> PretrainedArbiter:
    """The pretrained arbiter of ``--assist state``: ``path``, or the one shipped for the shipped
    machine of ``pretrain.observes``; a FileNotFoundError that says how to get one."""
    from dcsc_torchrl.shipped import shipped_arbiter_path

    path = shipped_arbiter_path(TASK, cfg.pretrain.get("observes")) if path is None else Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no pretrained arbiter at {path}: pretrain one next to your machine with "
                                "`dcsc arbiter lunarlander`, or pass --arbiter PATH")
    return load_pretrained_arbiter(path, TASK)


def load_machine(path: Path) -> tuple[nn.Module, nn.Module]:
    """The pretrained LunarLander actor and Q critic, or a FileNotFoundError that says how to get them."""
    if not Path(path).is_file():
        raise FileNotFoundError(
            f"no LunarLander checkpoint at {path}: run `dcsc pretrain lunarlander` first, "
            "pass --checkpoint PATH, or fly alone with --assist none"
        )
    return machine_from_checkpoint(load_checkpoint(path, task=TASK.name, modules=TASK.checkpoint_modules), TASK)


def make_play_env(
    render_env: gym.Env, pilot: KeyboardPilot, confidence: HumanConfidenceTransform, seed: int
) -> TransformedEnv:
    """One TargetLunarLander (batch ``[]``) with the pilot's and the confidence transforms."""
    base = GymWrapper(render_env)
    base.set_info_dict_reader(default_info_dict_reader(list(LUNAR_INFO_KEYS)))
    transforms = [HumanOperatorTransform(pilot, seed=seed), confidence]
    env = TransformedEnv(base, Compose(*transforms, RewardSum(), StepCounter()))
    env.set_seed(seed)
    return env


def assist_method(cfg: DictConfig) -> str:
    """The method name of the learned arbiter the config's ``arbiter.form`` picks."""
    from dcsc_torchrl.methods import learned_method

    return learned_method(cfg.arbiter.form)


def make_policy(env: TransformedEnv, machine: nn.Module | None, cfg: DictConfig | None = None, *,
                q_value: nn.Module | None = None, copilot: TrainedCopilot | None = None,
                state_arbiter: PretrainedArbiter | None = None) -> TensorDictModuleBase:
    """The shared policy around ``machine`` (as the simulated runs build it), or the pilot alone:
    DC-SC's learned arbiter, with ``q_value`` IDA's intervention on that Q critic, with
    ``state_arbiter`` a copy of that pretrained state-dependent arbiter; or ``copilot``'s own
    (Reddy et al.'s copilot and its tolerance rule)."""
    if copilot is not None:
        return copilot.policy(env.full_action_spec["action"])
    if machine is None:
        return operator_only_policy()
    from dcsc_torchrl.methods import build_policy, make_arbiter
    from dcsc_torchrl.protocol import ArbiterSettings

    cfg = play_config() if cfg is None else cfg
    if q_value is not None:
        arbiter = make_arbiter("ida", TASK.action_dims, q_value=q_value, discrete=TASK.discrete)
    elif state_arbiter is not None:
        arbiter = copy.deepcopy(state_arbiter.arbiter)
    else:
        method = assist_method(cfg)
        arbiter = make_arbiter(method, TASK.action_dims, **ArbiterSettings(**cfg.arbiter).start(method))
    return build_policy(machine, arbiter, env.full_action_spec["action"], discrete=TASK.discrete, **cfg.machine)


def make_learner(policy: TensorDictModuleBase, critic: nn.Module, cfg: DictConfig) -> Any:
    """Algorithm 1's online learner (theta and the critic) with the simulated runs' settings.

    Theta always reads the pretrained action critic here (``theta_critic="action"``): the
    authority critic is fitted on calibration runs of the two partners alone, which a
    person's play session does not have.
    """
    from dcsc_torchrl.online import make_online_learner

    return make_online_learner(policy, critic, **{**cfg.online, "theta_critic": "action"})


def status_lines(tensordict: TensorDictBase) -> list[str]:
    """The on-screen text: b_h, b_m, beta and the last RT, those the TensorDict holds."""
    return [
        f"{label}: {tensordict.get(key).flatten()[0].item():.2f}"
        for key, label in _STATUS_KEYS
        if key in tensordict.keys()
    ]


def _cell(value: Any) -> Any:
    """A CSV cell: NaN (no machine in the loop) as an empty cell."""
    return None if isinstance(value, float) and math.isnan(value) else value


class PlayRecorder:
    """Appends a play's frames to ``trace.csv`` and its episodes to ``episodes.csv`` in ``out``.

    Trace rows are formatted by the simulated runs' own :func:`~dcsc_torchrl.episodes.trace_rows`;
    without a machine (``--assist none``) the machine's columns are empty. Frames are
    buffered and written every :meth:`flush` (the play calls it every few frames, at each
    episode's end and on the way out, Ctrl-C included).

    Args:
        out: the output folder (made at the first row; refused now when it cannot be written,
            or when its ``episodes.csv`` has other columns).
        method: ``episodes.csv``'s method (``dcsc``, ``dcsc_centred`` or ``operator``).
        participant: the operator column.
        pretrain_seed: the machine's pretraining seed, where known.
    """

    def __init__(self, out: Path, method: str, participant: str, pretrain_seed: int | None = None) -> None:
        self.out = writable_folder(out)
        self.base = {"task": TASK.name, "operator": participant, "pretrain_seed": pretrain_seed, "method": method,
                     "phase": PHASE}
        self.session = time.strftime("%Y%m%dT%H%M%S")
        self.episodes = RunLog(self.out / "episodes.csv", EPISODE_COLUMNS)
        self.episodes.check_header()
        self.trace: RunLog | None = None
        self._pending: list[dict[str, Any]] = []

    def frame(self, tensordict: TensorDictBase, *, seed: int, episode: int, step: int) -> None:
        """Buffers one frame (the TensorDict after ``env.step``, ``next`` included)."""
        from dcsc_torchrl.episodes import trace_rows

        frame = tensordict.copy()  # shallow: the keys set below stay here
        machine = "machine_probs" in frame.keys()
        if not machine:  # the operator alone: no machine output to show
            nan = torch.full((1,), math.nan)
            for key in _MACHINE_KEYS:
                frame.set(key, nan)
            frame.set("beta", torch.zeros(1))
            frame.set("machine_probs", frame.get("human_action").float())
        row = trace_rows(frame.unsqueeze(0), TASK)[0]
        row["step"] = step
        if not machine:
            row["machine_action"] = None
        self._pending.append({**self.base, "seed": seed, "session": self.session, "episode": episode,
                              **{key: _cell(value) for key, value in row.items()}})

    def flush(self) -> None:
        """Writes the buffered frames to ``trace.csv``."""
        for row in self._pending:
            if self.trace is None:
                self.trace = RunLog(self.out / "trace.csv", list(row))
            self.trace.append(row)
        self._pending.clear()

    def episode(self, summary: dict[str, Any]) -> None:
        """Writes one finished episode's row (and the frames buffered so far)."""
        self.flush()
        row = {**self.base, "group": 0, "path_length": None, "hula_threshold": None, "session": self.session,
               **summary}
        self.episodes.append({key: _cell(value) for key, value in row.items()})


def play(
    env: TransformedEnv,
    policy: TensorDictModuleBase,
    pilot: KeyboardPilot,
    episodes: int,
    *,
    seed: int = 0,
    learner: Any | None = None,
    rollout_length: int = 5,
    recorder: PlayRecorder | None = None,
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> list[dict[str, Any]]:
    """Flies ``episodes`` episodes (fewer if the pilot quits); one summary dict per finished episode.

    Episode ``i`` plays scenario ``seed + i`` (the pad the simulated runs draw for that
    seed). With a ``learner`` (an :class:`~dcsc_torchrl.online.OnlineLearner`), every
    ``rollout_length`` frames are handed to it as a batch ``[1, rollout_length]``
    (Algorithm 1: theta, and the critic unless held, learn while the person flies). With a
    ``recorder``, every frame and every finished episode is written. ``exploration_type``
    is how the shared action is taken from Eq. 14's mixture (``protocol.shared_action``:
    ``RANDOM`` draws it, ``MODE`` takes its most likely key), as in the simulated runs.
    """
    summaries: list[dict[str, Any]] = []
    rollout: list[TensorDictBase] = []
    try:
        for episode in range(episodes):
            env.set_seed(seed + episode)
            with torch.no_grad():
                td = env.reset()
            step_index = 0
            while True:
                with torch.no_grad(), set_exploration_type(exploration_type):
                    td = policy(td)
                    pilot.status = status_lines(td)
                    td = env.step(td)
                step_index += 1
                step = td.get("next")
                if recorder is not None:
                    recorder.frame(td, seed=seed + episode, episode=episode, step=step_index)
                if learner is not None:
                    rollout.append(td.clone())
                    if len(rollout) == rollout_length:
                        learner(torch.stack(rollout).unsqueeze(0))
                        rollout.clear()
                        if recorder is not None:
                            recorder.flush()
                if pilot.quit_requested:
                    return summaries
                if step.get("done").any():
                    break
                with torch.no_grad():
                    td = step_mdp(td)
            summary = {
                "seed": seed + episode,
                "episode": episode,
                "success": bool(step.get("success").any()),
                "return": step.get("episode_reward").item(),
                "steps": int(step.get("step_count").item()),
            }
            if learner is not None:
                summary["theta"] = float(policy["arbiter"].theta.detach().reshape(-1)[0])
                summary["updates"] = len(learner.history)
            summaries.append(summary)
            if recorder is not None:
                recorder.episode(summary)
    finally:
        if recorder is not None:
            recorder.flush()
    return summaries


def run_play(args: argparse.Namespace) -> None:
    """A play session with the options of :func:`~dcsc_torchrl.recipes.options.add_play_options` (``dcsc play``)."""
    cfg = play_config()
    confidence = HumanConfidenceTransform(**cfg.human)
    try:
        networks = ready_machine(TASK, cfg, args.checkpoint) if args.assist in ("dcsc", "state", "ida") else None
        copilot = load_play_copilot(args.copilot) if args.assist == "reddy" else None
        state = load_play_arbiter(args.arbiter, cfg) if args.assist == "state" else None
        if state is not None:
            state.check_evaluated_next_to("person", networks[0])  # the machine it was pretrained next to
        method = {"dcsc": assist_method(cfg), "state": "dcsc_state", "ida": "ida", "reddy": "reddy",
                  "none": "operator"}[args.assist]
        recorder = PlayRecorder(args.out, method, args.participant)  # its folder checked before the window opens
        render_env = gym.make(LUNAR_ID, render_mode="rgb_array")
        pilot = KeyboardPilot(frame_source=render_env.render, t_d=confidence.t_d)
    except (FileNotFoundError, NoDisplayError, ValueError) as error:
        raise SystemExit(f"dcsc play: {error}") from error
    env = make_play_env(render_env, pilot, confidence, args.seed)
    machine, critic = networks if networks is not None else (None, None)
    policy = make_policy(env, machine, cfg, q_value=critic if args.assist == "ida" else None, copilot=copilot,
                         state_arbiter=state)
    learner = (make_learner(policy, critic, cfg) if args.assist == "dcsc"
               else state.learner(policy) if state is not None else None)
    print("arrow keys (or W/A/D): up = main engine, left/right = side engines; Esc quits")
    try:
        summaries = play(env, policy, pilot, args.episodes, seed=args.seed, learner=learner,
                         rollout_length=learner.segment_length if state is not None else int(cfg.protocol.rollout_length),
                         recorder=recorder,
                         exploration_type=ProtocolSettings(seed=cfg.seed, **cfg.protocol).exploration_type)
    finally:
        pilot.close()
    for summary in summaries:
        outcome = "landed on the pad" if summary["success"] else "no landing"
        theta = f", theta {summary['theta']:.3f}" if "theta" in summary else ""
        print(f"episode {summary['episode']}: {outcome}, return {summary['return']:.1f}, "
              f"{summary['steps']} steps{theta}")
    written = [name for name in ("episodes.csv", "trace.csv") if (recorder.out / name).exists()]
    print(f"results in {recorder.out} ({', '.join(written)})" if written else "nothing flown: nothing written")
