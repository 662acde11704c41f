"""The state-dependent arbiter: its scalar special case is Eq. 15 / the centred form and Eq. 19,
it learns *when* on a scripted task, it saves and loads, and `dcsc arbiter` pretrains one that a
cell refuses next to an operator of its pool or another machine."""

from __future__ import annotations

import copy

import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type

from dcsc_torchrl.arbiters import (
    CentredConfidenceArbiter,
    ConfidenceArbiter,
    load_arbiter,
    save_arbiter,
)
from dcsc_torchrl.checkpoint import CheckpointError, load_checkpoint
from dcsc_torchrl.cli import main
from dcsc_torchrl.losses import ThetaLoss
from dcsc_torchrl.machine import MCDropoutPolicy
from dcsc_torchrl.networks import machine_fingerprint, mlp
from dcsc_torchrl.online import PolicyGradientLearner
from dcsc_torchrl.policy import SharedPolicyModule
from dcsc_torchrl.shipped import shipped_machine, shipped_path
from dcsc_torchrl.state_arbiter import (
    StateDependentArbiter,
    load_pretrained_arbiter,
)
from dcsc_torchrl.tasks import get_task

LUNAR = get_task("lunarlander")


def frames(n: int = 64, *, obs: int = 9, keys: int = 4) -> TensorDict:
    torch.manual_seed(0)
    return TensorDict({
        "observation": torch.randn(n, obs), "machine_confidence": torch.rand(n, 1), "human_confidence": torch.rand(n, 1),
        "human_action": torch.nn.functional.one_hot(torch.randint(0, keys, (n,)), keys).float(),
        "machine_probs": torch.softmax(torch.randn(n, keys), -1),
        "action": torch.nn.functional.one_hot(torch.randint(0, keys, (n,)), keys).float(),
        "next": {"observation": torch.randn(n, obs), "reward": torch.randn(n, 1),
                 "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n])


def shared_policy(arbiter, obs: int = 9, keys: int = 4) -> SharedPolicyModule:
    torch.manual_seed(1)
    net = torch.nn.Sequential(torch.nn.Linear(obs, 8), torch.nn.Dropout(0.1), torch.nn.Linear(8, keys))
    return SharedPolicyModule(MCDropoutPolicy(net), arbiter, OneHot(keys))


@pytest.mark.parametrize(("form", "scalar"), [("paper", lambda: ConfidenceArbiter(0.7)),
                                              ("centred", lambda: CentredConfidenceArbiter(0.7, gain=2.0))])
def test_the_bias_only_case_is_the_scalar_arbiter_and_its_gradient_is_eq_19(form, scalar):
    state = StateDependentArbiter(9, 4, form=form, theta_init=0.7, gain=2.0)
    scalar = scalar()
    batch = frames()
    assert torch.allclose(state(batch.clone())["beta"], scalar(batch.clone())["beta"])  # g_psi starts at zero
    critic = torch.nn.Linear(9, 4)
    grads = []
    for arbiter in (state, scalar):
        loss = ThetaLoss(shared_policy(arbiter), TensorDictModule(critic, ["observation"], ["action_value"]))
        loss.loss_theta(batch)[0].backward()
        grads.append(arbiter.theta.grad.clone())
    assert torch.allclose(grads[0], grads[1], atol=1e-7) and grads[0].abs().sum() > 0  # Eq. 19, by autograd


def test_the_arbiter_learns_when_on_a_scripted_task():
    """Partner A (the operator) is right where x < 0, B (the machine) where x > 0; reward 1 for the right key."""
    torch.manual_seed(0)
    arbiter = StateDependentArbiter(1, 2, hidden=(16,))
    policy = shared_policy(arbiter, obs=1, keys=2)
    learner = PolicyGradientLearner(policy, mlp(1, 1, (16,), activation=torch.nn.Tanh), lr=3e-3, gamma=0.99,
                                    gae_lambda=0.95, entropy_coeff=0.0, critic_coeff=0.5, max_grad_norm=0.5,
                                    segment_length=4)
    actor = policy.authority_actor()

    def batch(n: int = 32, t: int = 4) -> TensorDict:
        x = torch.rand(n, t, 1) * 2 - 1
        right = torch.randint(0, 2, (n, t))
        human = torch.where(x[..., 0] < 0, right, 1 - right)
        machine = torch.where(x[..., 0] > 0, right, 1 - right)
        td = TensorDict({"observation": x, "human_action": torch.nn.functional.one_hot(human, 2).float(),
                         "machine_probs": torch.nn.functional.one_hot(machine, 2).float() * 0.9 + 0.05,
                         "machine_confidence": torch.full((n, t, 1), 0.5),
                         "human_confidence": torch.full((n, t, 1), 0.5)}, [n, t])
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            actor(td)
        done = torch.ones(n, t, 1, dtype=torch.bool)
        td["next"] = TensorDict({"observation": torch.rand(n, t, 1) * 2 - 1, "done": done, "terminated": done,
                                 "reward": (td["action"].argmax(-1) == right).float().unsqueeze(-1)}, [n, t])
        return td

    for _ in range(300):
        learner(batch())
    x = torch.linspace(-1, 1, 21).reshape(-1, 1)
    probe = TensorDict({"observation": x, "human_action": torch.eye(2)[[0] * 21], "machine_probs": torch.full((21, 2), 0.5),
                        "machine_confidence": torch.full((21, 1), 0.5), "human_confidence": torch.full((21, 1), 0.5)}, [21])
    beta = arbiter(probe)["beta"].squeeze(-1)
    away = x.squeeze(-1).abs() > 0.2
    assert (beta[(x.squeeze(-1) < 0) & away] < 0.1).all()  # A's region: the operator
    assert (beta[(x.squeeze(-1) > 0) & away] > 0.9).all()  # B's region: the machine
    assert len(learner.history) == 300 and {"theta", "loss_objective", "loss_critic"} <= set(learner.history[-1])


def test_save_load_gives_the_same_beta_and_refuses_another_form(tmp_path):
    arbiter = StateDependentArbiter(9, 4, form="paper", theta_init=1.0, hidden=(16, 8))
    torch.nn.init.normal_(arbiter.state_term[-1].weight)
    path = save_arbiter(arbiter, tmp_path / "a.pt", task="lunarlander")
    loaded = load_arbiter(path, task="lunarlander")
    batch = frames()
    assert type(loaded) is StateDependentArbiter and loaded.form == "paper"
    assert torch.equal(loaded(batch.clone())["beta"], arbiter(batch.clone())["beta"])
    with pytest.raises(CheckpointError, match="cannot be loaded into a CentredConfidenceArbiter"):
        load_arbiter(path, task="lunarlander", into=CentredConfidenceArbiter())


def test_bad_features_and_arguments_are_refused_in_one_line():
    with pytest.raises(ValueError, match="form must be one of paper, centred, got 'both'"):
        StateDependentArbiter(9, 4, form="both")
    with pytest.raises(ValueError, match="spread"):
        StateDependentArbiter(9, 4, spread=0.0)
    with pytest.raises(ValueError, match="reads 'observation' with 9 values per frame, got shape"):
        StateDependentArbiter(9, 4)(frames(obs=8))
    with pytest.raises(ValueError, match="authority_actor is the discrete mixture"):
        SharedPolicyModule(MCDropoutPolicy(torch.nn.Sequential(torch.nn.Linear(9, 3), torch.nn.Dropout(0.1)),
                                           output="action"), ConfidenceArbiter(), get_task("uav").make_envs(
                               [0], 2, []).full_action_spec["action"]).authority_actor()


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    """A quick `dcsc arbiter lunarlander` next to the shipped machine (its pool: surrogate_noisy)."""
    out = tmp_path_factory.mktemp("arbiter")
    assert main(["arbiter", "lunarlander", "--quick", "--out", str(out), "pretrain.shipped=true"]) == 0
    return out


def test_dcsc_arbiter_pretrains_next_to_the_machine_and_records_its_pool(pretrained):
    arbiter = load_pretrained_arbiter(pretrained / "arbiter.pt", LUNAR)
    machine, _ = shipped_machine(LUNAR, "target")
    assert arbiter.operators == ("surrogate_noisy",) and arbiter.machine == machine_fingerprint(machine)
    rows = pd.read_csv(pretrained / "pretraining.csv")
    assert set(rows["operator"]) == {"surrogate_noisy"} and (rows["first_seed"] >= 40_000).all()
    assert list(rows["beta"]) == [0.0, 1.0]  # the authority algorithm: the pool's constant blends
    assert (pretrained / "fig_state_beta.png").stat().st_size > 0
    data = torch.load(pretrained / "arbiter.pt", weights_only=True)
    assert data["seconds"] > 0 and data["frames"] > 0
    with pytest.raises(ValueError, match="pretrained with operator 'surrogate_noisy'"):
        arbiter.check_evaluated_next_to("surrogate_noisy", machine)
    with pytest.raises(ValueError, match="pretrained next to machine"):
        arbiter.check_evaluated_next_to("expert", shipped_machine(LUNAR, "blind")[0])
    with pytest.raises(ValueError, match="lunarlander-state-arbiter"):
        load_checkpoint(pretrained / "arbiter.pt", task="lunarlander")  # no machine
    del data["settings"]["critic_updates"]  # a file of an earlier version
    torch.save(data, pretrained / "old.pt")
    with pytest.raises(CheckpointError, match=r"lacks the learner's settings \['critic_updates'\]"):
        load_pretrained_arbiter(pretrained / "old.pt", LUNAR)


def test_dcsc_ship_exports_an_arbiter_of_the_shipped_machine_and_refuses_one_of_another(pretrained, tmp_path,
                                                                                      monkeypatch, capsys):
    import shutil

    import dcsc_torchrl.shipped as shipped

    shutil.copy(shipped_path(LUNAR, "target"), tmp_path)
    monkeypatch.setattr(shipped, "SHIPPED_DIR", tmp_path)  # never the package's own files
    assert main(["ship", "lunarlander", str(pretrained / "arbiter.pt")]) == 0
    assert "shipped arbiter in" in capsys.readouterr().err
    exported = load_checkpoint(tmp_path / "lunarlander_target_seed0_state.pt", task="lunarlander-state-arbiter")
    assert exported["command"] == "dcsc arbiter lunarlander pretrain.shipped=true pretrain.observes=target"
    assert load_pretrained_arbiter(tmp_path / "lunarlander_target_seed0_state.pt", LUNAR).operators == (
        "surrogate_noisy",)
    other = torch.load(pretrained / "arbiter.pt", weights_only=True)
    other["machine"] = "0123456789abcdef"  # pretrained next to a machine of one's own
    torch.save(other, tmp_path / "other.pt")
    assert main(["ship", "lunarlander", str(tmp_path / "other.pt")]) == 2
    err = capsys.readouterr().err
    assert "pretrained next to machine 0123456789abcdef, not the shipped one" in err and len(err.splitlines()) == 1


def test_a_cell_runs_dcsc_state_from_the_pretrained_arbiter_and_refuses_its_pool(pretrained, tmp_path, capsys):
    common = ["run", "lunarlander", "--quick", "--methods", "operator", "dcsc_state", "--out", str(tmp_path),
              "pretrain.shipped=true", "pretrain.seeds=[0]", f"state.arbiters=[{pretrained / 'arbiter.pt'}]"]
    assert main([*common, "--operators", "surrogate_noisy"]) == 2
    assert "none was pretrained without operator 'surrogate_noisy'" in capsys.readouterr().err
    assert main([*common, "--operators", "expert"]) == 0
    episodes = pd.read_csv(tmp_path / "lunarlander" / "episodes.csv")
    assert set(episodes.query("phase == 'validation'")["method"]) == {"operator", "dcsc_state"}
    assert set(episodes.query("phase == 'collaboration'")["method"]) == {"dcsc_state"}
    theta = pd.read_csv(tmp_path / "lunarlander" / "theta.csv")
    assert set(theta["method"]) == {"dcsc_state"} and len(theta) > 0
    assert (tmp_path / "lunarlander" / "fig_confidence_state.png").read_bytes()[:4] == b"\x89PNG"  # its traced episode


def test_the_policy_gradient_algorithm_pretrains_and_fine_tunes_in_the_cell(tmp_path, capsys):
    out = tmp_path / "arbiter"
    assert main(["arbiter", "lunarlander", "--quick", "--out", str(out), "pretrain.shipped=true",
                 "state.algorithm=policy_gradient", "state.segment_length=20"]) == 0
    pretrained = load_pretrained_arbiter(out / "arbiter.pt", LUNAR)
    assert pretrained.settings["algorithm"] == "policy_gradient" and pretrained.settings["segment_length"] == 20
    rows = pd.read_csv(out / "pretraining.csv")
    assert list(rows["round"]) == [0] and rows["frames"].iloc[0] > 0
    learner = pretrained.learner(shared_policy(copy.deepcopy(pretrained.arbiter)))
    assert isinstance(learner, PolicyGradientLearner) and learner.segment_length == 20
    assert main(["run", "lunarlander", "--quick", "--methods", "operator", "dcsc_state", "--operators", "expert",
                 "--out", str(tmp_path), "pretrain.shipped=true", "pretrain.seeds=[0]",
                 f"state.arbiters=[{out / 'arbiter.pt'}]", "warmup.refit_state_arbiter=false"]) == 0
    theta = pd.read_csv(tmp_path / "lunarlander" / "theta.csv")
    assert {"loss_objective", "loss_critic"} <= set(theta.columns) and len(theta) > 0
    capsys.readouterr()
    assert main(["run", "lunarlander", "--quick", "--methods", "dcsc_state", "--operators", "expert",
                 "--out", str(tmp_path / "refit"), "pretrain.shipped=true", "pretrain.seeds=[0]",
                 f"state.arbiters=[{out / 'arbiter.pt'}]"]) == 2  # the refit is the default
    err = capsys.readouterr().err
    assert "warmup.refit_state_arbiter refits the authority critic Q(s, beta): this arbiter learns by " \
           "'policy_gradient'" in err and err.count("\n") == 1


def test_a_cell_refits_the_authority_critic_on_its_own_calibration_runs(pretrained):
    """With ``warmup.refit_state_arbiter`` the cell's copy of Q(s, beta) fits the returns of its own
    calibration runs (the operator alone at beta 0, the machine alone at 1) better than the
    pretrained one, and the pretrained arbiter itself is left as it was."""
    from dcsc_torchrl.online import returns_to_go
    from dcsc_torchrl.protocol import ProtocolCell
    from dcsc_torchrl.recipes.grid import checked_grid
    from dcsc_torchrl.recipes.settings import cell_settings

    cfg = checked_grid("lunarlander", quick=True, overrides=["pretrain.shipped=true", "pretrain.seeds=[0]"],
                       operators=["expert"], option="operators").cfg
    assert cfg.warmup.refit_state_arbiter  # the default
    settings = cell_settings(cfg)
    machine, critic = shipped_machine(LUNAR, "target")
    state = load_pretrained_arbiter(pretrained / "arbiter.pt", LUNAR)
    before = copy.deepcopy(state.arbiter.state_dict())
    cell = ProtocolCell(LUNAR, LUNAR.make_operator("expert"), machine, base={}, pretrain_seed=0,
                        human=settings["human"], machine=settings["machine"], arbiter=settings["arbiter"],
                        online=settings["online"], protocol=settings["protocol"], state_arbiter=state)
    cell.calibrate(settings["scenarios"], critic, settings["warmup"])
    _, learners, _ = cell.collaborate(settings["scenarios"].collaboration, ["dcsc_state"])
    frames = cell.calibration_frames.reshape(-1)
    returns = returns_to_go(frames, learners["dcsc_state"].gamma)
    unrefitted = state.learner(shared_policy(copy.deepcopy(state.arbiter)))

    def error(learner) -> float:
        with torch.no_grad():
            return (learner.taken_value(frames) - returns).pow(2).mean().item()

    assert error(learners["dcsc_state"]) < error(unrefitted)
    assert all(torch.equal(value, before[key]) for key, value in state.arbiter.state_dict().items()
               if isinstance(value, torch.Tensor))


@pytest.mark.parametrize(("argv", "line"), [
    (["run", "lunarlander", "--quick", "--methods", "dcsc_state"], "method dcsc_state needs state.arbiters"),
    (["run", "uav", "--quick", "--methods", "dcsc_state"], "method dcsc_state needs state.arbiters"),
    (["arbiter", "uav", "--quick", "state.algorithm=policy_gradient"],
     "state.algorithm policy_gradient learns on Eq. 14's mixture of keys, which task uav does not draw from"),
    (["arbiter", "lunarlander", "--quick", "state.pool=[nobody]"], "state.pool: unknown operator preset"),
    (["arbiter", "lunarlander", "--quick", "state.lr=0"], "state.lr: expected a value > 0, got 0"),
    (["arbiter", "lunarlander", "--quick", "state.algorithm=sarsa"], "state.algorithm: unknown algorithm 'sarsa'"),
    (["arbiter", "lunarlander", "--quick", "state.betas=[0.0,1.5]"], "state.betas: expected a value in [0, 1]"),
])
def test_bad_state_arbiter_settings_are_refused_at_the_door(argv, line, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert line in err and err.count("\n") == 1


def test_the_uav_arbiter_learns_beta_per_action_dimension_and_runs_in_a_cell(tmp_path):
    out = tmp_path / "arbiter"
    assert main(["arbiter", "uav", "--quick", "--out", str(out), "pretrain.shipped=true"]) == 0
    uav = get_task("uav")
    pretrained = load_pretrained_arbiter(out / "arbiter.pt", uav)
    assert pretrained.arbiter.dims == 3 and pretrained.arbiter.in_keys[-1] == "machine_action"
    assert pretrained.settings["algorithm"] == "authority"
    assert (out / "fig_state_beta.png").stat().st_size > 0  # beta against the distance to the nearest obstacle
    assert main(["run", "uav", "--quick", "--methods", "operator", "dcsc_state", "--out", str(tmp_path / "run"),
                 "pretrain.shipped=true", "pretrain.seeds=[0]", f"state.arbiters=[{out / 'arbiter.pt'}]"]) == 0
    episodes = pd.read_csv(tmp_path / "run" / "uav" / "episodes.csv")
    state = episodes.query("phase == 'validation' and method == 'dcsc_state'")
    assert len(state) > 0 and state["mean_beta"].between(0, 1).all()
    theta = pd.read_csv(tmp_path / "run" / "uav" / "theta.csv")
    assert set(theta["method"]) == {"dcsc_state"} and len(theta) > 0
