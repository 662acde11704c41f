"""The shared-control protocol end to end (quick scale), and Algorithm 1's online update."""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch
from torchrl.collectors import Collector

from dcsc_torchrl.checkpoint import load_checkpoint
from dcsc_torchrl.methods import build_policy, make_arbiter, task_methods
from dcsc_torchrl.networks import machine_from_checkpoint
from dcsc_torchrl.online import DiscreteOnlineLearner
from dcsc_torchrl.recipes.reproduce import reproduce
from dcsc_torchrl.recipes.settings import task_config
from dcsc_torchrl.recipes.shared_control import run_task
from dcsc_torchrl.tasks import get_task
from dcsc_torchrl.transforms import HumanConfidenceTransform, HumanOperatorTransform

EPISODE_COLUMNS = {"task", "method", "operator", "pretrain_seed", "phase", "group", "seed", "success", "steps",
                   "return", "path_length", "hula_threshold"}
TRACE_COLUMNS = {"knowledge", "human_confidence", "machine_confidence", "confidence_ratio", "step", "reward"}


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """``make reproduce QUICK=1``'s code path, run once in a scratch directory."""
    root = tmp_path_factory.mktemp("reproduce")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        summary = reproduce(quick=True, workers=2)  # as `make reproduce QUICK=1`: 2 Ray workers
    return root, summary


@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_quick_reproduce_writes_every_output(quick_run, task):
    root, summary = quick_run
    out = root / "results" / "quick" / task
    episodes = pd.read_csv(out / "episodes.csv")
    assert set(episodes.columns) >= EPISODE_COLUMNS
    val = episodes[episodes["phase"] == "validation"]
    assert set(val["method"]) == set(task_methods(get_task(task)))  # the UAV has no rule-based switch
    assert sorted(val.loc[val["method"] == "constant", "constant_beta"].unique()) == [0.0, 0.5, 1.0]
    assert set(episodes["phase"]) == {"operator_alone", "machine_alone", "collaboration", "validation"}
    assert set(val["group"]) == {1, 2}
    assert val[["return", "steps", "hula_threshold"]].map(math.isfinite).all().all()
    if task == "uav":
        assert val["path_length"].map(math.isfinite).all()
    trace = pd.read_csv(out / "trace.csv")
    assert set(trace.columns) >= TRACE_COLUMNS
    assert set(trace["method"]) == set(task_methods(get_task(task))) - {"constant"}
    numeric = trace.select_dtypes("number")
    assert numeric.map(math.isfinite).all().all()
    for name in ["fig_performance", "fig_confidence", "fig_actions", "fig_reward", "fig_constant_beta", "fig_theta"] + (
        ["fig_trajectory"] if task == "uav" else []
    ):
        assert (out / f"{name}.png").stat().st_size > 5000, name
    text = (out / "summary.md").read_text()
    assert "DC-SC" in text and "±" in text
    assert summary.exists() and task in summary.read_text()


@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_theta_changes_during_dcsc_runs(quick_run, task):
    root, _ = quick_run
    theta = pd.read_csv(root / "results" / "quick" / task / "theta.csv")
    assert set(theta["phase"]) == {"collaboration", "validation"}
    values = theta["theta"].map(eval).tolist()
    assert values[0] != values[-1]


@pytest.mark.parametrize("task", ["lunarlander", "uav"])
def test_hula_hands_control_to_the_operator_exactly_above_the_threshold(quick_run, task):
    root, _ = quick_run
    out = root / "results" / "quick" / task
    threshold = pd.read_csv(out / "episodes.csv")["hula_threshold"].iloc[0]
    hula = pd.read_csv(out / "trace.csv").query("method == 'hula'")
    betas = hula[[c for c in hula.columns if c.startswith("beta")]].to_numpy()
    machine_in_control = (hula["machine_uncertainty"] <= threshold).to_numpy()
    assert ((betas == 1).all(1) == machine_in_control).all() and ((betas == 0).all(1) == ~machine_in_control).all()


def test_same_seed_gives_identical_episodes_csv(quick_run, tmp_path):
    root, _ = quick_run
    pretrained = root / "runs" / "quick" / "pretrain_lunarlander"
    run_task("lunarlander", quick=True, out=tmp_path, overrides=[f"pretrain.out_dir={pretrained}"])
    again = pd.read_csv(tmp_path / "lunarlander" / "episodes.csv")
    first = pd.read_csv(root / "results" / "quick" / "lunarlander" / "episodes.csv")
    pd.testing.assert_frame_equal(again, first)


