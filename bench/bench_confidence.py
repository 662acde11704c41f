"""Speed of the confidence math (Eqs. 9, 13) and of the MC-dropout pass (Eq. 10).

Run: ``python bench/bench_confidence.py [--against OLD_CONFIDENCE.py]`` (one torch thread,
CPU). Prints three tables:

1. evaluations/s of ``human_confidence`` and ``machine_confidence`` on 1e6-element batches,
   float32 and float64, with the cost relative to one ``torch.exp`` over the same batch
   (a baseline measured in the same run, so the ratio carries across machines);
2. MC-dropout with M = 10 samples: one batched forward pass of ``[M, B, obs]`` through a
   dropout MLP versus a Python loop of M forward passes, with the batched speed-up, for a
   training-size batch (B = 1024) and a rollout-size one (B = 8, one row per env);
3. the cost of ``machine_confidence`` against delta2 (1e5 elements, float64), relative to
   delta2 = 1.05; with ``--against FILE`` (another version of ``dcsc_torchrl/confidence.py``,
   e.g. ``git show REV:dcsc_torchrl/confidence.py > /tmp/old.py``) the same for that version,
   side by side: the before / after of a change.

Times are medians of several repeats (``time.perf_counter``).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn

from dcsc_torchrl.confidence import human_confidence, machine_confidence, mc_dropout_uncertainty

N_ELEMENTS = 1_000_000
REPEATS = 7
PAPER_LUNAR = {"p": 0.1, "eta": 0.6, "delta1": 2.0}
PAPER_LUNAR_MACHINE = {"lam": 0.6, "delta2": 1.05}
M_SAMPLES, BATCH, OBS, HIDDEN, ACT = 10, 1024, 8, 64, 4
DELTA2_SWEEP = (1.05, 2.0, 3.0, 3.5, 5.0, 10.0, 30.0, 100.0)
N_SWEEP = 100_000


def median_seconds(fn: Callable[[], object], repeats: int = REPEATS, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def bench_confidence() -> list[tuple[str, str, float, float, float]]:
    rows = []
    gen = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        # knowledge / uncertainty spread over 10 decades, as a batch of envs would see them
        values = torch.exp(torch.empty(N_ELEMENTS, dtype=dtype).uniform_(-9.0, 9.0, generator=gen))
        baseline = median_seconds(lambda v=values: torch.exp(v))
        for name, fn in (
            ("human_confidence", lambda v=values: human_confidence(v, **PAPER_LUNAR)),
            ("machine_confidence", lambda v=values: machine_confidence(v, **PAPER_LUNAR_MACHINE)),
        ):
            seconds = median_seconds(fn)
            rows.append(
                (
                    name,
                    str(dtype).removeprefix("torch."),
                    seconds,
                    N_ELEMENTS / seconds,
                    seconds / baseline,
                )
            )
    return rows


def dropout_mlp() -> nn.Module:
    return nn.Sequential(
        nn.Linear(OBS, HIDDEN),
        nn.Tanh(),
        nn.Dropout(0.05),
        nn.Linear(HIDDEN, HIDDEN),
        nn.Tanh(),
        nn.Dropout(0.05),
        nn.Linear(HIDDEN, ACT),
    ).train()  # dropout active: every sample draws its own mask


def bench_mc_dropout(batch: int) -> tuple[float, float]:
    torch.manual_seed(0)
    net = dropout_mlp()
    obs = torch.randn(batch, OBS)

    @torch.no_grad()
    def batched():
        samples = net(obs.expand(M_SAMPLES, batch, OBS))  # one pass, M masks
        return mc_dropout_uncertainty(samples)

    @torch.no_grad()
    def looped():
        samples = torch.stack([net(obs) for _ in range(M_SAMPLES)])
        return mc_dropout_uncertainty(samples)

    # both draw M independent masks per batch element
    assert batched()[0].shape == looped()[0].shape == (batch, ACT)
    repeats = 50 if batch >= 256 else 500
    return median_seconds(batched, repeats=repeats), median_seconds(looped, repeats=repeats)


def bench_delta2(fn: Callable[..., torch.Tensor]) -> list[float]:
    """Seconds per call of ``fn(c, lam=0.6, delta2)`` on N_SWEEP float64 values, per delta2."""
    gen = torch.Generator().manual_seed(1)
    values = torch.exp(torch.empty(N_SWEEP, dtype=torch.float64).uniform_(-9.0, 9.0, generator=gen))
    return [median_seconds(lambda d=d: fn(values, 0.6, d), repeats=3, warmup=1) for d in DELTA2_SWEEP]


def load_confidence_module(path: Path):
    """Imports another version of ``confidence.py`` from a file (for ``--against``)."""
    spec = importlib.util.spec_from_file_location("confidence_against", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", type=Path, default=None,
                        help="another confidence.py to time beside this one (delta2 table only)")
    parser.add_argument("--only-delta2", action="store_true", help="print only the delta2 table")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread, CPU\n")

    if not args.only_delta2:
        bench_tables()
    print(f"\nmachine_confidence against delta2, {N_SWEEP:.0e} float64 elements, lam = 0.6")
    versions = {"this": machine_confidence}
    if args.against is not None:
        versions[str(args.against)] = load_confidence_module(args.against).machine_confidence
    times = {name: bench_delta2(fn) for name, fn in versions.items()}
    header = "| delta2 | " + " | ".join(f"{name}: ms (x delta2=1.05)" for name in times) + " |"
    print(header)
    print("|---|" + "---|" * len(times))
    for i, delta2 in enumerate(DELTA2_SWEEP):
        cells = " | ".join(f"{t[i] * 1e3:.1f} ({t[i] / t[0]:.1f}x)" for t in times.values())
        print(f"| {delta2:g} | {cells} |")


def bench_tables() -> None:
    """Tables 1 and 2."""
    print(f"Confidence functions, batch of {N_ELEMENTS:.0e} elements (median of {REPEATS})")
    header = f"| {'function':<20} | {'dtype':<7} | {'ms/call':>8} | {'Meval/s':>8} | {'x torch.exp':>11} |"
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for name, dtype, seconds, rate, ratio in bench_confidence():
        print(
            f"| {name:<20} | {dtype:<7} | {seconds * 1e3:>8.1f} | {rate / 1e6:>8.2f} | {ratio:>11.1f} |"
        )

    print(f"\nMC dropout, M={M_SAMPLES} samples, MLP {OBS}-{HIDDEN}-{HIDDEN}-{ACT} in train mode")
    header = (
        f"| {'B':>5} | {'batched: 1 pass [M,B,obs] ms':>29} | {'loop: M passes [B,obs] ms':>26} "
        f"| {'speed-up':>8} |"
    )
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for batch in (BATCH, 8):
        batched, looped = bench_mc_dropout(batch)
        print(
            f"| {batch:>5} | {batched * 1e3:>29.3f} | {looped * 1e3:>26.3f} | {looped / batched:>7.2f}x |"
        )


if __name__ == "__main__":
    main()
