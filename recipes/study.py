"""``dcsc study TASK --participant ID``: a person through the paper's protocol (§6.1), on either task.

The protocol of a simulated cell (:class:`~dcsc_torchrl.protocol.ProtocolCell`), with a
person at the controls of one env at a time:

1. **practice** — the person alone on the operator-alone scenarios (20; seeds 10,000..):
   the paper's 20 runs to learn the task, and the cell's calibration runs;
2. **calibration** (nothing to fly) — HULA's threshold and the unit of the machine's
   uncertainty from the person's own practice frames; the machine alone on the same
   scenarios, headless; the critic's warm-up on both (:meth:`ProtocolCell.calibrate_with`);
3. **collaboration** — DC-SC in the config's form (``arbiter.form``) on 20 scenarios
   (seeds 20,000..), theta and the critic learning online (Algorithm 1);
4. **validation** — the validation scenarios (50; seeds 0..): the machine alone, headless,
   then the person flies each scenario once with DC-SC (still learning), once with HULA and
   once alone, the three in a counterbalanced order (:func:`validation_order`) that the
   window does not name (it shows no confidence or authority in this phase either).

Seeds, settings and code are those of ``dcsc run``: a person's rows and a simulated
operator's are the same kind of row, and the machine-alone rows are the simulated cells'
own. The episode counts are the config's ``scenarios.*`` keys (``--short``: 5 / 5 / 10, a
first try of about 10 minutes on LunarLander).

Outputs in ``OUT/<task>/<participant>/`` (default ``results/study``): ``episodes.csv``,
``trace.csv`` (every frame of each method's first validation scenario, as a cell's),
``frames.csv`` (every frame the person flew), ``theta.csv``, ``calibration.csv``,
``summary.md`` and ``fig_*.png`` (the simulated grid's report); ``study.json`` (the plan and
the config); ``episodes/`` (one folder per episode flown, ``episode.json`` written last) and
``calibration/``. ``dcsc study TASK --gather`` writes ``OUT/<task>/study.md``, the table over
participants.

Resume: the same command again continues at the first episode not finished (Esc, a closed
window, Ctrl-C or a crash lose only the episode in flight, replayed from its start, and
the learner's state is the one saved after the last finished episode). A folder whose
``study.json`` holds another plan or config is refused with the keys that differ.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import sys
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from dcsc_torchrl.config import ConfigError, UsageError, config_diff, to_plain, writable_folder
from dcsc_torchrl.episodes import EpisodeBatch, concat_runs, in_first_episode
from dcsc_torchrl.methods import learned_method
from dcsc_torchrl.networks import machine_fingerprint
from dcsc_torchrl.online import OnlineLearner
from dcsc_torchrl.protocol import ProtocolCell, Scenarios, run_seed
from dcsc_torchrl.recipes.folder import TABLES, folder_lock, write_csv
from dcsc_torchrl.recipes.machines import ready_machine
from dcsc_torchrl.recipes.settings import cell_settings, task_config
from dcsc_torchrl.report import (
    read_table,
    success_grid,
    summary_table,
    write_task_figures,
    write_task_summary,
)
from dcsc_torchrl.runlog import write_atomic
from dcsc_torchrl.task import Task
from dcsc_torchrl.transforms import HumanOperator

SHORT = ("scenarios.operator_runs=5", "scenarios.collaboration_runs=5", "scenarios.validation_scenarios=10",
         "protocol.group_size=5")
"""``--short``: a first try (5 practice, 5 collaboration, 10 validation scenarios a method)."""
PERSON_METHODS = ("hula", "operator")
"""What the person flies in validation besides DC-SC in the config's form."""
RECORD = "study.json"


class StudyStopped(Exception):
    """The participant stopped the session (Esc, Q or the window closed)."""