def test_first_theta_update_follows_the_sign_of_eq19(quick_run):
    root, _ = quick_run
    task = get_task("lunarlander")
    cfg = task_config(task, quick=True)
    data = load_checkpoint(root / "runs" / "quick" / "pretrain_lunarlander" / "seed0" / "checkpoint.pt",
                           task="lunarlander")
    machine, critic = machine_from_checkpoint(data, task)
    env = task.make_envs([0, 1, 2, 3], cfg.protocol.max_steps,
                         [HumanOperatorTransform(task.make_operator("noisy"), seed=0), HumanConfidenceTransform(**cfg.human)])
    policy = build_policy(machine, make_arbiter("dcsc", task.action_dims, theta_init=0.5),
                          env.full_action_spec["action"], discrete=True, **cfg.machine)
    torch.manual_seed(0)
    collector = Collector(env, policy, frames_per_batch=40, total_frames=40, auto_register_policy_transforms=False)
    batch = next(iter(collector)).reshape(-1)
    collector.shutdown()
    learner = DiscreteOnlineLearner(policy, critic, theta_lr=0.1, critic_lr=1e-4, gamma=0.99, tau=1e-3)
    with torch.no_grad():
        theta = policy["arbiter"].theta.clone()
        b = batch["confidence_ratio"]
        beta = torch.sigmoid(theta * b)
        q = critic(batch["observation"])
        grad_j = (b * beta * (1 - beta) * ((batch["machine_probs"] - batch["human_action"]) * q).sum(-1, keepdim=True)).mean()
    learner(batch)
    step = policy["arbiter"].theta.detach() - theta
    assert grad_j.abs() > 0
    assert torch.sign(step).item() == torch.sign(grad_j).item()
    torch.testing.assert_close(step, 0.1 * grad_j.reshape(1), rtol=1e-4, atol=1e-7)


def test_authority_critic_with_calibration_blends_runs_end_to_end(quick_run, tmp_path):
    """The option path of the protocol: blends on the calibration scenarios, theta by Q(s, beta),
    no constant sweep in validation (the report draws its figures all the same)."""
    root, _ = quick_run
    pretrained = root / "runs" / "quick" / "pretrain_lunarlander"
    out = run_task("lunarlander", quick=True, out=tmp_path, operators=["expert"],
                   methods=["operator", "machine", "dcsc_centred"],
                   overrides=[f"pretrain.out_dir={pretrained}", "online.theta_critic=authority",
                              "scenarios.blend_runs=2", "warmup.blend_betas=[0.25,0.75]"])
    episodes = pd.read_csv(out / "episodes.csv")
    blends = episodes[episodes["phase"] == "calibration_blend"]
    assert sorted(blends["constant_beta"].unique()) == [0.25, 0.75]
    assert (blends.groupby("constant_beta")["seed"].apply(list) == [[10_000, 10_001]] * 2).all()
    assert set(episodes.loc[episodes["phase"] == "validation", "method"]) == {"operator", "machine", "dcsc_centred"}
    theta = pd.read_csv(out / "theta.csv")
    assert (theta["loss_critic"] == 0).all() and theta["theta"].nunique() > 1
    assert (out / "fig_performance.png").exists() and not (out / "fig_constant_beta.png").exists()


@pytest.mark.parametrize("shared_action", ["sample", "mode"])
def test_the_mode_of_the_mixture_keeps_the_operators_key_below_half_the_authority(shared_action):
    """``protocol.shared_action``: at a constant beta = 0.4 the mode is the operator's key on
    every frame; sampling hands some frames to the machine's keys."""
    from dcsc_torchrl.episodes import run_scenarios
    from dcsc_torchrl.networks import lunar_actor
    from dcsc_torchrl.protocol import ProtocolSettings

    task = get_task("lunarlander")
    cfg = task_config(task, quick=True)
    env = task.make_envs([0, 1], 40, [HumanOperatorTransform(task.make_operator("expert"), seed=0),
                                      HumanConfidenceTransform(**cfg.human)])
    torch.manual_seed(0)
    policy = build_policy(lunar_actor([16], 0.1), make_arbiter("constant", 1, constant_beta=0.4),
                          env.full_action_spec["action"], discrete=True, **cfg.machine)
    settings = ProtocolSettings(shared_action=shared_action)
    frames = run_scenarios(env, policy, task, rollout_length=5, exploration_type=settings.exploration_type).frames
    same = (frames["action"] == frames["human_action"]).all(-1)
    assert same.all() if shared_action == "mode" else not same.all()


def test_an_unknown_shared_action_is_refused():
    from dcsc_torchrl.config import ConfigError

    with pytest.raises(ConfigError, match="protocol.shared_action must be one of sample, mode, got 'argmax'"):
        task_config(get_task("lunarlander"), ["protocol.shared_action=argmax"])


