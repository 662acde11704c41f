"""The confidence math of DC-SC: Eq. 6 (knowledge), Eqs. 7-9 (human confidence), Eq. 10
(MC-dropout uncertainty) and Eqs. 11-13 (machine confidence).

Every function here is a pure torch function: it takes tensors of any batch shape, keeps the
input's floating dtype (float32 or float64), never returns NaN for finite inputs in its
domain, and validates its scalar parameters with a :class:`ValueError` that names the bad
parameter and its value. :func:`check_in_range` and :func:`check_finite` are the two
validation helpers the rest of the library imports, so every module reports bad input the
same way; :func:`check_values` is the check the per-frame modules run on every frame (one
reduction, and no device sync: see there).

The two confidence integrals have no elementary closed form. Both are integrals of the
form ``∫_0^∞ e^{-u} h(u / y) du`` (see ``docs/math.md`` for the derivations); they are
evaluated with the trapezoidal rule in ``s = ln u``, on a lattice anchored to ``ln y`` so
that the kernel ``h`` is tabulated once per call and every element costs one ``exp`` per
node. The rule converges geometrically (the integrand is analytic in a strip around the
real axis); with the node spacing used here the error against a 30-digit reference is
below 1e-9 in float64 (``tests/test_confidence.py`` checks 1e-6).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from numbers import Real

import torch
from torch import Tensor

__all__ = [
    "check_finite",
    "check_in_range",
    "check_values",
    "defer_check",
    "flush_frame_checks",
    "human_confidence",
    "knowledge_update",
    "machine_confidence",
    "mc_dropout_uncertainty",
]

TensorLike = Tensor | float

# The quadrature: trapezoidal rule in s = ln u over [_S_LO, _S_HI].
# Below _S_LO the weight e^{s - e^s} ~ e^s integrates to e^{_S_LO} ~ 1e-10 (dropped);
# above _S_HI it is below e^{3.6 - e^{3.6}} ~ 5e-15.
_S_LO = -23.0
_S_HI = 3.6
# Node spacing. The weight e^{s - e^s} is analytic for |Im s| < pi/2, so the rule's error is
# ~exp(-pi^2 / h) ~ 2e-11 at h = 0.4. The machine kernel 1 / (1 + e^{delta2 t}) has poles at
# Im t = pi / delta2, so for delta2 > 2 the spacing shrinks to 0.8 / delta2.
_H = 0.4
# Elements per block: keeps the [block, nodes] work array inside the CPU cache.
_BLOCK = 2048
# Range of ln(a k) / ln(a c) whose kernel tables are cached (others are built per call), and
# the largest table (entries) built at once.
_M_CACHED = (-60.0, 40.0)
# Range of ln(a k) / ln(a c) over every finite positive input (ln of the dtype's smallest
# subnormal / largest value, plus ln a for a = -ln(eta) in [1.1e-16, 745]). Off the host, the
# table covers it all, so no element's row has to be read back (a device sync) to pick it.
_M_FULL = {torch.float64: (-783.0, 718.0), torch.float32: (-141.0, 96.0)}
_MAX_TABLE = 2_000_000
# Above this delta2 the machine integral is split at the kernel's step (``_steep_machine``):
# the lattice's cost grows like delta2 (spacing 0.8 / delta2), the split rule's does not.
_STEEP_DELTA = 3.0
# The split rule: its window is |delta2 * ln(u / y)| <= _T_STEEP (outside it the kernel is
# e^{-delta2 |t|} to a relative 1e-16), covered by two Gauss-Legendre panels of _N_STEEP nodes.
_T_STEEP = 37.0
_N_STEEP = 40


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------


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


def _check_mode(mode: str) -> None:
    if mode not in ("decay", "paper"):
        raise ValueError(f"mode must be 'decay' or 'paper', got {mode!r}")


def _as_float_tensor(name: str, value: TensorLike) -> Tensor:
    t = torch.as_tensor(value)
    if not t.is_floating_point():
        if t.is_complex():
            raise ValueError(f"{name} must be real, got dtype {t.dtype}")
        t = t.to(torch.get_default_dtype())
    return t


def _check_nonnegative_finite(name: str, t: Tensor) -> None:
    if not bool(((t >= 0) & torch.isfinite(t)).all()):  # one reduction on the usual path
        check_finite(name, t)
        check_in_range(name, t, 0.0, None)


# --------------------------------------------------------------------------------------
# the quadrature
# --------------------------------------------------------------------------------------


def _log_kernel(kind: str, t: Tensor, delta: float) -> Tensor:
    """ln of the kernel ``h(u / y)`` at ``t = ln(u / y)``."""
    zero = torch.zeros_like(t)
    if kind == "human":  # (1 + u/x)^-delta1
        return -delta * torch.logaddexp(t, zero)
    if kind == "accept":  # 1 / (1 + (u/y)^delta2)
        return -torch.logaddexp(delta * t, zero)
    return -torch.logaddexp(-delta * t, zero)  # "reject": 1 / (1 + (y/u)^delta2)


def _n_nodes(h: float) -> int:
    return math.ceil((_S_HI - _S_LO) / h) + 2


def _build_node_rows(
    kinds: tuple[str, ...],
    delta: float,
    h: float,
    lo: int,
    n_rows: int,
    dtype: torch.dtype,
    device: torch.device,
) -> Tensor:
    """``rows[r, j] = ln kernel(h (lo + r + j)) + h j`` for each kind, stacked along ``r``.

    Row ``r`` holds the kernel part of the node exponents of every element whose first node
    has lattice index ``i0 = lo + r`` (the integrand is ``exp(s - e^s) * kernel`` with
    ``s = a0 + h j``, and ``a0`` is added per element).
    """
    n_nodes = _n_nodes(h)
    lattice = h * torch.arange(lo, lo + n_rows + n_nodes - 1, dtype=torch.float64, device=device)
    hj = h * torch.arange(n_nodes, dtype=torch.float64, device=device)
    rows = [_log_kernel(kind, lattice, delta).unfold(0, n_nodes, 1) + hj for kind in kinds]
    return torch.cat(rows).to(dtype).contiguous()


_cached_node_rows = functools.lru_cache(maxsize=64)(_build_node_rows)


def _lattice_trapezoid(
    m: Tensor, kinds: tuple[str, ...], delta: float, h: float, which: Tensor | None = None
) -> Tensor:
    """``∫_R exp(s - e^s) * kernel(s - m) ds`` for every element of the 1-D tensor ``m``.

    Trapezoidal rule with spacing ``h`` on the nodes ``s_j = m + h (i0 + j)``, where the
    integer ``i0`` puts the first node in ``[_S_LO - h, _S_LO)``. The kernel is then only
    needed on the lattice ``t = h * i``: it is tabulated once (cached for the usual range of
    ``m``), each element selects its row, and costs one ``exp`` per node. As a function of
    ``m`` (``i0`` fixed) the sum is the trapezoidal rule of the integral, so autograd's
    derivative is the rule applied to the derivative of the integrand. ``which`` (0/1 per
    element) picks ``kinds[0]`` or ``kinds[1]`` as the kernel.
    """
    if m.numel() == 0:
        return m.new_zeros(0)
    dtype, device = m.dtype, m.device
    n_nodes = _n_nodes(h)
    i0 = torch.floor((_S_LO - m.detach()) / h)
    i0_long = i0.to(torch.long)
    full_lo = math.floor((_S_LO - _M_FULL[dtype][1]) / h)
    full_rows = math.floor((_S_LO - _M_FULL[dtype][0]) / h) - full_lo + 1
    if _sync_free(device) and full_rows * n_nodes * len(kinds) <= _MAX_TABLE:
        rows = _cached_node_rows(kinds, delta, h, full_lo, full_rows, dtype, device)
        return _sum_rows(rows, m, i0, i0_long - full_lo, full_rows, which, h, n_nodes)
    lo, hi = (int(v) for v in torch.stack(torch.aminmax(i0_long)).tolist())
    std_lo = math.floor((_S_LO - _M_CACHED[1]) / h)
    std_hi = math.floor((_S_LO - _M_CACHED[0]) / h)
    std_size = (std_hi - std_lo + 1) * n_nodes * len(kinds)
    if std_lo <= lo and hi <= std_hi and std_size <= _MAX_TABLE:  # usual case: cached table
        lo, n_rows = std_lo, std_hi - std_lo + 1
        rows = _cached_node_rows(kinds, delta, h, lo, n_rows, dtype, device)
    else:
        n_rows = hi - lo + 1
        if n_rows * n_nodes * len(kinds) > _MAX_TABLE and hi > lo:
            # a batch spanning a huge range of m with a fine lattice: split it by range
            low_half = i0_long <= (lo + hi) // 2
            out = torch.zeros_like(m)
            for part in (low_half, ~low_half):
                idx = part.nonzero().squeeze(-1)
                sub_which = None if which is None else which[idx]
                out = out.index_put((idx,), _lattice_trapezoid(m[idx], kinds, delta, h, sub_which))
            return out
        rows = _build_node_rows(kinds, delta, h, lo, n_rows, dtype, device)
    return _sum_rows(rows, m, i0, i0_long - lo, n_rows, which, h, n_nodes)


def _sync_free(device: torch.device) -> bool:
    """Whether the lattice uses the full-range table (no read-back): off the host."""
    return device.type != "cpu"


def _sum_rows(
    rows: Tensor, m: Tensor, i0: Tensor, offset: Tensor, n_rows: int, which: Tensor | None, h: float,
    n_nodes: int,
) -> Tensor:
    """The trapezoidal sums of :func:`_lattice_trapezoid` once its table ``rows`` is chosen."""
    growth = _growth(h, m.dtype, m.device)
    a0 = m + h * i0  # s of the first node, in [_S_LO - h, _S_LO); carries m's gradient
    if which is not None:
        offset = offset + n_rows * which
    block = max(16, _BLOCK * _n_nodes(_H) // n_nodes)  # same work array for finer lattices
    if a0.numel() <= block:
        return h * _node_sum(rows, a0, offset, growth)
    parts = zip(a0.split(block), offset.split(block), strict=True)
    return h * torch.cat([_node_sum(rows, a0_b, off_b, growth) for a0_b, off_b in parts])


def _node_sum(rows: Tensor, a0: Tensor, offset: Tensor, growth: Tensor) -> Tensor:
    """``Σ_j exp(rows[offset, j] + a0 - e^{a0} e^{h j})``: the integrand at the nodes, summed."""
    expo = rows.index_select(0, offset).add_(a0.unsqueeze(-1))
    return expo.addcmul_(torch.exp(a0).unsqueeze(-1), growth, value=-1.0).exp_().sum(-1)


@functools.lru_cache(maxsize=64)
def _growth(h: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``e^{h j}`` for the node index ``j``."""
    return torch.exp(h * torch.arange(_n_nodes(h), dtype=torch.float64, device=device)).to(dtype)


