"""The confidence math (Eqs. 6-13) against a 30-digit reference of the paper's definitions,
the properties of Section 5, and the validation of every parameter."""

from __future__ import annotations

import math
from functools import cache

import mpmath as mp
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dcsc_torchrl import quadrature
from dcsc_torchrl.confidence import (
    check_finite,
    check_in_range,
    human_confidence,
    knowledge_update,
    machine_confidence,
    mc_dropout_uncertainty,
)
from dcsc_torchrl.quadrature import STEEP_DELTA

mp.mp.dps = 30

PAPER_LUNAR = {"p": 0.1, "eta": 0.6, "delta1": 2.0, "lam": 0.6, "delta2": 1.05}
PAPER_UAV = {"p": 0.01, "eta": 0.6, "delta1": 2.3, "lam": 0.6, "delta2": 1.02}
TOL = 1e-6  # float64 accuracy required against the reference


# --------------------------------------------------------------------------------------
# reference: Eqs. 9 and 13 as printed, integrated over K and C with 30 digits. Both
# integrals of a ratio are divided by eta^k (lam^c), or eta^K underflows mp.quad's tolerance;
# the range is split at the scale of k (c) and of 1 / ln(1/eta).
# --------------------------------------------------------------------------------------


@cache
def human_confidence_reference(k: float, p: float, eta: float, delta1: float) -> float:
    """Eq. 9 with mu of Eq. 7 and f of Eq. 8 (f(k, inf) = 0), by quadrature over K."""
    k, p, eta, delta1 = (mp.mpf(v) for v in (k, p, eta, delta1))
    a = mp.log(1 / eta)
    density = lambda K: a * eta ** (K - k)  # noqa: E731  (1-p) eta^K ln(1/eta) / eta^k / (1-p)
    payoff = lambda K: (k / K) ** delta1  # noqa: E731
    split = sorted({k, 2 * k, 10 * k, k + 1 / a, k + 10 / a, k + 50 / a}) + [mp.inf]
    numerator = (1 - p) * mp.quad(lambda K: payoff(K) * density(K), split)  # + p * f(k, inf) = 0
    denominator = (1 - p) * mp.quad(density, [k, k + 1 / a, k + 50 / a, mp.inf]) + p * eta ** (-k)
    return float(numerator / denominator)


@cache
def machine_confidence_reference(c: float, lam: float, delta2: float) -> float:
    """Eq. 13 with mu of Eq. 11 and g of Eq. 12, by quadrature over C."""
    c, lam, delta2 = (mp.mpf(v) for v in (c, lam, delta2))
    a = mp.log(1 / lam)
    density = lambda C: a * lam ** (C - c)  # noqa: E731
    cost = lambda C: c**delta2 / (c**delta2 + (C - c) ** delta2)  # noqa: E731
    split = sorted({c, 2 * c, 11 * c, c + 1 / a, c + 10 / a, c + 50 / a}) + [mp.inf]
    numerator = mp.quad(lambda C: cost(C) * density(C), split)
    denominator = mp.quad(density, [c, c + 1 / a, c + 50 / a, mp.inf])
    return float(1 - numerator / denominator)


def log_grid(n: int, lo: float = 1e-8, hi: float = 1e4) -> torch.Tensor:
    return torch.logspace(math.log10(lo), math.log10(hi), n, dtype=torch.float64)


def max_error(values: torch.Tensor, reference: torch.Tensor, at: torch.Tensor) -> tuple:
    err = (values - reference).abs()
    i = int(err.argmax())
    return float(err[i]), float(at[i])


