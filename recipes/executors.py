"""Which executor runs a grid's cells: one after another here, or Ray tasks on a local instance.

One home for the choice ``dcsc run``, ``dcsc reproduce`` and ``dcsc map`` share through their
``--workers``. It sits above the grid driver (:mod:`dcsc_torchrl.recipes.grid`, the local
executor) and the sweep (:mod:`dcsc_torchrl.recipes.sweep`, Ray's), so neither imports the
other's way back, and Ray loads only when more than one worker is asked for.
"""

from __future__ import annotations

from dcsc_torchrl.recipes.grid import Executor, local_executor


def executor(workers: int) -> Executor:
    """``workers`` cells at a time: Ray tasks on a local instance, or (1) this process in turn."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        return local_executor
    from dcsc_torchrl.recipes.sweep import ray_executor  # Ray loads only here

    return ray_executor(retries=2, address=None, workers=workers)