def _compute_dtype(t: Tensor) -> torch.dtype:
    # float64 inputs stay float64; float32/float16/bfloat16 are computed in float32.
    return torch.float64 if t.dtype == torch.float64 else torch.float32


# --------------------------------------------------------------------------------------
# Eq. 6
# --------------------------------------------------------------------------------------


def knowledge_update(
    k: TensorLike,
    rt: TensorLike,
    K: float,
    t_d: float,
    mode: str = "decay",
    k_floor: float = 1e-3,
    cap: str = "min",
) -> Tensor:
    """Eq. 6: the human's knowledge level after one decision with response time ``rt``.

    Applied once per human *decision* (not every frame)::

        RT <= t_d   ->  min((1 + exp(-RT)) k, K)
        RT >  t_d   ->  mode "decay": k exp(-(RT - t_d))
                        mode "paper": clamp((1 - exp(RT - t_d)) k, k_floor, K)

    Case 1 of Eq. 6 (``k >= K -> K``) is read as a cap (``cap="min"``, the default):
    ``k_{t+1} = min(K, case 2 or 3)``, so a response slower than ``t_d`` still lowers the
    knowledge once it has reached ``K`` (the paper's text: past ``t_d`` "normal learning
    cannot take place, leading to a decrease in the amount of knowledge retained"; its
    Figs. 3a and 6a show b_h falling late in a task). ``cap="absorbing"`` is the strict
    reading, in which ``k = K`` never changes again.

    Case 3 as printed in the paper, ``(1 - exp(RT - t_d)) k``, is negative for every
    ``RT > t_d``; mode ``"paper"`` keeps the printed factor and clamps it, so a late response
    resets the knowledge to ``k_floor``. Mode ``"decay"`` (the default) forgets smoothly: the
    later the response, the more knowledge is lost (``docs/math.md``).

    Args:
        k: current knowledge, ``>= 0`` and finite, any shape.
        rt: response time of the decision in seconds, ``>= 0`` and finite; broadcasts with
            ``k``.
        K: task difficulty, the knowledge cap (``> 0``).
        t_d: upper limit of a normal response time in seconds (``> 0``).
        mode: ``"decay"`` or ``"paper"`` (see above).
        k_floor: lower clamp of mode ``"paper"``, in ``(0, K]``; unused by ``"decay"``.
        cap: ``"min"`` (case 1 caps k at K) or ``"absorbing"`` (k = K stays K).

    Returns:
        The new knowledge, in ``[0, K]``, with the broadcast shape of ``k`` and ``rt`` and
        their promoted floating dtype.

    Raises:
        ValueError: for a negative or non-finite ``k`` or ``rt``, or a parameter out of range.

    Examples:
        >>> k = torch.tensor([0.1, 0.1, 0.1, 30.0])
        >>> rt = torch.tensor([0.5, 1.5, 0.0, 0.5])
        >>> knowledge_update(k, rt, K=20.0, t_d=1.0)
        tensor([ 0.1607,  0.0607,  0.2000, 20.0000])
        >>> knowledge_update(k, rt, K=20.0, t_d=1.0, mode="paper")
        tensor([1.6065e-01, 1.0000e-03, 2.0000e-01, 2.0000e+01])
        >>> knowledge_update(torch.tensor([20.0, 20.0]), torch.tensor([1.5, 1.5]), K=20.0, t_d=1.0)
        tensor([12.1306, 12.1306])
        >>> knowledge_update(torch.tensor([20.0]), torch.tensor([1.5]), K=20.0, t_d=1.0, cap="absorbing")
        tensor([20.])
    """
    check_in_range("K", K, 0.0, math.inf, low_inclusive=False, high_inclusive=False)
    check_in_range("t_d", t_d, 0.0, None, low_inclusive=False)
    _check_mode(mode)
    if cap not in ("min", "absorbing"):
        raise ValueError(f"cap must be 'min' or 'absorbing', got {cap!r}")
    if mode == "paper":
        check_in_range("k_floor", k_floor, 0.0, float(K), low_inclusive=False)
    k_t = _as_float_tensor("k", k)
    rt_t = _as_float_tensor("rt", rt)
    _check_nonnegative_finite("k", k_t)
    _check_nonnegative_finite("rt", rt_t)
    dtype = torch.promote_types(k_t.dtype, rt_t.dtype)
    k_t, rt_t = k_t.to(dtype), rt_t.to(dtype)
    K_f = float(K)
    grown = torch.clamp((1.0 + torch.exp(-rt_t)) * k_t, max=K_f)
    late_by = rt_t - t_d
    if mode == "decay":
        late = k_t * torch.exp(-late_by)
    else:
        # capped exponent: the product is negative (clamped to k_floor) either way, and the cap
        # keeps 0 * (1 - e^big) finite.
        factor = -torch.expm1(torch.clamp(late_by, max=80.0))
        late = torch.clamp(factor * k_t, min=float(k_floor), max=K_f)
    new_k = torch.clamp(torch.where(rt_t <= t_d, grown, late), max=K_f)
    if cap == "absorbing":
        new_k = torch.where(k_t >= K_f, torch.full_like(new_k, K_f), new_k)
    return new_k


