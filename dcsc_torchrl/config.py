"""Configs as data: a yaml file per recipe, a ``quick`` block, and ``key=value`` overrides.

As in TorchRL's sota-implementations the config is grouped by concern (``env``,
``collector``, ``optim``, ``loss``, ``logger``); overrides use the same dotted syntax as
hydra (``optim.lr=1e-3``).

Every config is checked before any work starts, against a schema read from the recipe's
own yaml: each key of the file (outside its ``quick`` block) has the type of its value
there (int, float, bool, str, list of one type, a group; a ``null`` key the type that
:data:`NULLABLE` declares), so a key added to a yaml file is checked with no code to
change. An unknown key, an override of a key the file fixes (:data:`FIXED`), a value of
the wrong type, a number that is not finite or out of its range (:data:`LIMITS`) and an
empty list that needs an entry (:data:`NON_EMPTY`) are refused with one line naming the
key (:class:`ConfigError`); a repeated entry of a list of things run once
(:data:`DISTINCT`) is dropped with a warning. This module imports no torch: the ``dcsc``
command checks a config in a fraction of a second.
"""

from __future__ import annotations

import difflib
import errno
import math
import os
import sys
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf


class UsageError(ValueError):
    """A mistake of the user's (a bad argument, config or file): ``dcsc`` reports it as one line, exit 2."""


class ConfigError(UsageError):
    """A config key that does not exist, or a value of the wrong type or range."""