@dataclasses.dataclass(frozen=True)
class StudyEpisode:
    """One entry of a study's plan: a method on scenarios (one for the person, all at once for
    the machine alone), ``index`` the position of ``seeds[0]`` in its phase's scenarios."""

    phase: str
    method: str
    seeds: tuple[int, ...]
    index: int

    @property
    def person(self) -> bool:
        """Whether the person flies it (the machine alone is played headless)."""
        return self.method != "machine"

    def name(self, position: int) -> str:
        """Its folder in ``episodes/``: plan position, phase, method, first scenario."""
        return f"{position:03d}-{self.phase}-{self.method.replace('/', '_')}-{self.seeds[0]}"


def validation_order(methods: Sequence[str], scenario: int, participant: str) -> list[str]:
    """The order in which the person flies ``methods`` on validation scenario number ``scenario``.

    Scenario ``i`` takes permutation ``(start + i) mod m!`` of ``methods`` (``start`` a hash of
    the participant's id): over every ``m!`` consecutive scenarios each method is flown
    first, second and third equally often, and each method precedes each other equally
    often; participants start at different permutations.

    Examples:
        >>> [validation_order(["a", "b", "c"], i, "p1") for i in range(2)]
        [['b', 'c', 'a'], ['c', 'a', 'b']]
    """
    orders = list(itertools.permutations(methods))
    return list(orders[(zlib.crc32(participant.encode()) + scenario) % len(orders)])


def study_plan(scenarios: Scenarios, learned: str, participant: str) -> list[StudyEpisode]:
    """Every entry of a study in order (the calibration comes between practice and collaboration)."""
    plan = [StudyEpisode("operator_alone", "operator", (seed,), i) for i, seed in enumerate(scenarios.operator_alone)]
    plan += [StudyEpisode("collaboration", learned, (seed,), i) for i, seed in enumerate(scenarios.collaboration)]
    plan.append(StudyEpisode("validation", "machine", tuple(scenarios.validation), 0))
    for i, seed in enumerate(scenarios.validation):
        plan += [StudyEpisode("validation", method, (seed,), i)
                 for method in validation_order([learned, *PERSON_METHODS], i, participant)]
    return plan


class StatusDisplay(TensorDictModuleBase):
    """Runs ``policy``, then hands the person the lines they see on the next frame, and stops
    the run when they ask to (:class:`StudyStopped`).

    ``show``: b_h, b_m and beta (per action dimension) from the policy's output; else no
    line at all, so that nothing on screen names the method flown.
    """

    def __init__(self, policy: TensorDictModuleBase, person: HumanOperator, lines: Sequence[str], *,
                 show: bool) -> None:
        super().__init__()
        self.policy, self.person, self.lines, self.show = policy, person, list(lines), show
        self.in_keys, self.out_keys = policy.in_keys, policy.out_keys

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.person.quit_requested:
            raise StudyStopped
        tensordict = self.policy(tensordict)
        self.person.status = [*self.lines, *(status_lines(tensordict) if self.show else [])]
        return tensordict


STATUS_KEYS = (("human_confidence", "b_h (you)"), ("machine_confidence", "b_m (machine)"),
               ("beta", "beta (machine share)"))


def status_lines(tensordict: TensorDictBase) -> list[str]:
    """b_h, b_m and beta (each component of a vector) of env 0, those the TensorDict holds."""
    return [f"{label}: " + " ".join(f"{v:.2f}" for v in tensordict.get(key).reshape(-1).tolist())
            for key, label in STATUS_KEYS if key in tensordict.keys()]


def first_episode_update(learner: OnlineLearner) -> Callable[[TensorDictBase], None]:
    """``learner`` on the frames of a one-env batch up to its episode's end (the person flies
    one episode; what a held env adds after it is not a transition)."""

    def update(batch: TensorDictBase) -> None:
        learner(batch[in_first_episode(batch["next", "done"].squeeze(-1))].unsqueeze(0))

    return update