HUMAN_SETS = [
    pytest.param(PAPER_LUNAR["p"], PAPER_LUNAR["eta"], PAPER_LUNAR["delta1"], 40, id="paper-lunar"),
    pytest.param(PAPER_UAV["p"], PAPER_UAV["eta"], PAPER_UAV["delta1"], 40, id="paper-uav"),
    pytest.param(0.1, 0.1, 0.5, 12, id="d0.5-eta0.1"),
    pytest.param(0.3, 0.9, 1.0, 12, id="d1-eta0.9"),
    pytest.param(0.0, 0.6, 3.7, 12, id="d3.7-p0"),
    pytest.param(0.5, 0.9, 0.5, 12, id="d0.5-p0.5"),
]

MACHINE_SETS = [
    pytest.param(PAPER_LUNAR["lam"], PAPER_LUNAR["delta2"], 40, id="paper-lunar"),
    pytest.param(PAPER_UAV["lam"], PAPER_UAV["delta2"], 40, id="paper-uav"),
    pytest.param(0.1, 1.01, 12, id="d1.01-lam0.1"),
    pytest.param(0.9, 1.5, 12, id="d1.5-lam0.9"),
    pytest.param(0.6, 3.0, 12, id="d3"),
]


# --------------------------------------------------------------------------------------
# accuracy against the definitions
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("p", "eta", "delta1", "n"), HUMAN_SETS)
def test_human_confidence_matches_definition_of_eq9(p, eta, delta1, n):
    k = log_grid(n)
    ref = torch.tensor(
        [human_confidence_reference(float(v), p, eta, delta1) for v in k], dtype=torch.float64
    )
    err, where = max_error(human_confidence(k, p, eta, delta1), ref, k)
    assert err <= TOL, f"max |b_h - reference| = {err:.3e} at k = {where:.3e}"


@pytest.mark.parametrize(("lam", "delta2", "n"), MACHINE_SETS)
def test_machine_confidence_matches_definition_of_eq13(lam, delta2, n):
    c = log_grid(n)
    ref = torch.tensor(
        [machine_confidence_reference(float(v), lam, delta2) for v in c], dtype=torch.float64
    )
    err, where = max_error(machine_confidence(c, lam, delta2), ref, c)
    assert err <= TOL, f"max |b_m - reference| = {err:.3e} at c = {where:.3e}"


def test_human_confidence_closed_form_of_design_matches_definition():
    # docs/math.md, section 2: b_h = (1-p) x E_delta1(x) / ((1-p) e^-x + p), x = k ln(1/eta)
    p, eta, delta1 = PAPER_UAV["p"], PAPER_UAV["eta"], PAPER_UAV["delta1"]
    a = mp.log(1 / mp.mpf(eta))
    for k in (1e-6, 0.3, 4.0, 40.0):
        x = a * k
        closed = (1 - p) * x * mp.expint(delta1, x) / ((1 - p) * mp.exp(-x) + p)
        assert abs(float(closed) - human_confidence_reference(k, p, eta, delta1)) < 1e-12


def test_float32_agrees_with_float64():
    k = log_grid(60, 1e-6, 1e6)
    for kw in (PAPER_LUNAR, PAPER_UAV):
        h64 = human_confidence(k, kw["p"], kw["eta"], kw["delta1"])
        h32 = human_confidence(k.float(), kw["p"], kw["eta"], kw["delta1"])
        m64 = machine_confidence(k, kw["lam"], kw["delta2"])
        m32 = machine_confidence(k.float(), kw["lam"], kw["delta2"])
        assert h32.dtype == m32.dtype == torch.float32
        assert (h32.double() - h64).abs().max() < 2e-6
        assert (m32.double() - m64).abs().max() < 2e-6


# --------------------------------------------------------------------------------------
# Properties 1-3 and ranges (hypothesis)
# --------------------------------------------------------------------------------------

probability = st.floats(1e-6, 0.99)
base = st.floats(0.01, 0.99)  # eta, lam
delta1_st = st.floats(0.05, 8.0)
delta2_st = st.floats(1.001, 6.0)
dtypes = st.sampled_from([torch.float32, torch.float64])
shapes = st.lists(st.integers(0, 4), min_size=0, max_size=3).map(tuple)