@dataclass(frozen=True)
class Range:
    """The numbers a key accepts: from ``low`` to ``high``, each end included unless it is open.

    Examples:
        >>> unit = Range(0, 1, open_low=True)
        >>> 0.5 in unit, 0 in unit, str(unit)
        (True, False, 'a value in (0, 1]')
        >>> str(Range(1))
        'a value >= 1'
    """

    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def __contains__(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return above and below

    def __str__(self) -> str:
        if self.high == math.inf:
            return f"a value {'>' if self.open_low else '>='} {self.low:g}"
        return (f"a value in {'(' if self.open_low else '['}{self.low:g}, "
                f"{self.high:g}{')' if self.open_high else ']'}")


COUNT = Range(1)
NON_NEGATIVE = Range(0)
POSITIVE = Range(0, open_low=True)
UNIT = Range(0, 1)
"""A probability, a discount, a share of authority."""
STEP = Range(0, 1, open_low=True)
"""A soft-update coefficient: 0 would never move the target."""

LIMITS: dict[str, Range] = {
    # every recipe
    "seed": NON_NEGATIVE,
    "threads": COUNT,
    # pretraining
    "env.num_envs": COUNT,
    "network.hidden": COUNT,
    "network.actor_dropout": Range(0, 1, open_high=True),
    "collector.rollout_length": COUNT,
    "collector.workers": COUNT,
    "collector.init_random_frames": NON_NEGATIVE,
    "exploration.sigma_init": NON_NEGATIVE,
    "exploration.sigma_end": NON_NEGATIVE,
    "exploration.annealing_frames": COUNT,
    "loss.gamma": UNIT,
    "loss.gae_lambda": UNIT,
    "loss.polyak": UNIT,
    "loss.entropy_coeff": NON_NEGATIVE,
    "loss.critic_coeff": NON_NEGATIVE,
    "loss.reward_scale": POSITIVE,
    "train.episodes": COUNT,
    "train.frames": NON_NEGATIVE,
    "train.checkpoint_every": COUNT,
    "train.stop_success": UNIT,
    "train.stop_eval_episodes": COUNT,
    "eval.episodes": NON_NEGATIVE,
    "eval.scenarios": NON_NEGATIVE,
    "qcritic.buffer_size": COUNT,
    "qcritic.batch_size": COUNT,
    "qcritic.updates_per_batch": COUNT,
    "qcritic.lr": POSITIVE,
    "qcritic.tau": STEP,
    "optim.lr": POSITIVE,
    "optim.eps": POSITIVE,
    "ppo.epochs": COUNT,
    "ppo.minibatch_size": COUNT,
    "ppo.clip_epsilon": POSITIVE,
    "optim.actor_lr": POSITIVE,
    "optim.critic_lr": POSITIVE,
    "optim.batch_size": COUNT,
    "optim.buffer_size": COUNT,
    "optim.updates_per_frame": POSITIVE,
    "optim.max_grad_norm": POSITIVE,
    "optim.grad_clip": POSITIVE,
    # shared control
    "pretrain.seeds": NON_NEGATIVE,
    "machine.num_samples": Range(2),  # MC dropout's covariance needs two samples
    "arbiter.hula_threshold": NON_NEGATIVE,
    "arbiter.constant_betas": UNIT,
    "arbiter.centred.gain": POSITIVE,
    "online.theta_lr": NON_NEGATIVE,
    "online.critic_lr": NON_NEGATIVE,
    "online.gamma": UNIT,
    "online.tau": STEP,
    "online.updates_per_batch": COUNT,
    "warmup.updates": NON_NEGATIVE,
    "warmup.batch_size": COUNT,
    "warmup.lr": POSITIVE,
    "warmup.blend_betas": UNIT,
    "protocol.rollout_length": COUNT,
    "protocol.group_size": COUNT,
    "protocol.max_steps": COUNT,
    "scenarios.operator_runs": COUNT,
    "scenarios.machine_alone_runs": NON_NEGATIVE,
    "scenarios.collaboration_runs": COUNT,
    "scenarios.blend_runs": NON_NEGATIVE,
    "scenarios.validation_scenarios": COUNT,
    "scenarios.first_validation_seed": NON_NEGATIVE,
    # dcsc copilot (Reddy et al.'s DQN)
    "env.rollout_length": COUNT,
    "dqn.lr": POSITIVE,
    "dqn.batch_size": COUNT,
    "dqn.buffer_size": COUNT,
    "dqn.gamma": UNIT,
    "dqn.target_update_interval": COUNT,
    "dqn.updates_per_frame": POSITIVE,
    "dqn.exploration_fraction": STEP,
    "dqn.exploration_final_eps": UNIT,
    "dqn.train_alpha": UNIT,
    "alpha.grid": UNIT,
    "alpha.first_seed": NON_NEGATIVE,
    "alpha.scenarios": COUNT,
    # dcsc arbiter (the state-dependent arbiter's pretraining)
    "state.rounds": COUNT,
    "state.scenarios": COUNT,
    "state.calibration_runs": COUNT,
    "state.first_seed": NON_NEGATIVE,
    "state.segment_length": COUNT,
    "state.betas": UNIT,
    "state.blend_scenarios": COUNT,
    "state.critic_updates": COUNT,
    "state.arbiter_updates": COUNT,
    "state.batch_size": COUNT,
    "state.hidden": COUNT,
    "state.value_hidden": COUNT,
    "state.spread": POSITIVE,
    "state.lr": POSITIVE,
    "state.gae_lambda": UNIT,
    "state.entropy_coeff": NON_NEGATIVE,
    "state.critic_coeff": POSITIVE,
    "state.max_grad_norm": POSITIVE,
    # dcsc sweep
    "pretrain_seeds": NON_NEGATIVE,
    "ray.workers": COUNT,
    "ray.retries": NON_NEGATIVE,
}
"""The range of every count, rate and probability of every recipe's config (of each entry, for a
list); keys a config lacks are skipped, ``null`` passes. Every number must be finite besides."""

NULLABLE: dict[str, Any] = {
    "arbiter.hula_threshold": 0.5,
    "ida.expert": "runs/pretrain/seed0/checkpoint.pt",
    "reddy.copilots": ["runs/copilot_uav/copilot.pt"],
    "state.arbiters": ["runs/arbiter_lunarlander/arbiter.pt"],
    "protocol.max_steps": 1,
    "operators": ["expert"],
    "pretrain_seeds": [0],
    "methods": ["dcsc"],
    "ray.address": "auto",
}
"""The type of each key whose yaml value is ``null`` (a default computed at run time), given as an
example value: an override of it is checked as one of a key with that value in the yaml would be."""

NON_EMPTY = frozenset({"pretrain.seeds", "operator.presets", "tasks", "operators", "pretrain_seeds", "methods", "pool",
                       "alpha.grid", "state.pool", "state.betas", "selected"})
"""Lists that need an entry (``null`` passes where it is the default)."""

DISTINCT = frozenset({"pretrain.seeds", "operator.presets", "arbiter.constant_betas", "warmup.blend_betas", "tasks",
                      "operators", "pretrain_seeds", "methods", "pool", "alpha.grid", "state.pool", "state.betas"})
"""Lists of things each run once: a repeated entry is dropped, with a warning (it would count twice)."""

FIXED = frozenset({"task"})
"""Keys a yaml file fixes: the file is the task's, an override would run one task with another's settings."""

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
    """Refuses unknown keys, fixed keys and values whose type differs from the base yaml's (or
    :data:`NULLABLE`'s); coerces scalars to str."""
    for key, value in list(layer.items()):
        name = f"{prefix}{key}"
        if key not in schema:
            known = [f"{prefix}{k}" for k in schema]
            close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]}?" if close else "known keys here: " + ", ".join(known)
            raise ConfigError(f"unknown key {name} in {source} ({hint})")
        if name in FIXED:
            raise ConfigError(f"{name} is fixed by the config file ({schema[key]!r}), got {value!r}: choose the "
                              "task on the command line instead")
        base = schema[key]
        if base is None:
            if value is None:
                continue
            base = NULLABLE.get(name)
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


