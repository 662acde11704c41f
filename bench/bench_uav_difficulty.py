"""How hard the UAV scenarios are: each partner alone on the 50 validation scenarios.

Run: ``python bench/bench_uav_difficulty.py [--runs runs/pretrain_uav/seed0 ...]``. One
torch thread. Prints a markdown table over the validation scenarios (seeds 0..49):

- the best constant IIFDS coefficients, :data:`dcsc_torchrl.envs.uav.BEST_CONSTANT_ACTION` (chosen by
  :func:`dcsc_torchrl.envs.uav.best_constant_action` on seeds 1000..1099, none of them validation);
- the simulated operator alone, per preset of ``dcsc_torchrl.humans.traits.PRESETS``
  (its noisy look-ahead included), the operator seed 0;
- optionally the pretrained DDPG machines, read from each run's ``eval.csv`` (written by
  ``recipes/pretrain_ddpg_uav.py``: greedy, machine alone).

Path length and steps are means over the successful flights.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch

from dcsc_torchrl.batched_envs import make_uav_env
from dcsc_torchrl.envs.uav import BEST_CONSTANT_ACTION, HORIZON, constant_action_outcomes
from dcsc_torchrl.humans import SimulatedOperator
from dcsc_torchrl.humans.operator_alone import operator_only_policy
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.transforms import HumanOperatorTransform

VALIDATION = list(range(50))


def row(name: str, success: torch.Tensor, collision: torch.Tensor, length: torch.Tensor,
        steps: torch.Tensor, returns: torch.Tensor) -> str:
    ok = success.bool()
    return (
        f"| {name} | {ok.float().mean():.0%} | {collision.float().mean():.0%} | "
        f"{length[ok].mean():.2f} | {steps[ok].float().mean():.1f} | {returns.mean():.1f} |"
    )


@torch.no_grad()
def operator_alone(preset: str) -> dict[str, torch.Tensor]:
    """First episode of the operator alone on every validation scenario."""
    operator = SimulatedOperator.from_preset(preset)
    env = make_uav_env(
        len(VALIDATION), scenario_seeds=VALIDATION,
        transforms=[HumanOperatorTransform(operator, seed=0)],
    )
    env.set_seed(0)
    rollout = env.rollout(HORIZON, operator_only_policy(), break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    first = done.int().argmax(-1)  # every flight ends by the horizon
    rows = torch.arange(len(VALIDATION))
    end = rollout["next"][rows, first]
    return {
        "success": end["success"].squeeze(-1),
        "collision": end["collision"].squeeze(-1) | end["out_of_bounds"].squeeze(-1),
        "path_length": end["path_length"].squeeze(-1),
        "steps": first + 1,
        "return": end["episode_reward"].squeeze(-1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="*", default=[], help="pretraining run directories")
    parser.add_argument("--presets", nargs="*", default=list(PRESETS))
    args = parser.parse_args()
    torch.set_num_threads(1)

    print("| on validation seeds 0..49 | success | collision or exit | path length | steps |"
          " return |")
    print("|---|---:|---:|---:|---:|---:|")
    constant = constant_action_outcomes([BEST_CONSTANT_ACTION], VALIDATION)
    print(row(
        f"best constant {BEST_CONSTANT_ACTION}", constant["success"][0],
        constant["collision"][0] | constant["out_of_bounds"][0], constant["path_length"][0],
        constant["steps"][0], constant["return"][0],
    ))
    for preset in args.presets:
        out = operator_alone(preset)
        print(row(f"operator `{preset}` alone", out["success"], out["collision"],
                  out["path_length"], out["steps"], out["return"]), flush=True)
    for run in args.runs:
        frame = pd.read_csv(Path(run) / "eval.csv")
        values = {key: torch.tensor(frame[key].to_numpy()) for key in frame.columns}
        print(row(
            f"DDPG {run}", values["success"], values["collision"] | values["out_of_bounds"],
            values["path_length"], values["steps"], values["return"],
        ))


if __name__ == "__main__":
    main()
