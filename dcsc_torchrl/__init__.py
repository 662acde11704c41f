"""dcsc-torchrl: dual confidence-based human-machine shared control (DC-SC) on TorchRL.

The method of Zhou et al., "A dual confidence evaluation-based shared control approach for
human-machine collaboration", as composable TorchRL pieces:

- :mod:`dcsc_torchrl.confidence` — the math: Eq. 6 (knowledge), Eq. 9 (human confidence),
  Eq. 10 (MC-dropout uncertainty), Eq. 13 (machine confidence);
- :mod:`dcsc_torchrl.transforms` — the operator and its confidence as env transforms;
- :mod:`dcsc_torchrl.machine` — the MC-dropout machine policy;
- :mod:`dcsc_torchrl.arbiters` — DC-SC's learnable arbiter (Eqs. 15, 18) and the baselines;
- :mod:`dcsc_torchrl.policy` — the shared policy (Eq. 14);
- :mod:`dcsc_torchrl.losses` — the critic's TD loss and the theta update (Eq. 19).
"""

from dcsc_torchrl.arbiters import (
    Arbiter,
    ConfidenceArbiter,
    HULAArbiter,
    HumanOnlyArbiter,
    MachineOnlyArbiter,
    confidence_ratio,
    fusion_weight,
)
from dcsc_torchrl.confidence import (
    human_confidence,
    knowledge_update,
    machine_confidence,
    mc_dropout_uncertainty,
)
from dcsc_torchrl.losses import QCriticLoss, ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.policy import PolicyBlend, SharedPolicyModule
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperator, HumanOperatorTransform

__all__ = [
    "Arbiter",
    "ConfidenceArbiter",
    "HULAArbiter",
    "HumanConfidenceTransform",
    "HumanOnlyArbiter",
    "HumanOperator",
    "HumanOperatorTransform",
    "MCDropoutPolicy",
    "MachineOnlyArbiter",
    "PolicyBlend",
    "QCriticLoss",
    "SharedPolicyModule",
    "ThetaLoss",
    "confidence_ratio",
    "fusion_weight",
    "human_confidence",
    "knowledge_update",
    "machine_confidence",
    "mc_dropout_uncertainty",
]
