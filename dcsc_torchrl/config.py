"""Configs as data: a yaml file per recipe, a ``quick`` block, and ``key=value`` overrides.

As in TorchRL's sota-implementations the config is grouped by concern (``env``,
``collector``, ``optim``, ``loss``, ``logger``); overrides use the same dotted syntax as
hydra (``optim.lr=1e-3``). Unknown keys are an error, so a typo never silently does
nothing.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf


def load_config(path: str | os.PathLike, overrides: Sequence[str] = (), *, quick: bool = False) -> DictConfig:
    """Loads a recipe's yaml, applies its ``quick`` block if asked, then the overrides.

    Args:
        path: the yaml file.
        overrides: ``"group.key=value"`` strings (hydra's dotted syntax).
        quick: merge the file's top-level ``quick:`` block (the tiny setting used by tests
            and ``make reproduce QUICK=1``).

    Raises:
        ValueError: an override names a key the config does not have, or is malformed.
    """
    cfg = OmegaConf.load(path)
    quick_block = cfg.pop("quick", None)
    OmegaConf.set_struct(cfg, True)
    layers = [quick_block] if quick and quick_block is not None else []
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} is not of the form key=value")
    if overrides:
        layers.append(OmegaConf.from_dotlist(list(overrides)))
    try:
        for layer in layers:
            cfg = OmegaConf.merge(cfg, layer)
    except Exception as err:  # omegaconf raises its own key errors
        raise ValueError(f"bad config override for {path}: {err}") from err
    return cfg


def to_plain(cfg: DictConfig) -> dict[str, Any]:
    """The config as a plain dict (what a checkpoint stores)."""
    return OmegaConf.to_container(cfg, resolve=True)
