"""A task's shared-control config, checked whole: the yaml's keys, types and ranges, then
every group's values by the object that will use them (the door of ``dcsc run``, ``dcsc
sweep`` and ``dcsc reproduce``; docs/errors.md)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from omegaconf import DictConfig

from dcsc_torchrl.checkpoint import checkpoint_path
from dcsc_torchrl.config import (
    ConfigError,
    load_config,
)
from dcsc_torchrl.humans.traits import PRESETS
from dcsc_torchrl.networks import LUNAR_MACHINE_VIEWS, view_recipe_settings
from dcsc_torchrl.online import check_online_settings
from dcsc_torchrl.protocol import (
    ArbiterSettings,
    MachineSettings,
    ProtocolSettings,
    Scenarios,
    WarmupSettings,
)
from dcsc_torchrl.recipes.configs import CONFIGS
from dcsc_torchrl.tasks import Task
from dcsc_torchrl.transforms import HumanConfidenceTransform


def task_config(task: Task, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """The shared-control config of ``task`` (its yaml over ``shared_control.yaml``), checked whole:
    the yaml's keys, types and ranges (:func:`~dcsc_torchrl.config.load_config`), every group's
    values by the object that will use them (:func:`cell_settings`), the validation groups, the
    operator presets named and the pretraining recipe's settings (:func:`pretrain_config`)."""
    cfg = load_config(CONFIGS[task.name].protocol, overrides, quick=quick)
    cell_settings(cfg)
    check_groups(cfg)
    check_names("operator.presets", "operator preset", cfg.operator.presets, list(PRESETS))
    check_names("operator.main", "operator preset", [cfg.operator.main], list(PRESETS))
    if "observes" in cfg.pretrain:
        check_names("pretrain.observes", "machine view", [cfg.pretrain.observes], list(LUNAR_MACHINE_VIEWS))
    if not cfg.pretrain.shipped:
        pretrain_config(task, cfg, cfg.pretrain.seeds[0], quick=quick)
    return cfg


def check_groups(cfg: DictConfig) -> None:
    """Refuses a ``protocol.group_size`` that does not split the validation scenarios into equal groups."""
    size, count = cfg.protocol.group_size, cfg.scenarios.validation_scenarios
    if count % size:
        raise ConfigError(f"protocol.group_size: expected a divisor of scenarios.validation_scenarios ({count}), "
                          f"got {size} (the groups would differ in size)")


def pretrain_config(task: Task, cfg: DictConfig, seed: int, *, quick: bool) -> DictConfig:
    """The config that pretrains seed ``seed``'s machine of ``cfg``: the task's pretraining yaml with
    ``pretrain.recipe``'s settings, written to ``{pretrain.out_dir}/seed{seed}/``.

    Raises:
        ConfigError: a setting of ``pretrain.recipe`` is refused by the pretraining yaml (named).
    """
    out_dir = checkpoint_path(cfg.pretrain.out_dir, seed).parent
    settings = [*view_settings(cfg), *cfg.pretrain.recipe, f"seed={seed}", f"logger.out_dir={out_dir}"]
    try:
        return load_config(CONFIGS[task.name].pretrain, settings, quick=quick)
    except ConfigError as err:
        raise ConfigError(f"pretrain.recipe: {err}") from None


def view_settings(cfg: DictConfig) -> list[str]:
    """The pretraining settings of ``pretrain.observes`` (LunarLander): a machine that sees the
    pad (``target``) is pretrained on random pads, a goal-blind one on the centre pad; none for
    a task without the key. ``pretrain.recipe`` comes after them and may say otherwise."""
    observes = cfg.pretrain.get("observes")
    if observes is None:
        return []
    return view_recipe_settings(observes)


def _human_settings(**group: Any) -> dict[str, Any]:
    """:class:`HumanConfidenceTransform`'s keywords, its ranges checked (Eqs. 6-9: ``K > 0``, ...)."""
    HumanConfidenceTransform(**group)
    return group


def _online_settings(**group: Any) -> dict[str, Any]:
    """:class:`~dcsc_torchrl.online.OnlineLearner`'s keywords, the names it would refuse refused now."""
    check_online_settings(**group)
    return group


SETTINGS: dict[str, Callable[..., Any]] = {
    "human": _human_settings,
    "machine": MachineSettings,
    "arbiter": ArbiterSettings,
    "online": _online_settings,
    "warmup": WarmupSettings,
    "protocol": ProtocolSettings,
    "scenarios": Scenarios.standard,
}
"""The object each config group's keys are the keywords of (``protocol`` also gets the config's seed)."""


def _settings_of(group: str, build: Callable[..., Any], values: Mapping[str, Any], **extra: Any) -> Any:
    """``build(**values)``; a ``ValueError`` in it is a :class:`ConfigError` naming the key (``human.K ...``)."""
    try:
        return build(**values, **extra)
    except ValueError as err:
        text = str(err)
        named = text.split(" ", 1)[0] in values  # the message starts with the parameter's name
        raise ConfigError(f"{group}.{text}" if named else text) from None


def cell_settings(cfg: DictConfig) -> dict[str, Any]:
    """:func:`run_cell`'s settings from the config's groups, every value checked by the object
    that uses it: a bad one is a :class:`ConfigError` naming its key."""
    return {group: _settings_of(group, build, cfg[group], **({"seed": cfg.seed} if group == "protocol" else {}))
            for group, build in SETTINGS.items()}


def check_names(key: str, kind: str, names: Sequence[str], known: Sequence[str]) -> list[str]:
    """``names`` when every one is in ``known``; else a :class:`ConfigError` naming ``key`` and listing the known ones."""
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ConfigError(f"{key}: unknown {kind} {', '.join(map(repr, unknown))}: expected one of "
                          f"{', '.join(known)}")
    return list(names)