class Study:
    """One participant's study on ``task``: the plan, what is done, and the runs (see the module docstring).

    Args:
        task: the registered task.
        cfg: the task's protocol config (:func:`~dcsc_torchrl.recipes.settings.task_config`).
        participant: the participant's id (the ``operator`` column).
        folder: the participant's folder.
        person: the person at the controls (:attr:`Task.make_person`, or a scripted one in tests).
        machine, critic: the pretrained actor and critic.
    """

    def __init__(self, task: Task, cfg: DictConfig, participant: str, folder: Path, person: HumanOperator,
                 machine: torch.nn.Module, critic: torch.nn.Module) -> None:
        self.task, self.cfg, self.participant, self.folder, self.person = task, cfg, participant, folder, person
        self.critic_net = critic
        self.machine_hash = machine_fingerprint(machine)
        settings = cell_settings(cfg)
        self.scenarios: Scenarios = settings["scenarios"]
        self.warmup = settings["warmup"]
        self.learned = learned_method(cfg.arbiter.form)
        self.plan = study_plan(self.scenarios, self.learned, participant)
        self.pretrain_seed = int(cfg.pretrain.seeds[0])
        self.cell = ProtocolCell(
            dataclasses.replace(task, make_envs=self._envs), person, machine,
            base={"task": task.name, "operator": participant, "pretrain_seed": self.pretrain_seed},
            pretrain_seed=self.pretrain_seed, human=settings["human"], machine=settings["machine"],
            arbiter=settings["arbiter"], online=settings["online"], protocol=settings["protocol"],
            machine_alone_operator=task.make_operator(cfg.operator.main))
        self.learner: OnlineLearner | None = None

    # -- the files ---------------------------------------------------------------------
    def record(self) -> dict[str, Any]:
        """What ``study.json`` holds: the participant, the plan, the config and the machine (a hash of its weights)."""
        return {"task": self.task.name, "participant": self.participant,
                "plan": [entry.name(k) for k, entry in enumerate(self.plan)], "config": to_plain(self.cfg),
                "machine": self.machine_hash}

    def claim(self) -> None:
        """Writes ``study.json``, or refuses a folder whose record holds another plan or config."""
        path = self.folder / RECORD
        if path.exists():
            old, new = json.loads(path.read_text()), json.loads(json.dumps(self.record()))
            if "machine" not in old:  # a study begun before the record kept its machine
                new.pop("machine")
            changed = config_diff(old, new)
            if changed:
                raise ConfigError(f"{self.folder} holds a study of another plan or config ({'; '.join(changed[:5])}): "
                                  "resume it with the same command, or choose another --participant or --out")
        self.folder.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.record(), indent=1)
        write_atomic(path, lambda f: f.write(text))

    def entry_dir(self, position: int) -> Path:
        return self.folder / "episodes" / self.plan[position].name(position)

    def done(self, position: int) -> bool:
        return (self.entry_dir(position) / "episode.json").exists()

    def read_entry(self, position: int) -> dict[str, Any]:
        return json.loads((self.entry_dir(position) / "episode.json").read_text())

    # -- the runs ----------------------------------------------------------------------
    def _envs(self, seeds: Sequence[int], max_steps: int | None, transforms: Sequence[Any]) -> Any:
        """The task's envs; one scenario flown by the person is drawn for their window."""
        env = self.task.make_envs(seeds, max_steps, transforms, render=len(seeds) == 1)
        if hasattr(self.person, "frame_source") and hasattr(env.base_env, "render"):
            self.person.frame_source = env.base_env.render
        return env

    def calibrate(self) -> None:
        """The calibration from the practice episodes (once; then read back from ``calibration/``)."""
        folder = self.folder / "calibration"
        if (folder / "calibration.json").exists():
            saved = json.loads((folder / "calibration.json").read_text())
            self.cell.hula_threshold, self.cell.uncertainty_scale = saved["hula_threshold"], saved["uncertainty_scale"]
            self.cell.critic = copy.deepcopy(self.critic_net)
            self.cell.critic.load_state_dict(torch.load(folder / "critic.pt", weights_only=True))
            return
        practice = [k for k, entry in enumerate(self.plan) if entry.phase == "operator_alone"]
        frames = [torch.load(self.entry_dir(k) / "frames.pt", weights_only=False) for k in practice]
        rows = [row for k in practice for row in self.read_entry(k)["rows"]]
        alone = EpisodeBatch(rows, frames=concat_runs(*frames))
        print("calibrating on your practice runs (the machine alone flies its runs now)", file=sys.stderr, flush=True)
        machine_rows, calibration = self.cell.calibrate_with(alone, self.scenarios, self.critic_net, self.warmup)
        folder.mkdir(parents=True, exist_ok=True)
        write_atomic(folder / "critic.pt", lambda f: torch.save(self.cell.critic.state_dict(), f), binary=True)
        record = {"hula_threshold": self.cell.hula_threshold, "uncertainty_scale": self.cell.uncertainty_scale,
                  "calibration": calibration, "rows": machine_rows}
        text = json.dumps(record, indent=1)
        write_atomic(folder / "calibration.json", lambda f: f.write(text))  # last: the calibration is done

    def restore_learner(self) -> OnlineLearner:
        """DC-SC's learner: fresh from the calibrated critic, or as the last finished episode left it."""
        if self.learner is None:
            self.learner = self.cell.learner(self.cell.policy(self.learned))
            saved = [k for k, entry in enumerate(self.plan)
                     if entry.method == self.learned and self.done(k)]
            if saved:
                self.learner.load_state_dict(torch.load(self.entry_dir(saved[-1]) / "learner.pt", weights_only=False))
        return self.learner

    def fly(self, position: int) -> None:
        """Plays plan entry ``position`` and writes its folder, ``episode.json`` last."""
        entry = self.plan[position]
        learner = self.restore_learner() if entry.method == self.learned else None
        policy = learner.policy if learner is not None else self.cell.policy(entry.method)
        seed = None  # the machine alone is the simulated cells' run, its seed too
        if entry.person:  # each episode of the person's is a run of its own
            seed = run_seed(self.cfg.seed, self.pretrain_seed, entry.phase, f"{entry.method}/{entry.seeds[0]}")
        updates_before = len(learner.history) if learner is not None else 0
        if entry.person:
            total = sum(e.phase == entry.phase and e.person for e in self.plan)
            done = sum(e.phase == entry.phase and e.person for e in self.plan[:position])
            title = f"{entry.phase.replace('operator_alone', 'practice').replace('_', ' ')}: episode {done + 1} of {total}"
            if not self.person.prompt([title, "press Space to start (Esc: stop here, resume later)"]):
                raise StudyStopped
            policy = StatusDisplay(policy, self.person, [title], show=entry.phase != "validation")
        result = self.cell.play(entry.phase, entry.method, entry.seeds, policy,
                                update=None if learner is None else first_episode_update(learner), trace=True,
                                hold_done=True, torch_seed=seed)
        folder = self.entry_dir(position)
        folder.mkdir(parents=True, exist_ok=True)
        if entry.phase == "operator_alone":
            write_atomic(folder / "frames.pt", lambda f: torch.save(result.frames, f), binary=True)
        if learner is not None:
            write_atomic(folder / "learner.pt", lambda f: torch.save(learner.state_dict(), f), binary=True)
        record = {
            "rows": self.cell.rows(entry.phase, entry.method, entry.seeds, result, first_index=entry.index),
            "trace": self.cell.traced(entry.phase, entry.method, entry.seeds, result),
            "theta": [{**self.cell.base, "method": entry.method, "phase": entry.phase, **h}
                      for h in (learner.history[updates_before:] if learner is not None else [])],
        }
        text = json.dumps(record, default=float)
        write_atomic(folder / "episode.json", lambda f: f.write(text))  # last: the episode is done

    def run(self) -> bool:
        """Every entry not done yet, in order; ``True`` when the study is complete."""
        practice_end = next(k for k, entry in enumerate(self.plan) if entry.phase != "operator_alone")
        try:
            for position in range(len(self.plan)):
                if position == practice_end:
                    self.calibrate()
                if not self.done(position):
                    self.fly(position)
        except StudyStopped:
            return False
        return True

    # -- the tables and the report -----------------------------------------------------
    def gather(self, *, complete: bool, quick: bool = False) -> None:
        """The participant's tables from the finished episodes (and the report once complete)."""
        entries = [self.read_entry(k) for k in range(len(self.plan)) if self.done(k)]
        calibration_path = self.folder / "calibration" / "calibration.json"
        calibration = json.loads(calibration_path.read_text()) if calibration_path.exists() else None
        practice = sum(entry.phase == "operator_alone" for entry in self.plan)
        episodes = [row for entry in entries[:practice] for row in entry["rows"]]
        if calibration is not None:  # the threshold the practice runs gave, as a cell's calibration rows hold it
            episodes = [{**row, "hula_threshold": calibration["hula_threshold"]} for row in episodes]
            episodes += calibration["rows"]
        episodes += [row for entry in entries[practice:] for row in entry["rows"]]
        frames = [row for entry in entries for row in entry["trace"]]
        first = self.scenarios.validation[0] if len(self.scenarios.validation) else None
        tables = {"episodes": episodes,
                  "trace": [row for row in frames if row["phase"] == "validation" and row["seed"] == first],
                  "theta": [row for entry in entries for row in entry["theta"]],
                  "calibration": [] if calibration is None else [calibration["calibration"]]}
        for name in TABLES:
            if tables[name]:
                write_csv(tables[name], self.folder / f"{name}.csv")
        if frames:
            write_csv(frames, self.folder / "frames.csv")
        if complete:
            write_task_summary(self.folder, self.task, self.participant, self.pretrain_seed, quick=quick)
            write_task_figures(self.folder, self.task, self.participant, self.pretrain_seed)


