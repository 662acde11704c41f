"""Human operators: simulated pilots and a real person at the keyboard (docs/operators.md).

- :class:`SimulatedPilot` (TargetLunarLander) and :class:`SimulatedOperator` (UAV):
  a controller that knows the task, run with the human traits of
  :class:`OperatorTraits` (decision interval, noise, lag, ex-Gaussian RT, lapses);
  :data:`PRESETS` names the surrogate pilots (``expert``, ``noisy``, ``laggy``,
  ``distracted``).
- :class:`KeyboardPilot`: a person flies TargetLunarLander (``dcsc play lunarlander``);
  :class:`UAVKeyboardOperator`: a person flies the UAV. Both are a
  :class:`PersonAtControls` (pacing, RT per decision, quit, the prompt between episodes).
- :class:`RandomOperator`: a uniform random action every frame.

Every operator plugs into any pipeline through
:class:`~dcsc_torchrl.transforms.HumanOperatorTransform`; see ``docs/operators.md``.
"""

from dcsc_torchrl.humans.decision_loop import SimulatedHuman
from dcsc_torchrl.humans.keyboard import KeyboardPilot, NoDisplayError, PersonAtControls
from dcsc_torchrl.humans.operator_alone import operator_only_episodes, operator_only_policy
from dcsc_torchrl.humans.pilot import SimulatedPilot
from dcsc_torchrl.humans.random_operator import RandomOperator
from dcsc_torchrl.humans.traits import PRESETS, OperatorTraits
from dcsc_torchrl.humans.uav_keyboard import UAVCommand, UAVKeyboardOperator
from dcsc_torchrl.humans.uav_operator import SimulatedOperator

__all__ = [
    "PRESETS",
    "KeyboardPilot",
    "NoDisplayError",
    "OperatorTraits",
    "PersonAtControls",
    "RandomOperator",
    "SimulatedHuman",
    "SimulatedOperator",
    "SimulatedPilot",
    "UAVCommand",
    "UAVKeyboardOperator",
    "operator_only_episodes",
    "operator_only_policy",
]
