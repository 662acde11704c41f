"""Configs as data: a yaml file per recipe, a ``quick`` block, and ``key=value`` overrides.

As in TorchRL's sota-implementations the config is grouped by concern (``env``,
``collector``, ``optim``, ``loss``, ``logger``); overrides use the same dotted syntax as
hydra (``optim.lr=1e-3``).

Every config is checked before any work starts, against a schema read from the recipe's
own yaml: each key of the file (outside its ``quick`` block) has the type of its value
there (int, float, bool, str, list of one type, a group; ``null`` accepts anything), so a
key added to a yaml file is checked with no code to change. An unknown key, a value of
the wrong type and a count that is not positive (:data:`LIMITS`) are refused with one
line naming the key (:class:`ConfigError`). This module imports no torch: the ``dcsc``
command checks a config in a fraction of a second.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf


class UsageError(ValueError):
    """A mistake of the user's (a bad argument, config or file): ``dcsc`` reports it as one line, exit 2."""


class ConfigError(UsageError):
    """A config key that does not exist, or a value of the wrong type or range."""


LIMITS: dict[str, tuple[float, bool]] = {
    # key: (bound, strict) -- the value must be > bound (strict) or >= bound; null passes
    "threads": (1, False),
    "env.num_envs": (1, False),
    "collector.rollout_length": (1, False),
    "collector.workers": (1, False),
    "collector.init_random_frames": (0, False),
    "exploration.annealing_frames": (1, False),
    "train.episodes": (1, False),
    "train.checkpoint_every": (1, False),
    "eval.episodes": (0, False),
    "eval.scenarios": (0, False),
    "qcritic.buffer_size": (1, False),
    "qcritic.batch_size": (1, False),
    "qcritic.updates_per_batch": (1, False),
    "qcritic.lr": (0, True),
    "optim.lr": (0, True),
    "ppo.epochs": (1, False),
    "ppo.minibatch_size": (1, False),
    "ppo.clip_epsilon": (0, True),
    "optim.actor_lr": (0, True),
    "optim.critic_lr": (0, True),
    "optim.batch_size": (1, False),
    "optim.buffer_size": (1, False),
    "optim.updates_per_frame": (0, True),
    "optim.max_grad_norm": (0, True),
    "optim.grad_clip": (0, True),
    "machine.num_samples": (1, False),
    "online.updates_per_batch": (1, False),
    "warmup.updates": (0, False),
    "warmup.batch_size": (1, False),
    "warmup.lr": (0, True),
    "scenarios.machine_alone_runs": (0, False),
    "scenarios.blend_runs": (0, False),
    "scenarios.first_validation_seed": (0, False),
    "arbiter.centred.gain": (0, True),
    "protocol.rollout_length": (1, False),
    "online.theta_lr": (0, False),
    "online.critic_lr": (0, False),
    "scenarios.operator_runs": (1, False),
    "scenarios.collaboration_runs": (1, False),
    "scenarios.validation_scenarios": (1, False),
    "protocol.group_size": (1, False),
    "protocol.max_steps": (1, False),
    "ray.workers": (1, False),
    "ray.retries": (0, False),
}
"""Lower bounds of the counts and rates of every recipe's config; keys a config lacks are skipped."""

_TYPE_NAMES = {int: "an int", float: "a number", bool: "true or false", str: "a string", list: "a list",
               dict: "a group of keys"}


def _kind(value: Any) -> type | None:
    """The schema type of a base value (``None``: anything goes)."""
    if value is None:
        return None
    for kind in (bool, int, float, str, list, dict):
        if isinstance(value, kind):
            return kind
    return None


def _fits(kind: type, value: Any) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, kind)