def _numbers(value: Any) -> list[float]:
    """The numbers of a leaf: itself, or a list's entries (booleans are not numbers)."""
    values = value if isinstance(value, list) else [value]
    return [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]


def _check_values(cfg: Mapping[str, Any], source: str) -> None:
    """Refuses a number that is not finite, one out of its :data:`LIMITS` and an empty :data:`NON_EMPTY` list."""
    for key, value in _leaves(cfg).items():
        numbers = _numbers(value)
        if not all(math.isfinite(v) for v in numbers):
            raise ConfigError(f"{key}: expected a finite number, got {value!r} (in {source})")
        limit = LIMITS.get(key)
        if limit is not None and not all(v in limit for v in numbers):
            each = " for every entry" if isinstance(value, list) else ""
            raise ConfigError(f"{key}: expected {limit}{each}, got {value!r} (in {source})")
        if key in NON_EMPTY and value == []:
            raise ConfigError(f"{key}: expected at least one entry, got [] (in {source})")


def warn(message: str) -> None:
    """A warning for the user: one line on stderr, ``dcsc: warning: ...``."""
    print(f"dcsc: warning: {message}", file=sys.stderr, flush=True)


def distinct(name: str, values: Iterable[Any], *, quiet: bool = False) -> list[Any]:
    """``values`` without repeats, in order; a repeated one is named in a :func:`warning <warn>`.

    Examples:
        >>> distinct("pretrain.seeds", [0, 1, 0], quiet=True)
        [0, 1]
    """
    values = list(values)
    unique = list(dict.fromkeys(values))
    repeated = [v for v in unique if values.count(v) > 1]
    if repeated and not quiet:
        warn(f"{name} lists {', '.join(map(str, repeated))} more than once: each runs once")
    return unique


def _drop_repeats(cfg: DictConfig, *, quiet: bool) -> None:
    """Each :data:`DISTINCT` list of ``cfg`` without repeats (:func:`distinct`)."""
    for key in DISTINCT:
        value = OmegaConf.select(cfg, key)
        if value is not None and len(set(value)) < len(value):
            OmegaConf.update(cfg, key, distinct(key, value, quiet=quiet), merge=False)


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


def load_config(path: str | os.PathLike, overrides: Sequence[str] = (), *, quick: bool = False,
                quiet: bool = False) -> DictConfig:
    """Loads a recipe's yaml, applies its ``quick`` block if asked, then the overrides, and checks them.

    A file may name a ``base`` yaml (relative to it) whose keys it extends or overrides,
    its ``quick`` block included: the two shared-control tasks share one base.

    Args:
        path: the yaml file.
        overrides: ``"group.key=value"`` strings (hydra's dotted syntax).
        quick: merge the file's top-level ``quick:`` block (the tiny setting used by tests
            and ``make reproduce QUICK=1``).
        quiet: no warning for a repeated entry of a :data:`DISTINCT` list (it is still dropped):
            for a check before the command that uses the config loads it again.

    Raises:
        ConfigError: the file is missing or not yaml, an override is malformed, names a key
            the config does not have or one the file fixes (:data:`FIXED`), or has a value of
            another type than the yaml's (:data:`NULLABLE`'s for a ``null`` key); a number is not
            finite or out of its range (:data:`LIMITS`), or a :data:`NON_EMPTY` list is empty.

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
    _check_values(OmegaConf.to_container(cfg), path.name)
    _drop_repeats(cfg, quiet=quiet)
    return cfg


def writable_folder(path: str | os.PathLike, option: str = "--out") -> Path:
    """``path`` when a command can write there: a folder, or one that can be made (nothing is made).

    The nearest folder of ``path`` that exists must be one (not a file) and take a new entry
    (a read-only location, a folder of another user's): checked by making and removing an
    empty temporary folder there.

    Raises:
        UsageError: one line naming ``option``, ``path`` and what stands in the way.
    """
    path = Path(path)
    parent = path
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise UsageError(f"{option} {path}: {parent} is a file, not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".dcsc-probe-", dir=parent))
    except OSError as err:
        reason = os.strerror(err.errno) if err.errno else str(err)
        if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            reason = f"not writable ({reason})"
        raise UsageError(f"{option} {path}: cannot write in {parent}: {reason}") from None
    return path


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