def test_plays_operator_alone_holds_even_when_the_machine_puts_all_its_mass_on_another_key():
    """Below half the authority the mode is the operator's key even against a machine
    certain of another key (its probabilities exactly 1 and 0 in float32); at 1/2 it ties."""
    from tensordict import TensorDict
    from torchrl.data import OneHot
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from dcsc_torchrl.arbiters import ConstantArbiter
    from dcsc_torchrl.machine import MCDropoutPolicy
    from dcsc_torchrl.policy import SharedPolicyModule, plays_operator_alone

    net = torch.nn.Sequential(torch.nn.Linear(9, 4), torch.nn.Dropout(0.1))
    with torch.no_grad():
        net[0].weight.zero_()
        net[0].bias.copy_(torch.tensor([100.0, -100.0, -100.0, -100.0]))  # p_m = (1, 0, 0, 0) exactly
    human = torch.eye(4)[torch.arange(64) % 3 + 1].long()  # never the machine's key
    frames = TensorDict({"observation": torch.randn(64, 9), "human_action": human,
                         "human_confidence": torch.rand(64, 1)}, [64])
    for beta in (0.0, 0.1, 0.25, 0.4, 0.49, 0.5, 0.6):
        policy = SharedPolicyModule(MCDropoutPolicy(net, num_samples=4), ConstantArbiter(beta, 1), OneHot(4))
        with set_exploration_type(ExplorationType.MODE):
            action = policy(frames.clone())["action"]
        assert plays_operator_alone(beta, discrete=True, mode=True) == (action == human).all().item(), beta


def test_the_mode_of_a_tied_mixture_is_one_key_the_first():
    """At beta = 1/2 against a machine certain of key 0 (p_m exactly (1, 0, 0, 0)), the operator's
    key and key 0 tie at 1/2. TorchRL's mode marked both (a two-hot action, refused by the
    critic's loss: a LunarLander cell of the full run failed on it); the mode is key 0 alone."""
    from tensordict import TensorDict
    from torchrl.data import OneHot
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from dcsc_torchrl.arbiters import ConstantArbiter
    from dcsc_torchrl.machine import MCDropoutPolicy
    from dcsc_torchrl.policy import OneHotMixture, SharedPolicyModule, check_distribution

    net = torch.nn.Sequential(torch.nn.Linear(9, 8), torch.nn.Dropout(0.1), torch.nn.Linear(8, 4))
    with torch.no_grad():  # the hidden layer is 0 whatever dropout draws: p_m = (1, 0, 0, 0) on every sample
        for layer in (net[0], net[2]):
            layer.weight.zero_()
            layer.bias.zero_()
        net[2].bias.copy_(torch.tensor([100.0, -100.0, -100.0, -100.0]))
    human = torch.eye(4)[torch.arange(8) % 3 + 1].long()
    frames = TensorDict({"observation": torch.randn(8, 9), "human_action": human,
                         "human_confidence": torch.rand(8, 1)}, [8])
    policy = SharedPolicyModule(MCDropoutPolicy(net, num_samples=4), ConstantArbiter(0.5, 1), OneHot(4))
    with set_exploration_type(ExplorationType.MODE):
        out = policy(frames)
    assert (out["probs"].max(-1).values == 0.5).all() and (out["machine_probs"][:, 0] == 1).all()
    assert out["action"].equal(torch.eye(4, dtype=torch.long)[[0] * 8])
    check_distribution("action", out["action"])
    untied = torch.tensor([[0.1, 0.6, 0.2, 0.1]])
    assert OneHotMixture(probs=untied).mode.equal(torch.tensor([[0, 1, 0, 0]]))


def test_a_constant_beta_that_plays_the_operator_alone_takes_the_operators_episodes():
    """The operator's episodes reused for the sweep's beta 0 and 0.3 are the rows playing them gives."""
    from dcsc_torchrl.protocol import run_cell
    from dcsc_torchrl.recipes.settings import cell_settings

    task = get_task("lunarlander")
    cfg = task_config(task, ["scenarios.operator_runs=1", "scenarios.machine_alone_runs=1",
                             "scenarios.validation_scenarios=3", "protocol.group_size=1", "protocol.max_steps=80",
                             "protocol.shared_action=mode", "arbiter.constant_betas=[0.0,0.3,0.6]"], quick=True)
    torch.manual_seed(0)
    machine, critic = task.make_networks({"hidden": [16], "actor_dropout": 0.1})

    def constant_rows(methods: tuple[str, ...]) -> pd.DataFrame:
        cell = run_cell(task, task.make_operator("noisy"), machine, critic, operator_name="noisy", pretrain_seed=0,
                        methods=methods, **cell_settings(cfg))
        rows = pd.DataFrame(cell.episodes)
        return rows[(rows["phase"] == "validation") & (rows["method"] == "constant")].reset_index(drop=True)

    replayed, played = constant_rows(("operator", "constant")), constant_rows(("constant",))
    pd.testing.assert_frame_equal(replayed.drop(columns="mean_beta"), played.drop(columns="mean_beta"))
    assert replayed["mean_beta"].tolist() == pytest.approx(played["mean_beta"].tolist())
    assert sorted(replayed["constant_beta"].unique()) == [0.0, 0.3, 0.6]