@settings(max_examples=40, deadline=None)
@given(
    p=st.one_of(st.just(0.0), probability),
    eta=base,
    delta1=delta1_st,
    dtype=dtypes,
    shape=shapes,
    seed=st.integers(0, 2**31 - 1),
)
def test_human_confidence_in_unit_interval_for_any_shape_and_dtype(
    p, eta, delta1, dtype, shape, seed
):
    g = torch.Generator().manual_seed(seed)
    k = torch.exp(torch.empty(shape, dtype=torch.float64).uniform_(-20, 18.4, generator=g))
    k = k.to(dtype)
    b = human_confidence(k, p, eta, delta1)
    assert b.shape == k.shape and b.dtype == dtype
    assert torch.isfinite(b).all() and (b >= 0).all() and (b <= 1).all()
    flat = human_confidence(k.reshape(-1), p, eta, delta1)
    torch.testing.assert_close(b.reshape(-1), flat, rtol=0, atol=0)
    edges = human_confidence(torch.tensor([0.0, 1e8], dtype=dtype), p, eta, delta1)
    assert torch.isfinite(edges).all() and edges[0] == 0  # b_h(0) = 0 exactly (Eq. 8)


@settings(max_examples=40, deadline=None)
@given(lam=base, delta2=delta2_st, dtype=dtypes, shape=shapes, seed=st.integers(0, 2**31 - 1))
def test_machine_confidence_in_unit_interval_for_any_shape_and_dtype(
    lam, delta2, dtype, shape, seed
):
    g = torch.Generator().manual_seed(seed)
    c = torch.exp(torch.empty(shape, dtype=torch.float64).uniform_(-20, 18.4, generator=g))
    c = c.to(dtype)
    b = machine_confidence(c, lam, delta2)
    assert b.shape == c.shape and b.dtype == dtype
    assert torch.isfinite(b).all() and (b >= 0).all() and (b <= 1).all()
    edges = machine_confidence(torch.tensor([0.0, 1e8], dtype=dtype), lam, delta2)
    assert torch.isfinite(edges).all() and edges[0] == 1  # b_m(0) = 1
    assert edges[1] < 1e-5


@settings(max_examples=30, deadline=None)
@given(p=probability, eta=base, delta1=delta1_st)
def test_human_confidence_vanishes_with_knowledge_property1(p, eta, delta1):
    a = math.log(1 / eta)
    # beyond x = ln((1-p)/p) + 40 the share of the finite-difficulty tasks is < e^-40
    k_far = (math.log((1 - p) / p) + 40.0) / a
    k = torch.tensor([0.0, k_far, 2 * k_far, 1e8 / a], dtype=torch.float64)
    b = human_confidence(k, p, eta, delta1)
    assert b[0] == 0
    assert (b[1:] < 1e-15).all(), b
    assert b[2] <= b[1]


@settings(max_examples=30, deadline=None)
@given(p=probability, eta=base, delta1=delta1_st)
def test_human_confidence_rises_then_falls_property2(p, eta, delta1):
    a = math.log(1 / eta)
    k_far = (math.log((1 - p) / p) + 40.0) / a
    k = torch.logspace(-8, math.log10(k_far), 300, dtype=torch.float64)
    b = human_confidence(k, p, eta, delta1)
    step = torch.diff(b)
    signs = torch.sign(step[step.abs() > 1e-13])
    assert signs[0] == 1 and signs[-1] == -1, "b_h must rise from 0 and fall at large k"
    assert int((torch.diff(signs) != 0).sum()) == 1, "b_h must be unimodal on the grid"
    # Property 2 directly: the derivative is negative for large k
    k_big = torch.tensor([2.0 * float(k[int(b.argmax())]) + 1.0], dtype=torch.float64)
    k_big.requires_grad_(True)
    (grad,) = torch.autograd.grad(human_confidence(k_big, p, eta, delta1).sum(), k_big)
    assert grad.item() <= 0


