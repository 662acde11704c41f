"""How long the ``dcsc`` command takes to answer: help, a sub-command's help, a config typo.

Each command runs as a fresh subprocess (what a person typing it waits for: interpreter
start, imports, the answer), ``--repeats`` times; the table gives the median and the
fastest. None of these may import torch (tests/test_cli.py checks that; this measures it).

    python bench/bench_cli.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMANDS = {
    "dcsc --help": ["--help"],
    "dcsc run --help": ["run", "--help"],
    "dcsc pretrain --help": ["pretrain", "--help"],
    "dcsc pretrain mars (argparse error)": ["pretrain", "mars"],
    "dcsc pretrain lunarlander train.episodez=5": ["pretrain", "lunarlander", "train.episodez=5"],
    "dcsc run uav scenarios.validation_scenarios=-4": ["run", "uav", "scenarios.validation_scenarios=-4"],
}


def dcsc() -> list[str]:
    """The installed ``dcsc`` script next to this interpreter, else ``python -m dcsc_torchrl.cli``."""
    script = Path(sys.executable).with_name("dcsc")
    return [str(script)] if script.exists() else [sys.executable, "-m", "dcsc_torchrl.cli"]


def time_command(argv: list[str], repeats: int, cwd: str) -> tuple[list[float], int]:
    seconds, code = [], 0
    for _ in range(repeats):
        start = time.perf_counter()
        code = subprocess.run([*dcsc(), *argv], capture_output=True, cwd=cwd).returncode
        seconds.append(time.perf_counter() - start)
    return seconds, code


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="runs per command (default 7)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as cwd:
        time_command(["--help"], 1, cwd)  # warm the file cache once
        print(f"{'command':50s} {'exit':>4s} {'median s':>9s} {'min s':>7s}")
        for label, argv in COMMANDS.items():
            seconds, code = time_command(argv, args.repeats, cwd)
            print(f"{label:50s} {code:4d} {statistics.median(seconds):9.3f} {min(seconds):7.3f}")


if __name__ == "__main__":
    main()
