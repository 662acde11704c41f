"""``dcsc play lunarlander``: fly TargetLunarLander yourself, alone or with DC-SC.

    dcsc play lunarlander [--assist dcsc|none] [--checkpoint PATH] [--episodes N] [--seed S]

The frames of a ``render_mode="rgb_array"`` TargetLunarLander go to the
:class:`~dcsc_torchrl.humans.KeyboardPilot`'s window. With ``--assist dcsc`` the
pretrained machine (MC dropout, Eqs. 10, 13) shares control with you through the
confidence arbiter (Eqs. 14-18), and b_h, b_m and beta are drawn live on screen; alone,
your b_h (Eqs. 6, 9) and last RT are.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import Compose, GymWrapper, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.libs.gym import default_info_dict_reader
from torchrl.envs.utils import step_mdp

from dcsc_torchrl.arbiters import ConfidenceArbiter
from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.humans.evaluate import operator_only_policy
from dcsc_torchrl.humans.keyboard import KeyboardPilot, NoDisplayError
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.tasks import LUNAR_ID, LUNAR_INFO_KEYS
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

DEFAULT_CHECKPOINT = Path("runs/pretrain_lunarlander/checkpoint.pt")
_STATUS_KEYS = (
    ("human_confidence", "b_h (you)"),
    ("machine_confidence", "b_m (machine)"),
    ("beta", "beta (machine share)"),
    ("human_rt", "your last RT [s]"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dcsc play", description=__doc__.split("\n\n")[0])
    parser.add_argument("task", choices=["lunarlander"])
    parser.add_argument(
        "--assist",
        choices=["dcsc", "none"],
        default="dcsc",
        help="share control with the pretrained machine (dcsc) or fly alone",
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=DEFAULT_CHECKPOINT,
        help="LunarLander pretraining checkpoint (for --assist dcsc)",
    )
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    return parser


def load_machine(path: Path) -> nn.Module:
    """The pretrained LunarLander actor, or a FileNotFoundError that says how to get one."""
    if not Path(path).is_file():
        raise FileNotFoundError(
            f"no LunarLander checkpoint at {path}: run `dcsc pretrain lunarlander` first, "
            "pass --checkpoint PATH, or fly alone with --assist none"
        )
    actor, _ = machine_from_checkpoint(load_checkpoint(path, task="lunarlander"), "lunarlander")
    return actor


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


def make_policy(env: TransformedEnv, machine: nn.Module | None) -> TensorDictModuleBase:
    """DC-SC's shared policy around ``machine``, or the pilot alone when ``machine`` is None."""
    if machine is None:
        return operator_only_policy()
    return SharedPolicyModule(
        MCDropoutPolicy(machine, output="probs"), ConfidenceArbiter(), env.action_spec
    )


def status_lines(tensordict: TensorDictBase) -> list[str]:
    """The on-screen text: b_h, b_m, beta and the last RT, those the TensorDict holds."""
    return [
        f"{label}: {tensordict.get(key).flatten()[0].item():.2f}"
        for key, label in _STATUS_KEYS
        if key in tensordict.keys()
    ]


@torch.no_grad()
def play(
    env: TransformedEnv, policy: TensorDictModuleBase, pilot: KeyboardPilot, episodes: int
) -> list[dict[str, float]]:
    """Flies ``episodes`` episodes (fewer if the pilot quits); one summary dict per episode."""
    summaries = []
    for _ in range(episodes):
        td = env.reset()
        while True:
            td = policy(td)
            pilot.status = status_lines(td)
            td = env.step(td)
            step = td.get("next")
            if pilot.quit_requested:
                return summaries
            if step.get("done").any():
                break
            td = step_mdp(td)
        summaries.append(
            {
                "success": bool(step.get("success").any()),
                "return": step.get("episode_reward").item(),
                "steps": step.get("step_count").item(),
            }
        )
    return summaries


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``dcsc play`` (``argv`` = ``["lunarlander", *options]``)."""
    args = build_parser().parse_args(argv)
    confidence = HumanConfidenceTransform()
    try:
        machine = load_machine(args.checkpoint) if args.assist == "dcsc" else None
        render_env = gym.make(LUNAR_ID, render_mode="rgb_array")
        pilot = KeyboardPilot(frame_source=render_env.render, t_d=confidence.t_d)
    except (FileNotFoundError, NoDisplayError) as error:
        raise SystemExit(f"dcsc play: {error}") from error
    env = make_play_env(render_env, pilot, confidence, args.seed)
    print("arrow keys (or W/A/D): up = main engine, left/right = side engines; Esc quits")
    for episode, summary in enumerate(play(env, make_policy(env, machine), pilot, args.episodes)):
        outcome = "landed on the pad" if summary["success"] else "no landing"
        print(
            f"episode {episode}: {outcome}, return {summary['return']:.1f}, {summary['steps']} steps"
        )
    pilot.close()