def _leaves(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a.b": value}`` for every leaf of a nested mapping."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(_leaves(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def _check_layer(layer: Mapping[str, Any], schema: Mapping[str, Any], source: str, prefix: str = "") -> None:
    """Refuses unknown keys and values whose type differs from the base yaml's; coerces scalars to str."""
    for key, value in list(layer.items()):
        name = f"{prefix}{key}"
        if key not in schema:
            known = [f"{prefix}{k}" for k in schema]
            close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]}?" if close else "known keys here: " + ", ".join(known)
            raise ConfigError(f"unknown key {name} in {source} ({hint})")
        base = schema[key]
        kind = _kind(base)
        if kind is dict:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{name}: expected a group of keys ({', '.join(base)}), got {value!r}")
            _check_layer(value, base, source, f"{name}.")
            continue
        if kind is None:
            continue
        if kind is str and isinstance(value, (int, float)) and not isinstance(value, bool):
            layer[key] = str(value)  # a name that looks like a number (`operator.main=1`)
            continue
        if not _fits(kind, value):
            raise ConfigError(f"{name}: expected {_TYPE_NAMES[kind]}, got {value!r}")
        if kind is list and base:
            element = _kind(base[0])
            if element is not None and all(_fits(element, b) for b in base):
                bad = [v for v in value if not _fits(element, v)]
                if bad:
                    raise ConfigError(f"{name}: expected a list of {_TYPE_NAMES[element].split(' ', 1)[1]}s, "
                                      f"got {value!r}")


def _check_limits(cfg: Mapping[str, Any], source: str) -> None:
    flat = _leaves(cfg)
    for key, (bound, strict) in LIMITS.items():
        value = flat.get(key)
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if value < bound or (strict and value == bound):
            raise ConfigError(f"{key}: expected a value {'>' if strict else '>='} {bound:g}, got {value!r} "
                              f"(in {source})")


def parse_override(item: str) -> dict[str, Any]:
    """``"a.b=1"`` as ``{"a": {"b": 1}}``, the value read as yaml (hydra's dotted syntax)."""
    key, sep, _ = item.partition("=")
    if not sep or not key or key.startswith("-"):
        raise ConfigError(f"override {item!r} is not of the form key=value")
    try:
        return OmegaConf.to_container(OmegaConf.from_dotlist([item]))
    except Exception as err:  # omegaconf's grammar errors
        raise ConfigError(f"override {item!r}: {str(err).splitlines()[0]}") from None


def _read(path: Path, seen: tuple[Path, ...] = ()) -> DictConfig:
    """The yaml at ``path`` merged over its ``base`` file's (a path relative to it), recursively."""
    if not path.is_file():
        raise ConfigError(f"no config file at {path}")
    try:
        cfg = OmegaConf.load(path)
    except Exception as err:  # yaml scanner / parser errors
        raise ConfigError(f"{path} is not valid yaml: {str(err).splitlines()[0]}") from None
    base = cfg.pop("base", None)
    if base is None:
        return cfg
    base_path = (path.parent / str(base)).resolve()
    if base_path in seen:
        raise ConfigError(f"{path}: base {base} includes itself")
    return OmegaConf.merge(_read(base_path, (*seen, path.resolve())), cfg)


def load_config(path: str | os.PathLike, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """Loads a recipe's yaml, applies its ``quick`` block if asked, then the overrides, and checks them.

    A file may name a ``base`` yaml (relative to it) whose keys it extends or overrides,
    its ``quick`` block included: the two shared-control tasks share one base.

    Args:
        path: the yaml file.
        overrides: ``"group.key=value"`` strings (hydra's dotted syntax).
        quick: merge the file's top-level ``quick:`` block (the tiny setting used by tests
            and ``make reproduce QUICK=1``).

    Raises:
        ConfigError: the file is missing or not yaml, an override is malformed, names a key
            the config does not have or has a value of another type than the yaml's, or a
            count of :data:`LIMITS` is out of range.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "c.yaml"
        >>> _ = path.write_text("train: {episodes: 5}\\n")
        >>> load_config(path, ["train.episodes=7"]).train.episodes
        7
        >>> load_config(path, ["train.episodez=7"])
        Traceback (most recent call last):
        ...
        dcsc_torchrl.config.ConfigError: unknown key train.episodez in c.yaml (did you mean train.episodes?)
    """
    path = Path(path)
    cfg = _read(path)
    quick_block = cfg.pop("quick", None)
    schema = OmegaConf.to_container(cfg)
    layers: list[tuple[dict[str, Any], str]] = []
    if quick and quick_block is not None:
        layers.append((OmegaConf.to_container(quick_block), f"the quick block of {path.name}"))
    layers += [(parse_override(item), path.name) for item in overrides]
    for layer, source in layers:
        _check_layer(layer, schema, source)
    OmegaConf.set_struct(cfg, True)
    for layer, _ in layers:
        cfg = OmegaConf.merge(cfg, layer)
    _check_limits(OmegaConf.to_container(cfg), path.name)
    return cfg


def to_plain(cfg: DictConfig) -> dict[str, Any]:
    """The config as a plain dict (what a checkpoint stores)."""
    return OmegaConf.to_container(cfg, resolve=True)


def config_diff(old: Mapping[str, Any], new: Mapping[str, Any], *, ignore: Iterable[str] = ()) -> list[str]:
    """The keys whose values differ between two plain configs, as ``"key: old -> new"``.

    Examples:
        >>> config_diff({"env": {"num_envs": 8}, "seed": 0}, {"env": {"num_envs": 3}, "seed": 0})
        ['env.num_envs: 8 -> 3']
    """
    before, after, skip = _leaves(old), _leaves(new), set(ignore)
    missing = object()
    lines = []
    for key in sorted(before.keys() | after.keys()):
        a, b = before.get(key, missing), after.get(key, missing)
        if key in skip or a == b:
            continue
        show = [("(absent)" if v is missing else repr(v)) for v in (a, b)]
        lines.append(f"{key}: {show[0]} -> {show[1]}")
    return lines
