"""The compute a person waits for in ``dcsc study``: a ``--short`` study, timed end to end.

    python bench/bench_study.py [--tasks lunarlander uav]

The participant is the tests' scripted one (``tests/test_study.py``: it presses keys in turn
and its clock never sleeps), flying next to the shipped seed-0 machine, so the wall time is
the pipeline's alone: calibration, the machine's runs, the learner's updates, the files and
the report. Divided by the frames the person flew it bounds the compute per frame from
above; a study runs at the person's pace while that stays under the frame time (20 ms at
LunarLander's 50 frames/s, 100 ms at the UAV's 10 steps/s). The scripted participant's
episodes are not a person's lengths: this measures cost per frame, not a session's length.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_study import PEOPLE, SHIPPED, ScriptedParticipant  # noqa: E402

from dcsc_torchrl.recipes.study import run_study  # noqa: E402
from dcsc_torchrl.tasks import get_task  # noqa: E402

FRAME_MS = {"lunarlander": 1000 / 50, "uav": 1000 / 10}


def time_study(task: str, out: Path) -> tuple[float, int]:
    """Seconds of a ``--short`` study with the scripted participant, and the frames it flew."""
    make, keys = PEOPLE[task]
    script = ScriptedParticipant(keys)
    start = time.perf_counter()
    run_study(get_task(task), "bench", out=out, short=True, person=make(script), overrides=SHIPPED)
    return time.perf_counter() - start, script.frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(PEOPLE), choices=list(PEOPLE))
    args = parser.parse_args()
    print("| task | wall s | person frames | ms per frame (upper bound) | frame time ms |")
    print("|---|---:|---:|---:|---:|")
    for task in args.tasks:
        with tempfile.TemporaryDirectory() as tmp:
            wall, frames = time_study(task, Path(tmp))
        print(f"| {task} | {wall:.1f} | {frames:,} | {1000 * wall / max(frames, 1):.1f} | {FRAME_MS[task]:.0f} |")


if __name__ == "__main__":
    main()
