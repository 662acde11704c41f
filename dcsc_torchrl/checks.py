"""The checks every module runs on what enters it, so all of them report bad input the same way.

:func:`check_in_range` and :func:`check_finite` refuse a parameter out of its range or a
non-finite value with a :class:`ValueError` that names it; :func:`check_values` is the check
the per-frame modules run on every frame: one reduction per tensor, and on a device no host
sync (the verdict is deferred, :func:`defer_check`, and read by :func:`flush_frame_checks`).
"""

from __future__ import annotations

import math
from collections import deque
from numbers import Real

import torch
from torch import Tensor

__all__ = ["check_finite", "check_in_range", "check_values", "defer_check", "flush_frame_checks"]

TensorLike = Tensor | float


def check_in_range(
    name: str,
    value: TensorLike,
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> TensorLike:
    """Raise a :class:`ValueError` naming ``name`` unless ``value`` lies in the interval.

    ``low`` / ``high`` of ``None`` leave that side open (unbounded). NaN is never in range.
    ``value`` may be a Python number or a tensor (every element is checked).

    Args:
        name: the parameter's name, used in the message.
        value: the value to check.
        low: lower bound, or ``None``.
        high: upper bound, or ``None``.
        low_inclusive: whether ``value == low`` is allowed.
        high_inclusive: whether ``value == high`` is allowed.

    Returns:
        ``value`` unchanged, so a constructor can write ``self.p = check_in_range("p", p, 0, 1,
        high_inclusive=False)``.

    Raises:
        ValueError: if ``value`` (or any element of it) is outside the interval or NaN.

    Examples:
        >>> check_in_range("eta", 0.6, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
        0.6
        >>> check_in_range("eta", 1.0, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
        Traceback (most recent call last):
        ...
        ValueError: eta must be in (0.0, 1.0), got 1.0
    """
    lo_br = "[" if low_inclusive else "("
    hi_br = "]" if high_inclusive else ")"
    interval = f"{lo_br}{'-inf' if low is None else low}, {'inf' if high is None else high}{hi_br}"
    if isinstance(value, Tensor):
        v = value.detach()
        ok = ~torch.isnan(v)
        if low is not None:
            ok &= (v >= low) if low_inclusive else (v > low)
        if high is not None:
            ok &= (v <= high) if high_inclusive else (v < high)
        if not bool(ok.all()):
            bad = v[~ok].flatten()[0].item()
            n_bad = int((~ok).sum())
            raise ValueError(
                f"{name} must be in {interval}, got {bad}"
                + (f" ({n_bad} of {v.numel()} elements out of range)" if v.numel() > 1 else "")
            )
        return value
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ValueError(f"{name} must be a real number in {interval}, got {value!r}")
    v = float(value)
    ok = not math.isnan(v)
    if ok and low is not None:
        ok = v >= low if low_inclusive else v > low
    if ok and high is not None:
        ok = v <= high if high_inclusive else v < high
    if not ok:
        raise ValueError(f"{name} must be in {interval}, got {value}")
    return value


def check_finite(name: str, tensor: Tensor) -> Tensor:
    """Raise a :class:`ValueError` naming ``name`` if ``tensor`` holds NaN or +/-inf.

    Args:
        name: what the tensor is (a TensorDict key such as ``"observation"``).
        tensor: the values to check.

    Returns:
        ``tensor`` unchanged.

    Raises:
        ValueError: naming ``name``, the number of non-finite entries and the first one.

    Examples:
        >>> check_finite("observation", torch.zeros(3)).shape
        torch.Size([3])
        >>> check_finite("machine_confidence", torch.tensor([0.5, float("nan")]))
        Traceback (most recent call last):
        ...
        ValueError: machine_confidence has 1 non-finite value(s) of 2: nan at index (1,)
    """
    if not isinstance(tensor, Tensor):
        tensor = torch.as_tensor(tensor)
    if not tensor.is_floating_point() and not tensor.is_complex():
        return tensor
    finite = torch.isfinite(tensor.detach())
    if not bool(finite.all()):
        bad = (~finite).nonzero()[0]
        index = tuple(int(i) for i in bad)
        raise ValueError(
            f"{name} has {int((~finite).sum())} non-finite value(s) of {tensor.numel()}: "
            f"{tensor.detach()[index].item()} at index {index}"
        )
    return tensor


def _interval(low: float | None, high: float | None) -> str:
    return f"[{'-inf' if low is None else low}, {'inf' if high is None else high}]"


def check_values(name: str, tensor: Tensor, low: float | None = None, high: float | None = None) -> Tensor:
    """The every-frame check: ``tensor`` finite and, where given, in ``[low, high]``.

    It costs one reduction, ``torch.aminmax`` (NaN and +/-inf reach its ends), whatever
    the tensor's size. Where it is read decides when a bad frame is refused:

    - on the host (CPU), the two ends are read at once (no device to wait for): a bad
      frame raises here, with :func:`check_in_range` / :func:`check_finite`'s message
      (the first bad index and value);
    - on a device (CUDA), the verdict ``low <= min and max <= high`` is computed there and
      handed to :func:`defer_check`, which copies it to pinned host memory without
      blocking and reads it on a later call, once the copy has landed: no per-frame host
      sync, and the :class:`ValueError` (naming ``name``) comes a few frames late, or at
      :func:`flush_frame_checks`. (``torch._assert_async`` would not sync either, but a
      failed device assert carries no message and leaves the CUDA context unusable.)

    Integer tensors are checked against the range only; bool and empty tensors pass.

    Args:
        name: what the tensor is (a TensorDict key such as ``"observation"``).
        tensor: the values to check.
        low: lower bound (inclusive), or ``None``.
        high: upper bound (inclusive), or ``None``.

    Returns:
        ``tensor`` unchanged.

    Raises:
        ValueError: naming ``name``, for a NaN, an inf or a value out of range.

    Examples:
        >>> check_values("human_confidence", torch.tensor([[0.2], [1.0]]), 0.0, 1.0).shape
        torch.Size([2, 1])
        >>> check_values("human_rt", torch.tensor([0.3, float("inf")]), 0.0)
        Traceback (most recent call last):
        ...
        ValueError: human_rt has 1 non-finite value(s) of 2: inf at index (1,)
    """
    bounded = low is not None or high is not None
    if (not tensor.is_floating_point() and (tensor.dtype == torch.bool or not bounded)) or not tensor.numel():
        return tensor
    values = tensor.detach()
    lo, hi = torch.aminmax(values)
    if values.is_cpu:
        lo_value, hi_value = lo.item(), hi.item()  # NaN fails every comparison below
        if not (-math.inf < lo_value and hi_value < math.inf and (low is None or lo_value >= low)
                and (high is None or hi_value <= high)):
            if bounded:
                check_in_range(name, values, low, high)
            check_finite(name, values)
        return tensor
    largest = torch.finfo(values.dtype).max if values.is_floating_point() else math.inf
    floor = -largest if low is None else max(low, -largest)
    ceiling = largest if high is None else min(high, largest)
    requirement = f"in {_interval(low, high)}" if bounded else "finite"
    defer_check(f"{name} must be {requirement}: a frame on {values.device} was not (read back without a sync, "
                "a few frames after it)", (lo >= floor) & (hi <= ceiling))
    return tensor


class _DeferredChecks:
    """Verdicts of device checks on their way to the host: (message, pinned verdict, event), oldest first."""

    def __init__(self) -> None:
        self.pending: deque[tuple[str, Tensor, torch.Event]] = deque()

    def add(self, message: str, ok: Tensor) -> None:
        self.read(wait=False)
        verdict = torch.empty((), dtype=torch.bool, pin_memory=True)
        verdict.copy_(ok, non_blocking=True)
        event = torch.Event(ok.device)
        event.record()
        self.pending.append((message, verdict, event))

    def read(self, *, wait: bool) -> None:
        while self.pending:
            message, verdict, event = self.pending[0]
            if wait:
                event.synchronize()
            elif not event.query():  # not landed yet: no waiting
                return
            self.pending.popleft()
            if not bool(verdict):
                self.pending.clear()
                raise ValueError(message)


_DEFERRED = _DeferredChecks()


def defer_check(message: str, ok: Tensor) -> None:
    """Refuses a device frame later, without a sync: ``ValueError(message)`` once ``ok`` reads False.

    ``ok`` (a 0-dim bool tensor on a device, computed there) is copied to pinned host
    memory with ``non_blocking=True`` and an event is recorded behind the copy. Every call
    (and :func:`flush_frame_checks`) first reads the verdicts whose event has completed
    (``Event.query()``, which never waits), oldest first, and raises for the first False.

    Args:
        message: the one-line message of the :class:`ValueError`, naming the key.
        ok: True where the frame passed.

    Raises:
        ValueError: for an earlier verdict that has landed False.
    """
    _DEFERRED.add(message, ok)


def flush_frame_checks() -> None:
    """Waits for every pending device verdict of :func:`defer_check` and raises for the first False.

    One sync: call it once per batch (the losses do, before learning from a batch) or at
    the end of a run, so that a bad frame on a device is not left unread. A no-op on the host.

    Raises:
        ValueError: the message of the first failed check.
    """
    _DEFERRED.read(wait=True)