def run_study(task: Task, participant: str, *, out: Path = Path("results/study"), overrides: Sequence[str] = (),
              short: bool = False, quick: bool = False, checkpoint: Path | None = None,
              person: HumanOperator | None = None) -> Path:
    """Runs (or resumes) ``participant``'s study on ``task``; returns their folder.

    Everything is checked before the window opens: the config, the folder, the machine.
    ``person`` defaults to the task's person at the keys (:attr:`Task.make_person`).
    """
    cfg = task_config(task, [*(SHORT if short else ()), *overrides], quick=quick)
    folder = writable_folder(Path(out) / task.name / participant)
    machine, critic = ready_machine(task, cfg, checkpoint)
    torch.set_num_threads(cfg.threads)
    with folder_lock(folder):
        if person is None:
            from dcsc_torchrl.humans import NoDisplayError

            try:
                person = task.make_person(float(cfg.human.t_d))
            except NoDisplayError as error:
                raise UsageError(str(error)) from None
        study = Study(task, cfg, participant, folder, person, machine, critic)
        study.claim()
        try:
            complete = study.run()
        finally:
            person.close()
            study.gather(complete=False)
        if complete:
            study.gather(complete=True, quick=quick)
    left = sum(not study.done(k) for k in range(len(study.plan)))
    print(f"study of {participant}: " + ("complete" if complete else f"stopped, {left} episodes left (run the same "
          "command to resume)") + f"; files in {folder}", file=sys.stderr, flush=True)
    return folder


def gather_participants(task: Task, out: Path = Path("results/study")) -> Path:
    """``OUT/<task>/study.md``: every participant's validation success and the study's table.

    Raises:
        UsageError: no participant's ``episodes.csv`` under ``OUT/<task>/``.
    """
    root = Path(out) / task.name
    tables = [read_table(path) for path in sorted(root.glob("*/episodes.csv"))]
    if not tables:
        raise UsageError(f"--out {out}: no participant of {task.name} there (no {root}/<participant>/episodes.csv)")
    validation = pd.concat(tables, ignore_index=True)
    validation = validation[validation["phase"] == "validation"]
    text = "\n".join([
        f"# {task.title}: the study over {validation['operator'].nunique()} participant(s)\n",
        "Validation success (%) per method and participant (mean ± 95% CI over scenarios):\n",
        success_grid(validation, task),
        "\n## Pooled over participants\n",
        summary_table(validation, task),
        "",
    ])
    path = root / "study.md"
    write_atomic(path, lambda f: f.write(text))
    return path
