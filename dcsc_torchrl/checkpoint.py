"""Checkpoints that are safe to share: atomic writes, no code on load, task and shape checks.

A checkpoint is a plain dict of tensors, numbers, strings and lists, written with
``torch.save`` to a temporary file in the same directory and renamed over the target
(``os.replace`` is atomic on POSIX), so a run killed while writing leaves the previous
checkpoint intact. It is read back with ``torch.load(..., weights_only=True)``: loading a
checkpoint someone sent you does not run their code (DESIGN §6).
"""

from __future__ import annotations

import os
import random
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

FORMAT_VERSION = 1


def rng_state() -> dict[str, Any]:
    """The global RNG states of Python, NumPy and torch, as tensors and plain values."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": pos,
                  "has_gauss": has_gauss, "cached_gaussian": cached},
        "python": [list(s) if isinstance(s, tuple) else s for s in random.getstate()],
    }


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restores the RNG states written by :func:`rng_state`."""
    torch.set_rng_state(state["torch"])
    np_state = state["numpy"]
    np.random.set_state(
        (np_state["kind"], np_state["keys"].numpy().astype(np.uint32), np_state["pos"],
         np_state["has_gauss"], np_state["cached_gaussian"])
    )
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


def save_checkpoint(path: str | os.PathLike, *, task: str, payload: Mapping[str, Any]) -> Path:
    """Writes ``payload`` (+ ``task``, format version) atomically to ``path``.

    Args:
        path: the checkpoint file.
        task: the task the checkpoint belongs to (``"lunarlander"`` or ``"uav"``); a
            recipe of another task refuses to load it.
        payload: state dicts, counters, RNG states and the config as plain data.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"format_version": FORMAT_VERSION, "task": task, **payload}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(data, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike, *, task: str) -> dict[str, Any]:
    """Reads a checkpoint with ``weights_only=True`` and checks it is one of ``task``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a dcsc checkpoint, or belongs to another task.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    data = torch.load(path, weights_only=True, map_location="cpu")
    if not isinstance(data, dict) or "task" not in data:
        raise ValueError(f"{path} is not a dcsc-torchrl checkpoint")
    if data["task"] != task:
        raise ValueError(
            f"checkpoint {path} was written for task {data['task']!r}, but this run is for task {task!r}"
        )
    return data


def load_module_state(module: nn.Module, state: Mapping[str, torch.Tensor], *, name: str) -> None:
    """``module.load_state_dict(state)`` with a clear error on missing keys or shape mismatch."""
    own = module.state_dict()
    problems = [f"missing {k}" for k in own if k not in state]
    problems += [f"unexpected {k}" for k in state if k not in own]
    problems += [
        f"{k}: checkpoint {tuple(state[k].shape)} vs network {tuple(v.shape)}"
        for k, v in own.items()
        if k in state and state[k].shape != v.shape
    ]
    if problems:
        raise ValueError(f"checkpoint's {name} does not fit this network: " + "; ".join(problems[:5]))
    module.load_state_dict(state)


def _first_rows(tree: Mapping[str, Any], n: int) -> dict[str, Any]:
    return {k: _first_rows(v, n) if isinstance(v, Mapping) else v[:n].clone() for k, v in tree.items()}


def replay_buffer_state(buffer: Any) -> dict[str, Any]:
    """A TorchRL ``ReplayBuffer``'s state with only its filled rows.

    ``LazyTensorStorage`` preallocates its whole capacity (1e6 transitions for Table A2's
    DDPG), which its ``state_dict`` would write to every checkpoint; the rows past
    ``len(buffer)`` are empty and are left out.
    """
    state = buffer.state_dict()
    storage = state["_storage"]
    if storage.get("initialized", False):
        storage["_storage"] = _first_rows(storage["_storage"], storage["_len"])
    return state


def load_replay_buffer_state(buffer: Any, state: Mapping[str, Any]) -> None:
    """Restores a state written by :func:`replay_buffer_state` into ``buffer``."""
    from tensordict import TensorDict

    storage = state["_storage"]
    if not storage.get("initialized", False):
        buffer.load_state_dict(state)
        return
    n = storage["_len"]
    buffer.empty()
    # the storage's state dict flattens nested keys as "next.reward"
    buffer.extend(TensorDict(storage["_storage"], batch_size=[n]).unflatten_keys("."))
    full = buffer.state_dict()
    full.update({key: value for key, value in state.items() if key != "_storage"})
    buffer.load_state_dict(full)