# --------------------------------------------------------------------------------------
# Eqs. 7-9
# --------------------------------------------------------------------------------------


def _check_human_params(p: float, eta: float, delta1: float) -> None:
    check_in_range("p", p, 0.0, 1.0, high_inclusive=False)
    check_in_range("eta", eta, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
    check_in_range("delta1", delta1, 0.0, math.inf, low_inclusive=False, high_inclusive=False)


def human_confidence(k: TensorLike, p: float, eta: float, delta1: float) -> Tensor:
    """Eq. 9 (with the prior of Eq. 7 and the payoff of Eq. 8): human confidence ``b_h(k)``.

    ``b_h(k) = ∫_{K>k} (k/K)^delta1 dmu(K) / ∫_{K>k} dmu(K)`` where ``mu`` puts mass ``p`` on
    ``K = inf`` (payoff 0) and density ``(1-p) eta^K ln(1/eta)`` on ``K > 0``. Substituting
    ``K = k + u / a`` with ``a = ln(1/eta)`` and ``x = a k`` gives (docs/math.md, section 2)::

        b_h = J(x) * (1-p) e^-x / ((1-p) e^-x + p),   J(x) = ∫_0^∞ e^-u (1 + u/x)^-delta1 du
            = (1-p) x E_delta1(x) / ((1-p) e^-x + p)

    ``b_h(0) = 0``; for ``p > 0`` it rises, peaks and falls to 0 (Properties 1-2). With
    ``p = 0`` it rises to 1 instead (Property 1 needs ``p > 0``).

    Args:
        k: knowledge level, ``>= 0`` and finite, any shape.
        p: probability that the task is impossible (``K = inf``), in ``[0, 1)``.
        eta: base of the exponential prior over task difficulty, in ``(0, 1)``.
        delta1: exponent of the marginal payoff ``(k/K)^delta1``, ``> 0``.

    Returns:
        ``b_h`` in ``[0, 1]``, same shape and floating dtype as ``k``; differentiable w.r.t.
        ``k`` (the gradient reported at ``k = 0`` is 0).

    Raises:
        ValueError: for a parameter out of range or a negative / non-finite ``k``.

    Examples:
        >>> human_confidence(torch.tensor([0.0, 0.5, 3.0, 30.0]), p=0.1, eta=0.6, delta1=2.0)
        tensor([0.0000e+00, 1.4768e-01, 3.2761e-01, 1.7707e-06])
    """
    _check_human_params(p, eta, delta1)
    k_t = _as_float_tensor("k", k)
    _check_nonnegative_finite("k", k_t)
    out_dtype = k_t.dtype
    a = -math.log(eta)  # not log(1 / eta): 1 / eta overflows for a subnormal eta
    k_c = k_t.to(_compute_dtype(k_t)).reshape(-1)
    x = k_c * a  # may overflow to inf (huge k, tiny eta): the sigmoid below takes it
    positive = k_c > 0
    # ln x as ln k + ln a: finite for every finite k > 0 and eta in (0, 1)
    m = torch.log(torch.where(positive, k_c, torch.ones_like(k_c))) + math.log(a)
    j = _lattice_trapezoid(m, ("human",), float(delta1), _H)
    # (1-p) e^-x / ((1-p) e^-x + p) = sigmoid(ln((1-p)/p) - x); exactly 1 when p = 0
    logit = math.log1p(-p) - math.log(p) if p > 0 else math.inf
    share = torch.sigmoid(logit - x)
    b = torch.where(positive, j * share, torch.zeros_like(j)).clamp(0.0, 1.0)
    return b.reshape(k_t.shape).to(out_dtype)


# --------------------------------------------------------------------------------------
# Eqs. 11-13
# --------------------------------------------------------------------------------------


def check_machine_params(lam: float, delta2: float, tau_inv: float = 0.0) -> None:
    """Refuses Eqs. 11-13's parameters out of range: ``0 < lam < 1``, ``delta2 > 1``, ``tau_inv >= 0``.

    Examples:
        >>> check_machine_params(lam=0.6, delta2=0.5)
        Traceback (most recent call last):
        ...
        ValueError: delta2 must be in (1.0, inf), got 0.5
    """
    check_in_range("tau_inv", tau_inv, 0.0, math.inf)
    check_in_range("lam", lam, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
    check_in_range("delta2", delta2, 1.0, math.inf, low_inclusive=False, high_inclusive=False)


@functools.lru_cache(maxsize=64)
def _steep_nodes(delta: float, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Nodes of :func:`_steep_machine`: ``t_j`` (in ``s - ln y``), ``e^{t_j}`` and the weights
    ``[n, 2]`` of the reject (column 0) and accept (column 1) kernels."""
    x, w = (torch.as_tensor(v, dtype=torch.float64) for v in _gauss_legendre(_N_STEEP))
    half = _T_STEEP / 2
    tau = torch.cat([(x - 1.0) * half, (x + 1.0) * half])  # two panels: [-T, 0] and [0, T]
    weights = torch.cat([w, w]) * half / delta
    coef = torch.stack([weights * torch.sigmoid(tau), weights * torch.sigmoid(-tau)], dim=-1)
    t = tau / delta
    return t.to(dtype=dtype, device=device), t.exp().to(dtype=dtype, device=device), coef.to(
        dtype=dtype, device=device
    )


@functools.cache
def _gauss_legendre(n: int) -> tuple[list[float], list[float]]:
    import numpy as np

    x, w = np.polynomial.legendre.leggauss(n)
    return x.tolist(), w.tolist()


def _steep_machine(m: Tensor, delta: float) -> Tensor:
    """``b_m`` at ``y = e^m`` for a steep cost (``delta2 > _STEEP_DELTA``), at a cost flat in delta2.

    The kernel ``σ(δ t)`` (``t = s - m``, ``s = ln u``) is a step smoothed over ``|t| ~ 1/δ``.
    With ``L = T / δ``: for ``t < -L`` it is ``e^{δ t}`` to a relative ``e^{-T}``, for
    ``t > L`` it is 1 to an absolute ``e^{-T}``, so (docs/math.md, section 5)::

        b_m = y^-δ γ(δ+1, y e^-L) + ∫_{-L}^{L} w(m + t) σ(δ t) dt + exp(-y e^L)

    with ``w(s) = exp(s - e^s)``; the middle integral, in ``τ = δ t``, is summed with
    Gauss-Legendre on ``[-T, 0]`` and ``[0, T]`` (the kernel's poles sit at ``τ = ±iπ``
    whatever δ). For ``y < 1`` the accept form ``1 - b_m`` is summed instead (relative
    accuracy where ``b_m -> 1``): ``1 - b_m = -expm1(-y e^-L) - y^-δ γ(...) + ∫ w σ(-δ t)``.
    """
    if m.numel() == 0:
        return m.new_zeros(0)
    t, growth, coef = _steep_nodes(delta, m.dtype, m.device)
    y = torch.exp(m)
    large = m >= 0
    L = _T_STEEP / delta
    block = max(16, _BLOCK * _n_nodes(_H) // t.numel())
    near_parts = []
    for m_b, y_b in zip(m.split(block), y.split(block), strict=True):
        w = torch.exp((m_b.unsqueeze(-1) + t).addcmul_(y_b.unsqueeze(-1), growth, value=-1.0))
        near_parts.append(w @ coef)
    near = torch.cat(near_parts)
    # the e^{δ t} tail, only where it counts (y >= 1; below, it is under e^-T of 1 - b_m)
    x_low = torch.where(large, y * math.exp(-L), torch.zeros_like(y))
    lower = torch.special.gammainc(torch.tensor(delta + 1.0, dtype=m.dtype, device=m.device), x_low)
    has_tail = lower > 0
    log_tail = math.lgamma(delta + 1.0) - delta * m + torch.log(torch.where(has_tail, lower, torch.ones_like(lower)))
    # exp of 0 where there is no tail: an overflowing exp would turn where()'s zero gradient to NaN
    tail = torch.where(has_tail, torch.exp(torch.where(has_tail, log_tail, torch.zeros_like(log_tail))), 0.0)
    reject = tail + near[:, 0] + torch.exp(-y * math.exp(L))
    accept = -torch.expm1(-y * math.exp(-L)) + near[:, 1]
    return torch.where(large, reject, 1.0 - accept)


def machine_confidence(c: TensorLike, lam: float, delta2: float, *, validate: bool = True) -> Tensor:
    """Eq. 13 (with the prior of Eq. 11 and the cost of Eq. 12): machine confidence ``b_m(c)``.

    ``b_m(c) = 1 - ∫_{C>c} g(c, C) dmu(C) / ∫_{C>c} dmu(C)`` with
    ``g = c^delta2 / (c^delta2 + (C - c)^delta2)`` and ``mu(C) = lam^C ln(1/lam)``.
    Substituting ``C = c + u / a`` with ``a = ln(1/lam)`` and ``y = a c`` gives::

        b_m = 1 - ∫_0^∞ e^-u / (1 + (u / y)^delta2) du = ∫_0^∞ e^-u / (1 + (y / u)^delta2) du

    ``b_m(0) = 1``, strictly decreasing in ``c`` (Property 3), ``-> 0`` as ``c -> inf``. For
    ``y < 1`` the first form is summed (relative accuracy as ``b_m -> 1``), otherwise the
    second (relative accuracy as ``b_m -> 0``).

    Args:
        c: decision uncertainty (Eq. 10), ``>= 0`` and finite, any shape.
        lam: base of the exponential prior over the risk tolerance ``C``, in ``(0, 1)``.
        delta2: exponent of the marginal cost, ``> 1`` and finite.
        validate: check that ``c`` is ``>= 0`` and finite (reads the result on the host: a
            device sync). The MC-dropout machine passes False on its frames: its ``c`` is a
            sum of squares of samples it checks finite on every frame (:func:`check_values`).

    Returns:
        ``b_m`` in ``[0, 1]``, same shape and floating dtype as ``c``; differentiable w.r.t.
        ``c`` (the gradient reported at ``c = 0`` is 0).

    Raises:
        ValueError: for a parameter out of range or a negative / non-finite ``c``.

    Examples:
        >>> machine_confidence(torch.tensor([0.0, 0.01, 1.0, 100.0]), lam=0.6, delta2=1.05)
        tensor([1.0000, 0.9783, 0.5363, 0.0159])
    """
    check_machine_params(lam, delta2)
    c_t = _as_float_tensor("c", c)
    if validate:
        _check_nonnegative_finite("c", c_t)
    out_dtype = c_t.dtype
    a = -math.log(lam)  # not log(1 / lam): 1 / lam overflows for a subnormal lam
    c_c = c_t.to(_compute_dtype(c_t)).reshape(-1)
    positive = c_c > 0
    # ln y as ln c + ln a: finite for every finite c > 0 (c * a may overflow)
    m = torch.log(torch.where(positive, c_c, torch.ones_like(c_c))) + math.log(a)
    delta = float(delta2)
    if delta > _STEEP_DELTA:
        b = _steep_machine(m, delta)
    else:
        h = min(_H, 2.0 * _H / delta)
        large = m >= 0
        total = _lattice_trapezoid(m, ("accept", "reject"), delta, h, which=large.to(torch.long))
        b = torch.where(large, total, 1.0 - total)
    b = torch.where(positive, b, torch.ones_like(b)).clamp(0.0, 1.0)
    return b.reshape(c_t.shape).to(out_dtype)


# --------------------------------------------------------------------------------------
# Eq. 10
# --------------------------------------------------------------------------------------


def mc_dropout_uncertainty(samples: Tensor, tau_inv: float = 0.0) -> tuple[Tensor, Tensor]:
    """Eq. 10: mean policy output and scalar uncertainty from ``M`` MC-dropout samples.

    With the ``M`` outputs ``mu_j`` (row vectors of size ``d``)::

        E[pi]       = 1/M sum_j mu_j
        E[pi^T pi]  = tau^-1 I + 1/M sum_j mu_j^T mu_j
        Cov         = E[pi^T pi] - E[pi]^T E[pi]          (biased, 1/M)
        c           = trace(Cov) = sum_d Var_d + d tau^-1

    The paper's ``Var[pi]`` is this ``d x d`` matrix; the scalar the confidence model needs
    is its trace (docs/math.md, section 3). The variances are computed from centred samples, so ``c >= 0``
    exactly.

    Args:
        samples: ``[M, *batch, d]`` policy outputs of ``M`` stochastic forward passes (drawn
            in one batched pass).
        tau_inv: observation noise ``tau^-1 >= 0`` added to each of the ``d`` variances.

    Returns:
        ``(mean, c)`` with shapes ``[*batch, d]`` and ``[*batch, 1]``.

    Raises:
        ValueError: if ``samples`` has fewer than 2 dims, ``M < 1``, or ``tau_inv < 0``.

    Examples:
        >>> samples = torch.tensor([[[0.0, 1.0]], [[2.0, 3.0]]])  # M=2, batch=1, d=2
        >>> mean, c = mc_dropout_uncertainty(samples, tau_inv=0.5)
        >>> mean, c
        (tensor([[1., 2.]]), tensor([[3.]]))
    """
    check_in_range("tau_inv", tau_inv, 0.0, math.inf)
    if not isinstance(samples, Tensor) or samples.dim() < 2:
        shape = tuple(samples.shape) if isinstance(samples, Tensor) else type(samples).__name__
        raise ValueError(f"samples must be a tensor of shape [M, *batch, d], got {shape}")
    if samples.shape[0] < 1:
        raise ValueError(f"samples needs M >= 1 samples along dim 0, got M={samples.shape[0]}")
    if not samples.is_floating_point():
        samples = samples.to(torch.get_default_dtype())
    d = samples.shape[-1]
    mean = samples.mean(0)
    var = (samples - mean).square().mean(0)
    c = var.sum(-1, keepdim=True) + d * float(tau_inv)
    return mean, c
