"""dcsc-torchrl: dual confidence-based human-machine shared control (DC-SC) on TorchRL.

The method of Zhou et al., "A dual confidence evaluation-based shared control approach for
human-machine collaboration", as composable TorchRL pieces:

- :mod:`dcsc_torchrl.confidence` — the math: Eq. 6 (knowledge), Eq. 9 (human confidence),
  Eq. 10 (MC-dropout uncertainty), Eq. 13 (machine confidence);
- :mod:`dcsc_torchrl.transforms` — the operator and its confidence as env transforms;
- :mod:`dcsc_torchrl.machine` — the MC-dropout machine policy;
- :mod:`dcsc_torchrl.arbiters` — DC-SC's learnable arbiter (Eqs. 15, 18) and the baselines;
- :mod:`dcsc_torchrl.policy` — the shared policy (Eq. 14);
- :mod:`dcsc_torchrl.losses` — the critic's TD loss and the theta update (Eq. 19);
- :mod:`dcsc_torchrl.copilot` — a field's assistant beside it: Reddy et al.'s copilot.

The names below are imported from their modules on first use, so importing the package
(``import dcsc_torchrl.config``, the ``dcsc`` command's help) does not load torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_HOMES = {
    "arbiters": ["Arbiter", "CentredConfidenceArbiter", "ConfidenceArbiter", "ConstantArbiter",
                 "FrozenConfidenceArbiter", "HULAArbiter", "HumanOnlyArbiter", "MachineOnlyArbiter", "RuleArbiter",
                 "centred_fusion_weight", "confidence_ratio", "fusion_weight", "load_arbiter", "save_arbiter"],
    "copilot": ["CopilotPolicy", "CopilotQNetwork", "ToleranceArbiter", "TrainedCopilot", "copilot_task", "keeps_pilot",
                "load_copilot", "nearest_action", "save_copilot", "tolerant_choice"],
    "confidence": ["human_confidence", "knowledge_update", "machine_confidence", "mc_dropout_uncertainty"],
    "losses": ["QCriticLoss", "ThetaLoss"],
    "machine": ["MCDropoutPolicy", "calibrated_uncertainty_scale"],
    "policy": ["PolicyBlend", "SharedPolicyModule"],
    "transforms": ["HumanConfidenceTransform", "HumanOperator", "HumanOperatorTransform"],
}
_MODULE_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str) -> Any:
    if name not in _MODULE_OF:
        raise AttributeError(f"module 'dcsc_torchrl' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"dcsc_torchrl.{_MODULE_OF[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
