"""The confidence math of DC-SC: Eq. 6 (knowledge), Eqs. 7-9 (human confidence), Eq. 10
(MC-dropout uncertainty) and Eqs. 11-13 (machine confidence).

Every function here is a pure torch function: it takes tensors of any batch shape, keeps the
input's floating dtype (float32 or float64), never returns NaN for finite inputs in its
domain, and validates its scalar parameters with a :class:`ValueError` that names the bad
parameter and its value (:mod:`dcsc_torchrl.checks`, whose helpers this module re-exports).
The two confidence integrals have no elementary closed form; :mod:`dcsc_torchrl.quadrature`
sums them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dcsc_torchrl.checks import (
    TensorLike,
    check_finite,
    check_in_range,
    check_values,
    defer_check,
    flush_frame_checks,
)
from dcsc_torchrl.quadrature import (
    STEEP_DELTA,
    H,
    compute_dtype,
    lattice_trapezoid,
    steep_machine_integral,
)

__all__ = [
    "check_finite",
    "check_in_range",
    "check_machine_params",
    "check_values",
    "defer_check",
    "flush_frame_checks",
    "human_confidence",
    "knowledge_update",
    "machine_confidence",
    "mc_dropout_uncertainty",
]


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
    k_c = k_t.to(compute_dtype(k_t)).reshape(-1)
    x = k_c * a  # may overflow to inf (huge k, tiny eta): the sigmoid below takes it
    positive = k_c > 0
    # ln x as ln k + ln a: finite for every finite k > 0 and eta in (0, 1)
    m = torch.log(torch.where(positive, k_c, torch.ones_like(k_c))) + math.log(a)
    j = lattice_trapezoid(m, ("human",), float(delta1), H)
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
    c_c = c_t.to(compute_dtype(c_t)).reshape(-1)
    positive = c_c > 0
    # ln y as ln c + ln a: finite for every finite c > 0 (c * a may overflow)
    m = torch.log(torch.where(positive, c_c, torch.ones_like(c_c))) + math.log(a)
    delta = float(delta2)
    if delta > STEEP_DELTA:
        b = steep_machine_integral(m, delta)
    else:
        h = min(H, 2.0 * H / delta)
        large = m >= 0
        total = lattice_trapezoid(m, ("accept", "reject"), delta, h, which=large.to(torch.long))
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