@settings(max_examples=30, deadline=None)
@given(lam=base, delta2=delta2_st)
def test_machine_confidence_strictly_decreases_with_uncertainty_property3(lam, delta2):
    c = torch.logspace(-8, 8, 200, dtype=torch.float64)
    b = machine_confidence(c, lam, delta2)
    assert (torch.diff(b) < 0).all(), "b_m must be strictly decreasing in float64"
    b32 = machine_confidence(c.float(), lam, delta2)
    assert (torch.diff(b32) <= 0).all(), "b_m must be non-increasing in float32"
    c_grad = torch.tensor([1e-3, 0.1, 1.0, 30.0], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(machine_confidence(c_grad, lam, delta2).sum(), c_grad)
    assert (grad < 0).all()


def test_confidences_accept_python_numbers_and_empty_batches():
    assert human_confidence(3.0, **_human(PAPER_LUNAR)).shape == ()
    assert machine_confidence(0, **_machine(PAPER_LUNAR)).item() == 1.0
    assert human_confidence(torch.zeros(0, 3), **_human(PAPER_LUNAR)).shape == (0, 3)
    assert machine_confidence(torch.zeros(2, 0), **_machine(PAPER_LUNAR)).shape == (2, 0)


def test_confidences_over_the_whole_float64_range(monkeypatch):
    c = torch.cat([torch.zeros(1), torch.logspace(-300, 300, 121, dtype=torch.float64)])
    b_m = machine_confidence(c, **_machine(PAPER_UAV))
    b_h = human_confidence(c, **_human(PAPER_UAV))
    for b in (b_m, b_h):
        assert torch.isfinite(b).all() and (b >= 0).all() and (b <= 1).all()
    assert (torch.diff(b_m) <= 0).all()
    # a batch spanning a range too wide for one kernel table is split by range: same values
    monkeypatch.setattr(quadrature, "_MAX_TABLE", 5_000)
    torch.testing.assert_close(
        machine_confidence(c, **_machine(PAPER_UAV)), b_m, rtol=0, atol=1e-15
    )
    torch.testing.assert_close(human_confidence(c, **_human(PAPER_UAV)), b_h, rtol=0, atol=1e-15)


@pytest.mark.parametrize(("lam", "delta2"), [(0.6, 8.0), (0.3, 20.0)])
def test_machine_confidence_accurate_for_steep_cost(lam, delta2):
    # delta2 > 2 narrows the analyticity strip of the kernel: the lattice is refined
    c = log_grid(8)
    ref = torch.tensor(
        [machine_confidence_reference(float(v), lam, delta2) for v in c], dtype=torch.float64
    )
    err, where = max_error(machine_confidence(c, lam, delta2), ref, c)
    assert err <= TOL, f"max |b_m - reference| = {err:.3e} at c = {where:.3e}"


@pytest.mark.parametrize("delta2", [3.0001, 10.0, 100.0, 1000.0])
def test_machine_confidence_accurate_for_very_steep_cost_split_rule(delta2):
    # above delta2 = 3 the integral is split at the kernel's step (cost flat in delta2)
    c = log_grid(8)
    ref = torch.tensor(
        [machine_confidence_reference(float(v), 0.6, delta2) for v in c], dtype=torch.float64
    )
    err, where = max_error(machine_confidence(c, 0.6, delta2), ref, c)
    assert err <= TOL, f"max |b_m - reference| = {err:.3e} at c = {where:.3e}"
    c_grad = torch.tensor([1e-3, 0.3, 2.0, 40.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: machine_confidence(c, 0.6, delta2), (c_grad,))


def test_split_rule_continues_the_lattice_at_the_switch():
    c = log_grid(30, 1e-6, 1e3)
    below = machine_confidence(c, 0.6, STEEP_DELTA)
    above = machine_confidence(c, 0.6, STEEP_DELTA + 1e-9)
    assert (below - above).abs().max() < 1e-8


@pytest.mark.parametrize("tiny", [1e-300, 5e-324])
def test_subnormal_eta_and_lambda_give_values_not_overflow_errors(tiny):
    k = torch.tensor([0.0, 1e-6, 0.5, 3.0, 1e300], dtype=torch.float64)
    b_h = human_confidence(k, 0.1, tiny, 2.0)
    b_m = machine_confidence(k, tiny, 1.05)
    assert torch.isfinite(b_h).all() and torch.isfinite(b_m).all()
    assert b_h[0] == 0 and b_m[0] == 1 and (torch.diff(b_m) <= 0).all()
    assert b_h[-1] == 0 and b_m[-1] < 1e-10


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_full_range_table_of_devices_gives_the_host_values(monkeypatch, dtype):
    # off the host the lattice uses one table for every finite input (no read-back to pick it)
    tiny, big = torch.finfo(dtype).tiny * 1e-6 if dtype == torch.float32 else 5e-324, torch.finfo(dtype).max
    c = torch.cat([torch.zeros(1, dtype=torch.float64), torch.logspace(-300, 300, 61, dtype=torch.float64)])
    c = torch.cat([c.to(dtype), torch.tensor([tiny, big], dtype=dtype)])
    c = c[torch.isfinite(c)]
    host = [human_confidence(c, 0.1, 5e-324, 2.0), machine_confidence(c, 0.6, 1.05), machine_confidence(c, 0.6, 2.5),
            human_confidence(c, 0.1, 1 - 1e-16, 2.0)]
    monkeypatch.setattr(quadrature, "_sync_free", lambda device: True)
    device = [human_confidence(c, 0.1, 5e-324, 2.0), machine_confidence(c, 0.6, 1.05), machine_confidence(c, 0.6, 2.5),
              human_confidence(c, 0.1, 1 - 1e-16, 2.0)]
    for a, b in zip(host, device, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-15 if dtype == torch.float64 else 1e-7)


def test_machine_confidence_without_validation_skips_only_the_check():
    c = torch.tensor([0.0, 0.3, 7.0])
    torch.testing.assert_close(machine_confidence(c, 0.6, 1.05, validate=False), machine_confidence(c, 0.6, 1.05))


def _human(kw: dict) -> dict:
    return {"p": kw["p"], "eta": kw["eta"], "delta1": kw["delta1"]}


def _machine(kw: dict) -> dict:
    return {"lam": kw["lam"], "delta2": kw["delta2"]}


# --------------------------------------------------------------------------------------
# gradients
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kw", [PAPER_LUNAR, PAPER_UAV], ids=["paper-lunar", "paper-uav"])
def test_human_confidence_gradcheck_wrt_knowledge(kw):
    k = torch.tensor([0.01, 0.4, 2.5, 7.0, 15.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda k: human_confidence(k, **_human(kw)), (k,))


@pytest.mark.parametrize("kw", [PAPER_LUNAR, PAPER_UAV], ids=["paper-lunar", "paper-uav"])
def test_machine_confidence_gradcheck_wrt_uncertainty(kw):
    c = torch.tensor([1e-3, 0.05, 0.7, 3.0, 80.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: machine_confidence(c, **_machine(kw)), (c,))


def test_gradients_are_finite_at_zero():
    k = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    human_confidence(k, **_human(PAPER_LUNAR)).sum().backward()
    c = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    machine_confidence(c, **_machine(PAPER_LUNAR)).sum().backward()
    assert torch.isfinite(k.grad).all() and torch.isfinite(c.grad).all()


# --------------------------------------------------------------------------------------
# Eq. 6
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["decay", "paper"])
def test_knowledge_update_saturates_at_task_difficulty_case1_absorbing(mode):
    k = torch.tensor([10.0, 12.0])
    out = knowledge_update(k, torch.tensor([0.3, 5.0]), K=10.0, t_d=1.0, mode=mode, cap="absorbing")
    torch.testing.assert_close(out, torch.tensor([10.0, 10.0]))


@pytest.mark.parametrize("mode", ["decay", "paper"])
def test_knowledge_update_case1_is_a_cap_so_a_late_decision_lowers_k_at_K(mode):
    k = torch.tensor([10.0, 10.0, 12.0])
    out = knowledge_update(k, torch.tensor([0.3, 1.5, 0.3]), K=10.0, t_d=1.0, mode=mode)
    assert out[0] == 10.0 and out[2] == 10.0  # timely decisions stay at the cap
    assert out[1] < 10.0  # a decision slower than t_d lowers k even at K
    b_h = human_confidence(out, **_human(PAPER_LUNAR))
    assert b_h[1] != b_h[0]


def test_knowledge_update_rejects_unknown_cap():
    with pytest.raises(ValueError, match="cap"):
        knowledge_update(torch.tensor([1.0]), torch.tensor([0.1]), K=10.0, t_d=1.0, cap="sticky")


@pytest.mark.parametrize("mode", ["decay", "paper"])
def test_knowledge_update_learns_on_timely_response_case2(mode):
    k = torch.tensor([0.5, 0.5, 8.0], dtype=torch.float64)
    rt = torch.tensor([0.2, 1.0, 0.1], dtype=torch.float64)  # RT == t_d still learns
    out = knowledge_update(k, rt, K=10.0, t_d=1.0, mode=mode)
    expected = torch.tensor([0.5 * (1 + math.exp(-0.2)), 0.5 * (1 + math.exp(-1.0)), 10.0])
    torch.testing.assert_close(out, expected.double())


def test_knowledge_update_decays_on_late_response_case3_decay():
    k = torch.tensor([2.0, 2.0], dtype=torch.float64)
    rt = torch.tensor([1.5, 4.0], dtype=torch.float64)
    out = knowledge_update(k, rt, K=10.0, t_d=1.0)
    torch.testing.assert_close(
        out, torch.tensor([2.0 * math.exp(-0.5), 2.0 * math.exp(-3.0)]).double()
    )


def test_knowledge_update_case3_paper_factor_clamped_to_floor():
    # the printed factor 1 - exp(RT - t_d) < 0 for every RT > t_d: clamped to k_floor
    k = torch.tensor([2.0, 0.0, 5.0], dtype=torch.float64)
    rt = torch.tensor([1.0001, 3.0, 1e6], dtype=torch.float64)
    out = knowledge_update(k, rt, K=10.0, t_d=1.0, mode="paper", k_floor=0.05)
    torch.testing.assert_close(out, torch.full((3,), 0.05, dtype=torch.float64))
    assert ((1 - torch.exp(rt - 1.0)) * k <= 0).all()


@settings(max_examples=50, deadline=None)
@given(
    mode=st.sampled_from(["decay", "paper"]),
    K=st.floats(1e-2, 1e3),
    t_d=st.floats(0.05, 3.0),
    seed=st.integers(0, 2**31 - 1),
    dtype=dtypes,
)
def test_knowledge_update_stays_in_zero_to_K(mode, K, t_d, seed, dtype):
    g = torch.Generator().manual_seed(seed)
    k = (torch.rand(64, generator=g, dtype=torch.float64) * 1.5 * K).to(dtype)
    k[0] = 0.0
    rt = torch.cat(
        [torch.rand(62, generator=g, dtype=torch.float64) * 3 * t_d, torch.tensor([0.0, 1e9])]
    )
    rt = rt.to(dtype)
    out = knowledge_update(k, rt, K=K, t_d=t_d, mode=mode, k_floor=min(1e-3, K))
    assert out.dtype == dtype and out.shape == k.shape
    assert torch.isfinite(out).all() and (out >= 0).all() and (out <= K * (1 + 1e-6)).all()
    # below K, learning never decreases knowledge and a late answer never increases it
    timely, below = rt <= t_d, k < K
    assert (out[timely & below] >= k[timely & below] * (1 - 1e-6)).all()
    assert (out[~below & timely] == K).all()  # case 1 caps at K ...
    late = ~below & ~timely  # ... and a late answer lowers k even there
    assert (out[late] <= torch.clamp(k[late] * (1 + 1e-6), max=K)).all()
    assert (out[late & (k == K)] < K).all()
    strict = knowledge_update(k, rt, K=K, t_d=t_d, mode=mode, k_floor=min(1e-3, K), cap="absorbing")
    assert (strict[~below] == K).all()
    if mode == "decay":
        assert (out[~timely & below] <= k[~timely & below]).all()


def test_knowledge_update_broadcasts_knowledge_and_response_time():
    out = knowledge_update(
        torch.full((3, 1), 0.5), torch.tensor([0.1, 0.5, 2.0, 0.0]), K=5.0, t_d=1.0
    )
    assert out.shape == (3, 4)
    assert out.dtype == torch.float32


# --------------------------------------------------------------------------------------
# Eq. 10
# --------------------------------------------------------------------------------------


def eq10_by_hand(samples: torch.Tensor, tau_inv: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 10 with explicit loops: mean, outer products, covariance matrix, its trace."""
    m_samples, batch, d = samples.shape
    means, traces = [], []
    for b in range(batch):
        mean = torch.zeros(d, dtype=torch.float64)
        second = tau_inv * torch.eye(d, dtype=torch.float64)
        for j in range(m_samples):
            mu = samples[j, b].double()
            mean += mu / m_samples
            second += torch.outer(mu, mu) / m_samples  # mu^T mu of a row vector
        cov = second - torch.outer(mean, mean)
        means.append(mean)
        traces.append(torch.trace(cov).reshape(1))
    return torch.stack(means), torch.stack(traces)


@pytest.mark.parametrize("tau_inv", [0.0, 0.25])
@pytest.mark.parametrize("m_samples", [1, 2, 10])
def test_mc_dropout_uncertainty_is_trace_of_eq10_covariance(tau_inv, m_samples):
    g = torch.Generator().manual_seed(m_samples)
    samples = torch.randn(m_samples, 5, 3, generator=g, dtype=torch.float64)
    mean, c = mc_dropout_uncertainty(samples, tau_inv=tau_inv)
    mean_ref, c_ref = eq10_by_hand(samples, tau_inv)
    assert mean.shape == (5, 3) and c.shape == (5, 1)
    torch.testing.assert_close(mean, mean_ref)
    torch.testing.assert_close(c, c_ref)
    if m_samples == 1:
        torch.testing.assert_close(c, torch.full((5, 1), 3 * tau_inv, dtype=torch.float64))


def test_mc_dropout_uncertainty_keeps_batch_dims_and_is_nonnegative():
    samples = torch.full((10, 2, 3, 4), 0.1, dtype=torch.float32) + 1e-9
    mean, c = mc_dropout_uncertainty(samples)
    assert mean.shape == (2, 3, 4) and c.shape == (2, 3, 1)
    assert (c >= 0).all()
    # the same uncertainty as the flattened batch
    flat_mean, flat_c = mc_dropout_uncertainty(samples.reshape(10, 6, 4))
    torch.testing.assert_close(c.reshape(6, 1), flat_c)


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------

GOOD_H = {"p": 0.1, "eta": 0.6, "delta1": 2.0}
GOOD_M = {"lam": 0.6, "delta2": 1.05}
GOOD_K = {"K": 10.0, "t_d": 1.0, "mode": "decay", "k_floor": 1e-3}

INVALID = [
    ("human", "p", -0.1),
    ("human", "p", 1.0),
    ("human", "p", float("nan")),
    ("human", "eta", 0.0),
    ("human", "eta", 1.0),
    ("human", "delta1", 0.0),
    ("human", "delta1", -2.0),
    ("human", "delta1", float("inf")),
    ("human", "k", -1.0),
    ("human", "k", float("inf")),
    ("human", "k", float("nan")),
    ("machine", "lam", 0.0),
    ("machine", "lam", 1.5),
    ("machine", "delta2", 1.0),
    ("machine", "delta2", 0.5),
    ("machine", "delta2", float("inf")),
    ("machine", "c", -1e-3),
    ("machine", "c", float("inf")),
    ("knowledge", "K", 0.0),
    ("knowledge", "K", -3.0),
    ("knowledge", "t_d", 0.0),
    ("knowledge", "mode", "forget"),
    ("knowledge", "k_floor", 0.0),
    ("knowledge", "k", -0.5),
    ("knowledge", "k", float("nan")),
    ("knowledge", "rt", -0.1),
    ("knowledge", "rt", float("inf")),
    ("mc", "tau_inv", -1.0),
    ("mc", "samples", None),
]


def _call(fn: str, name: str, value):
    if fn == "human":
        kwargs = dict(GOOD_H, **({} if name == "k" else {name: value}))
        k = torch.tensor([0.5, value]) if name == "k" else torch.tensor([0.5])
        return human_confidence(k, **kwargs)
    if fn == "machine":
        kwargs = dict(GOOD_M, **({} if name == "c" else {name: value}))
        c = torch.tensor([0.5, value]) if name == "c" else torch.tensor([0.5])
        return machine_confidence(c, **kwargs)
    if fn == "knowledge":
        kwargs = dict(GOOD_K, **({} if name in ("k", "rt") else {name: value}))
        if name == "k_floor":
            kwargs["mode"] = "paper"
        k = torch.tensor([value]) if name == "k" else torch.tensor([0.5])
        rt = torch.tensor([value]) if name == "rt" else torch.tensor([0.5])
        return knowledge_update(k, rt, **kwargs)
    if name == "samples":
        return mc_dropout_uncertainty(torch.zeros(4))
    return mc_dropout_uncertainty(torch.zeros(10, 2, 3), tau_inv=value)


@pytest.mark.parametrize(
    ("fn", "name", "value"), INVALID, ids=[f"{f}-{n}-{v}" for f, n, v in INVALID]
)
def test_invalid_input_raises_value_error_naming_it(fn, name, value):
    with pytest.raises(ValueError, match=name):
        _call(fn, name, value)


def test_check_in_range_bounds_and_messages():
    assert check_in_range("x", 0.0, 0.0, 1.0) == 0.0
    with pytest.raises(ValueError, match=r"x must be in \(0.0, 1.0\], got 0.0"):
        check_in_range("x", 0.0, 0.0, 1.0, low_inclusive=False)
    with pytest.raises(ValueError, match=r"x must be in \[-inf, 2.0\), got 2.0"):
        check_in_range("x", 2.0, None, 2.0, high_inclusive=False)
    with pytest.raises(ValueError, match="theta_init"):
        check_in_range("theta_init", "a", 0.0, 1.0)
    t = torch.tensor([0.2, 3.0, 0.5])
    with pytest.raises(ValueError, match=r"beta must be in \[0.0, 1.0\], got 3.0 \(1 of 3"):
        check_in_range("beta", t, 0.0, 1.0)
    assert check_in_range("beta", t.clamp(max=1), 0.0, 1.0) is not None


def test_check_finite_names_the_key_and_value():
    check_finite("observation", torch.ones(2, 9))
    check_finite("human_decided", torch.ones(2, 1, dtype=torch.bool))
    bad = torch.zeros(2, 9)
    bad[1, 4] = float("-inf")
    with pytest.raises(
        ValueError, match=r"observation has 1 non-finite value\(s\) of 18: -inf at index \(1, 4\)"
    ):
        check_finite("observation", bad)
