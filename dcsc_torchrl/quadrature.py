"""The quadrature behind the two confidence integrals of :mod:`dcsc_torchrl.confidence`.

Both integrals are of the form ``∫_0^∞ e^{-u} h(u / y) du`` (docs/math.md). They are
evaluated with the trapezoidal rule in ``s = ln u``, on a lattice anchored to ``ln y`` so
that the kernel ``h`` is tabulated once per call and every element costs one ``exp`` per
node (:func:`lattice_trapezoid`). The rule converges geometrically (the integrand is analytic
in a strip around the real axis); with the node spacing :data:`H` the error against a
30-digit reference is below 1e-9 in float64 (``tests/test_confidence.py`` checks 1e-6). A
steep machine cost (``delta2 > STEEP_DELTA``) is summed at the kernel's step instead, at a
cost flat in delta2 (:func:`steep_machine_integral`).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

__all__ = ["H", "STEEP_DELTA", "compute_dtype", "lattice_trapezoid", "steep_machine_integral"]


# The quadrature: trapezoidal rule in s = ln u over [_S_LO, _S_HI].
# Below _S_LO the weight e^{s - e^s} ~ e^s integrates to e^{_S_LO} ~ 1e-10 (dropped);
# above _S_HI it is below e^{3.6 - e^{3.6}} ~ 5e-15.
_S_LO = -23.0
_S_HI = 3.6
# Node spacing. The weight e^{s - e^s} is analytic for |Im s| < pi/2, so the rule's error is
# ~exp(-pi^2 / h) ~ 2e-11 at h = 0.4. The machine kernel 1 / (1 + e^{delta2 t}) has poles at
# Im t = pi / delta2, so for delta2 > 2 the spacing shrinks to 0.8 / delta2.
H = 0.4
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
# Above this delta2 the machine integral is split at the kernel's step (``steep_machine_integral``):
# the lattice's cost grows like delta2 (spacing 0.8 / delta2), the split rule's does not.
STEEP_DELTA = 3.0
# The split rule: its window is |delta2 * ln(u / y)| <= _T_STEEP (outside it the kernel is
# e^{-delta2 |t|} to a relative 1e-16), covered by two Gauss-Legendre panels of _N_STEEP nodes.
_T_STEEP = 37.0
_N_STEEP = 40


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


def lattice_trapezoid(
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
                out = out.index_put((idx,), lattice_trapezoid(m[idx], kinds, delta, h, sub_which))
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
    """The trapezoidal sums of :func:`lattice_trapezoid` once its table ``rows`` is chosen."""
    growth = _growth(h, m.dtype, m.device)
    a0 = m + h * i0  # s of the first node, in [_S_LO - h, _S_LO); carries m's gradient
    if which is not None:
        offset = offset + n_rows * which
    block = max(16, _BLOCK * _n_nodes(H) // n_nodes)  # same work array for finer lattices
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


def compute_dtype(t: Tensor) -> torch.dtype:
    # float64 inputs stay float64; float32/float16/bfloat16 are computed in float32.
    return torch.float64 if t.dtype == torch.float64 else torch.float32


@functools.lru_cache(maxsize=64)
def _steep_nodes(delta: float, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Nodes of :func:`steep_machine_integral`: ``t_j`` (in ``s - ln y``), ``e^{t_j}`` and the weights
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


def steep_machine_integral(m: Tensor, delta: float) -> Tensor:
    """``b_m`` at ``y = e^m`` for a steep cost (``delta2 > STEEP_DELTA``), at a cost flat in delta2.

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
    block = max(16, _BLOCK * _n_nodes(H) // t.numel())
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
