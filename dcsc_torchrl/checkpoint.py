"""Checkpoints that are safe to share: atomic writes, no code on load, task and shape checks.

A checkpoint is a plain dict of tensors, numbers, strings and lists, written with
``torch.save`` to a temporary file in the same directory and renamed over the target
(``os.replace`` is atomic on POSIX), so a run killed while writing leaves the previous
checkpoint intact. It is read back with ``torch.load(..., weights_only=True)``: loading a
checkpoint someone sent you does not run their code. A file that cannot be read (empty,
truncated, not a checkpoint, or holding objects other than plain data) is refused with one
line naming it (:class:`CheckpointError`).

Every command reads a pretraining seed's machine from one place,
:func:`checkpoint_path` (``<pretrain.out_dir>/seed<s>/checkpoint.pt``). Checkpoints are
written readable by the group (the umask's mode, not ``mkstemp``'s private 0600), and the
temporary files of a writer that was killed are removed at the next save.

This module imports torch only when a checkpoint is written or read.
"""

from __future__ import annotations

import os
import random
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dcsc_torchrl.config import UsageError

if TYPE_CHECKING:
    import torch
    from torch import nn

FORMAT_VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"


class CheckpointError(UsageError):
    """A checkpoint file that cannot be used: corrupt, truncated, of another task or not ours."""


def checkpoint_path(out_dir: str | os.PathLike, seed: int) -> Path:
    """Where pretraining seed ``seed``'s checkpoint lives: ``<out_dir>/seed<seed>/checkpoint.pt``.

    The one layout every command reads and writes (``dcsc pretrain``, ``dcsc run``,
    ``dcsc sweep``, ``dcsc play``); ``out_dir`` is a config's ``pretrain.out_dir``,
    relative to the current folder unless absolute.

    Examples:
        >>> checkpoint_path("runs/pretrain_lunarlander", 2).as_posix()
        'runs/pretrain_lunarlander/seed2/checkpoint.pt'
    """
    return Path(out_dir) / f"seed{int(seed)}" / CHECKPOINT_NAME


def stale_temp_files(path: str | os.PathLike) -> list[Path]:
    """The temporary files a killed :func:`save_checkpoint` of ``path`` left behind."""
    path = Path(path)
    return sorted(path.parent.glob(f".{path.name}.*.tmp")) if path.parent.is_dir() else []


def remove_stale_temp_files(path: str | os.PathLike) -> int:
    """Removes :func:`stale_temp_files` of ``path``; returns how many there were."""
    stale = stale_temp_files(path)
    for tmp in stale:
        tmp.unlink(missing_ok=True)
    return len(stale)


def _shared_mode() -> int:
    """The mode an ordinary new file gets (0644 under the usual umask 022)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def rng_state() -> dict[str, Any]:
    """The global RNG states of Python, NumPy and torch, as tensors and plain values."""
    import numpy as np
    import torch

    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": pos,
                  "has_gauss": has_gauss, "cached_gaussian": cached},
        "python": [list(s) if isinstance(s, tuple) else s for s in random.getstate()],
    }


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restores the RNG states written by :func:`rng_state`."""
    import numpy as np
    import torch

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
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temp_files(path)
    data = {"format_version": FORMAT_VERSION, "task": task, **payload}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(data, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _shared_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


_REMEDY = "a run's own file: delete it and run its command again (a pretraining run pretrains it); else name another file"
"""What to do with a checkpoint that cannot be read: it may be a run's (a machine, a copilot, an arbiter) or a
file the user named by mistake, which deleting would not mend."""


def load_checkpoint(path: str | os.PathLike, *, task: str | None, modules: Sequence[str] = ()) -> dict[str, Any]:
    """Reads a checkpoint with ``weights_only=True`` and checks it is one of ``task``, of this format.

    Args:
        path: the checkpoint file.
        task: the task it must belong to (``None``: any; the caller reads ``data["task"]``).
        modules: for a pretrained machine, the state dicts it is rebuilt from
            (:attr:`Task.checkpoint_modules <dcsc_torchrl.task.Task.checkpoint_modules>`):
            also require them and the network settings ``config.network``.

    Raises:
        FileNotFoundError: no file at ``path``.
        CheckpointError: the file is empty, truncated or corrupt, holds objects other than
            tensors and plain data, is not a dcsc checkpoint, is of another format version (an
            older or newer dcsc-torchrl), lacks an entry this version reads, or belongs to another task.
    """
    import pickle

    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    if path.stat().st_size == 0:
        raise CheckpointError(f"checkpoint {path} is empty (its writer was stopped?): {_REMEDY}")
    try:
        data = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        if "Unsupported global" in str(err) or "GLOBAL" in str(err):
            raise CheckpointError(f"checkpoint {path} holds objects other than tensors and plain data; "
                                  "refusing to load it (a dcsc checkpoint never does)") from None
        raise CheckpointError(f"checkpoint {path} is corrupt or truncated, or not a checkpoint: {_REMEDY}") from None
    except (EOFError, RuntimeError, KeyError, ValueError, OSError, IndexError) as err:
        raise CheckpointError(f"checkpoint {path} is corrupt or truncated, or not a checkpoint "
                              f"({type(err).__name__}): {_REMEDY}") from None
    if not isinstance(data, dict) or "task" not in data:
        raise CheckpointError(f"{path} is not a dcsc-torchrl checkpoint")
    version = data.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} is of format version {version}, this dcsc-torchrl reads version "
                              f"{FORMAT_VERSION}: pretrain it again (delete it), or use the version that wrote it")
    if task is not None and data["task"] != task:
        raise CheckpointError(
            f"checkpoint {path} was written for task {data['task']!r}, but this run is for task {task!r}"
        )
    if modules:
        _check_machine_entries(data, path, modules)
    return data


def _check_machine_entries(data: Mapping[str, Any], path: Path, modules: Sequence[str]) -> None:
    """Refuses a checkpoint without what a pretrained machine is rebuilt from: ``config.network``
    and the state dicts ``modules`` (each a group of keys)."""

    def has(entry: str) -> bool:
        tree: Any = data
        for key in entry.split("."):
            tree = tree.get(key) if isinstance(tree, Mapping) else None
        return isinstance(tree, Mapping)

    entries = ["config.network", *(f"state.{name}" for name in modules)]
    missing = [entry for entry in entries if not has(entry)]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {', '.join(missing)} (written by another version of "
                              "dcsc-torchrl?): pretrain it again (delete it)")


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
        raise CheckpointError(f"checkpoint's {name} does not fit this network: " + "; ".join(problems[:5]))
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
