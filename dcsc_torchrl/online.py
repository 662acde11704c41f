"""Algorithm 1 online: theta (Eq. 19) and the critic learn from every collected batch.

One small class per action kind, as TorchRL has one loss per algorithm:

- :class:`DiscreteOnlineLearner` (LunarLander): :class:`ThetaLoss`, i.e. ``-sum_a pi_theta Q``
  plus the Q critic's TD loss;
- :class:`ContinuousOnlineLearner` (UAV): TorchRL's ``DDPGLoss`` with the shared policy as
  actor and only theta trainable (its actor loss has the gradient of Eq. 19), the
  critic's TD loss keeping it adapting.

:func:`make_online_learner` picks the class from the policy. Both soft-update their
target critic with ``SoftUpdate`` (:class:`~dcsc_torchrl.losses.ForeachSoftUpdate`) and keep :attr:`OnlineLearner.history`, one row per
update (theta, its gradient, both losses).

:class:`PolicyGradientLearner` is the state-dependent arbiter's (:mod:`dcsc_torchrl.state_arbiter`):
TorchRL's ``A2CLoss`` on the shared policy's own frames, a value critic of that policy beside it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator
from torchrl.objectives import A2CLoss, DDPGLoss, LossModule, ValueEstimators

from dcsc_torchrl.losses import AuthorityThetaLoss, ForeachSoftUpdate, ThetaLoss, call_with_params
from dcsc_torchrl.policy import SharedPolicyModule

THETA_OPTIMIZERS = {"sgd": torch.optim.SGD, "adam": torch.optim.Adam}
WARMUP_TARGETS = ("td", "return")
THETA_CRITICS = ("action", "authority")
"""What theta's gradient reads: ``action``, Algorithm 1's critic of the key / action
(``Q(s, a)``); ``authority``, a critic of the authority split (``Q(s, beta)``)."""


class OnlineLearner(ABC):
    """The updates of Algorithm 1 shared by both action kinds, once per collected batch.

    Each collected batch gives ``updates_per_batch`` gradient steps of theta and the
    critic (every step on the whole batch). Subclasses build :attr:`loss` and say which of
    its terms are the critic's and theta's.

    Args:
        policy: the DC-SC shared policy (its arbiter holds theta).
        critic: the pretrained critic network (``Q(s, .)`` or ``Q(s, a)``), trained on.
        theta_lr: alpha of Algorithm 1 (line 15).
        critic_lr: beta of Algorithm 1 (line 12).
        gamma: discount factor.
        tau: soft-update rate of the target critic.
        updates_per_batch: gradient steps per collected batch (>= 1).
        theta_optimizer: ``"sgd"`` (Algorithm 1 line 15 as printed: ``theta += alpha
            grad J``) or ``"adam"`` (the same ascent direction, steps of about ``alpha`` in
            theta's own units whatever the scale of Q: one step size serves both tasks).
    """

    loss: LossModule
    soft_updated: bool = True
    """Whether the loss keeps a target critic that :attr:`targets` soft-updates."""

    def __init__(
        self, policy: SharedPolicyModule, critic: torch.nn.Module, *, theta_lr: float, critic_lr: float,
        gamma: float, tau: float, updates_per_batch: int = 1, theta_optimizer: str = "sgd",
    ) -> None:
        if int(updates_per_batch) != updates_per_batch or updates_per_batch < 1:
            raise ValueError(f"updates_per_batch must be an integer >= 1, got {updates_per_batch!r}")
        check_online_settings(theta_optimizer=theta_optimizer)
        self.policy = policy
        self.critic = critic
        self.gamma = float(gamma)
        self.updates_per_batch = int(updates_per_batch)
        self.loss = self._make_loss(policy, critic)
        self.targets = ForeachSoftUpdate(self.loss, tau=tau) if self.soft_updated else None
        self.theta_optim = THETA_OPTIMIZERS[theta_optimizer](list(policy["arbiter"].parameters()), lr=theta_lr)
        self.critic_optim = torch.optim.Adam(list(self.critic_params.values(True, True)), lr=critic_lr, foreach=True)
        self.history: list[dict[str, Any]] = []

    # -- what each action kind defines ----------------------------------------------------
    @abstractmethod
    def _make_loss(self, policy: SharedPolicyModule, critic: torch.nn.Module) -> LossModule:
        """The TorchRL loss holding the critic (and its target) and theta's term."""

    @property
    @abstractmethod
    def critic_params(self) -> TensorDictBase:
        """The critic's trainable parameters inside :attr:`loss`."""

    @abstractmethod
    def critic_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """The critic's TD loss on a flat batch (Algorithm 1, lines 9-12)."""

    @abstractmethod
    def theta_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """The loss whose theta-gradient is minus Eq. 19, on a flat batch."""

    @abstractmethod
    def taken_value(self, frames: TensorDictBase) -> torch.Tensor:
        """The critic's value of the action taken on each frame of a flat batch, ``[N]``."""

    @abstractmethod
    def action_gap(self, frames: TensorDictBase) -> torch.Tensor:
        """``Q(s, a_machine) - Q(s, a_operator)`` per frame under the current critic.

        Positive where the critic prefers the machine's action: how the protocol checks
        that low-``b_m`` frames are frames where the machine's action is worse.
        """

    # -- the critic's warm-up --------------------------------------------------------------
    def warm_up(self, frames: TensorDictBase, *, target: str, updates: int, batch_size: int, lr: float,
                seed: int) -> float:
        """Fits the critic alone on recorded transitions (the calibration runs), theta untouched.

        The pretrained critic has never seen the task's target (the LunarLander machine is
        pretrained on the centred pad); ``updates`` steps (Adam at ``lr``) on minibatches
        of ``batch_size`` frames drawn (with a generator seeded by ``seed``) give it a start
        before theta learns from it. ``target``:

        - ``"td"``: Algorithm 1's TD loss;
        - ``"return"``: ``Q(s, a_taken)`` regressed on the recorded discounted
          return-to-go. A TD target carries an outcome back one step per update, so
          after a short warm-up the critic still ranks actions mostly by their immediate
          reward; the recorded return carries the landing or the crash to every frame at
          once. ``frames`` must then be first episodes tagged with ``env_index`` /
          ``frame_index`` (:func:`dcsc_torchrl.episodes.run_scenarios`).

        Returns the last minibatch loss (``nan`` with no updates).
        """
        if target not in WARMUP_TARGETS:
            raise ValueError(f"warm-up target must be one of {', '.join(WARMUP_TARGETS)}, got {target!r}")
        frames = frames.reshape(-1)
        returns = returns_to_go(frames, self.gamma) if target == "return" else None
        generator = torch.Generator().manual_seed(seed)
        optim = torch.optim.Adam(self.critic_optim.param_groups[0]["params"], lr=lr, foreach=True)
        loss = torch.tensor(float("nan"))
        for _ in range(updates):
            index = torch.randint(frames.shape[0], (min(batch_size, frames.shape[0]),), generator=generator)
            if returns is None:
                loss = self.critic_loss(frames[index])
            else:
                loss = (self.taken_value(frames[index]) - returns[index]).pow(2).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
            self._soft_update()
        return loss.item()

    def _soft_update(self) -> None:
        if self.targets is not None:
            self.targets.step()

    # -- keeping what was learned -----------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything the learner has learned: theta (the arbiter), the critic and its target
        (the loss), both optimisers and the update history. :meth:`load_state_dict` of a
        learner built the same way continues exactly where this one stopped (``dcsc study``
        resumes a person's session with it)."""
        return {"arbiter": self.policy["arbiter"].state_dict(), "loss": self.loss.state_dict(),
                "theta_optim": self.theta_optim.state_dict(), "critic_optim": self.critic_optim.state_dict(),
                "history": list(self.history)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restores a :meth:`state_dict` (of a learner of the same policy and critic shapes)."""
        self.policy["arbiter"].load_state_dict(state["arbiter"])
        self.loss.load_state_dict(state["loss"])
        self.theta_optim.load_state_dict(state["theta_optim"])
        self.critic_optim.load_state_dict(state["critic_optim"])
        self.history = list(state["history"])

    # -- Algorithm 1, once per collected batch ---------------------------------------------
    def __call__(self, batch: TensorDictBase) -> None:
        batch = batch.reshape(-1)
        theta = self.policy["arbiter"].theta
        for _ in range(self.updates_per_batch):
            loss_critic = self.critic_loss(batch)
            loss_theta = self.theta_loss(batch)
            self.critic_optim.zero_grad()
            self.theta_optim.zero_grad()
            (loss_theta + loss_critic).backward()
            grad = theta.grad.detach().clone()
            self.critic_optim.step()
            self.theta_optim.step()
            self._soft_update()
            self.history.append({
                "update": len(self.history) + 1,
                "theta": theta.detach().tolist(),
                "theta_grad": grad.tolist(),
                "loss_theta": loss_theta.item(),
                "loss_critic": loss_critic.item(),
            })


class DiscreteOnlineLearner(OnlineLearner):
    """Algorithm 1 on a discrete action: :class:`ThetaLoss` over ``Q(s, .)``."""

    def _make_loss(self, policy: SharedPolicyModule, critic: torch.nn.Module) -> ThetaLoss:
        return ThetaLoss(policy, TensorDictModule(critic, ["observation"], ["action_value"]), gamma=self.gamma)

    @property
    def critic_params(self) -> TensorDictBase:
        return self.loss.qvalue_network_params

    def critic_loss(self, batch: TensorDictBase) -> torch.Tensor:
        return self.loss.loss_qvalue(batch)[0]

    def theta_loss(self, batch: TensorDictBase) -> torch.Tensor:
        return self.loss.loss_theta(batch)[0]

    def taken_value(self, frames: TensorDictBase) -> torch.Tensor:
        q = self.loss.action_values(frames, self.critic_params)
        return (q * frames["action"].to(q.dtype)).sum(-1)

    def action_gap(self, frames: TensorDictBase) -> torch.Tensor:
        """As :meth:`OnlineLearner.action_gap`; the machine's action is its most likely key."""
        frames = frames.reshape(-1)
        with torch.no_grad():
            q = self.critic(frames["observation"])
            machine = q.gather(-1, frames["machine_probs"].argmax(-1, keepdim=True))
            human = q.gather(-1, frames["human_action"].argmax(-1, keepdim=True))
        return (machine - human).reshape(-1)


class ContinuousOnlineLearner(OnlineLearner):
    """Algorithm 1 on a continuous action: ``DDPGLoss`` with only theta trainable on the actor side."""

    def _make_loss(self, policy: SharedPolicyModule, critic: torch.nn.Module) -> DDPGLoss:
        loss = DDPGLoss(policy, ValueOperator(critic, in_keys=["observation", "action"]))
        loss.make_value_estimator(ValueEstimators.TD0, gamma=self.gamma)
        return loss

    @property
    def critic_params(self) -> TensorDictBase:
        return self.loss.value_network_params

    def critic_loss(self, batch: TensorDictBase) -> torch.Tensor:
        return self.loss.loss_value(batch)[0]

    def theta_loss(self, batch: TensorDictBase) -> torch.Tensor:
        return self.loss.loss_actor(batch)[0]

    def taken_value(self, frames: TensorDictBase) -> torch.Tensor:
        observed = frames.select("observation", "action").copy()
        return call_with_params(self.loss.value_network, self.critic_params, observed)["state_action_value"].reshape(-1)

    def action_gap(self, frames: TensorDictBase) -> torch.Tensor:
        frames = frames.reshape(-1)
        with torch.no_grad():
            obs = frames["observation"]
            gap = self.critic(obs, frames["machine_action"]) - self.critic(obs, frames["human_action"].float())
        return gap.reshape(-1)


class AuthorityOnlineLearner(OnlineLearner):
    """Theta by Eq. 19 through the authority critic ``Q(s, beta)`` (:class:`AuthorityThetaLoss`), either action kind.

    The critic is fitted on the calibration runs' recorded returns (:meth:`warm_up` with
    ``target="return"``: each frame's stored ``beta``, 0 for the operator alone, 1 for the
    machine alone) and then held: theta learns online from it, the critic does not (a TD
    step would need the next frame's beta, which the arbiter decides only when that frame
    comes). ``critic_lr`` must therefore be 0.
    """

    soft_updated = False

    def __init__(self, policy: SharedPolicyModule, critic: torch.nn.Module, **settings: Any) -> None:
        check_online_settings(theta_critic="authority", **settings)
        super().__init__(policy, critic, **settings)

    def _make_loss(self, policy: SharedPolicyModule, critic: torch.nn.Module) -> AuthorityThetaLoss:
        arbiter = policy["arbiter"]
        return AuthorityThetaLoss(arbiter, TensorDictModule(critic, ["observation", arbiter.out_keys[1]],
                                                            ["state_value"]))

    @property
    def critic_params(self) -> TensorDictBase:
        return self.loss.authority_network_params

    def critic_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Zero: the authority critic is held after its warm-up."""
        return torch.zeros(())

    def theta_loss(self, batch: TensorDictBase) -> torch.Tensor:
        return self.loss.loss_theta(batch)[0]

    def taken_value(self, frames: TensorDictBase) -> torch.Tensor:
        return self.loss.authority_value(frames)

    def action_gap(self, frames: TensorDictBase) -> torch.Tensor:
        """``Q(s, beta=1) - Q(s, beta=0)``: the critic's value of handing the machine all the authority."""
        frames = frames.reshape(-1)
        ones = torch.ones(frames.shape[0], self.policy["arbiter"].dims)
        with torch.no_grad():
            return self.loss.authority_value(frames, ones) - self.loss.authority_value(frames, 0 * ones)

    def warm_up(self, frames: TensorDictBase, *, target: str, **kwargs: Any) -> float:
        if target != "return":
            raise ValueError(f"the authority critic is fitted on recorded returns: warm-up target must be 'return', "
                             f"got {target!r}")
        return super().warm_up(frames, target=target, **kwargs)

    def fit(self, frames: TensorDictBase, *, critic_updates: int, arbiter_updates: int, batch_size: int, lr: float,
            seed: int) -> None:
        """The authority update offline: ``Q(s, beta)`` fitted on the recorded returns of ``frames``
        (:meth:`warm_up`, ``critic_updates`` steps at ``lr``), then ``arbiter_updates`` steps of the
        arbiter against it, the critic held, on minibatches of ``batch_size`` of the same frames
        (drawn with a generator seeded by ``seed``)."""
        self.warm_up(frames, target="return", updates=critic_updates, batch_size=batch_size, lr=lr, seed=seed)
        flat = frames.reshape(-1)
        generator = torch.Generator().manual_seed(seed)
        for _ in range(arbiter_updates):
            index = torch.randint(flat.shape[0], (min(batch_size, flat.shape[0]),), generator=generator)
            loss = self.theta_loss(flat[index])
            self.theta_optim.zero_grad()
            loss.backward()
            self.theta_optim.step()


class PolicyGradientLearner:
    """A state-dependent arbiter learned from the shared policy's own frames (A2C, the machine frozen).

    Eq. 16 asks for ``Q^{pi_theta}``, the value of the *shared* policy; Algorithm 1's critic
    is warmed up on the partners flying alone. Here the arbiter's parameters ``psi`` follow
    the policy gradient of Eq. 14's mixture (:meth:`~dcsc_torchrl.policy.SharedPolicyModule.authority_actor`,
    the machine's stored output read, not rerun) with GAE advantages from a value critic
    ``V(s)`` of the shared policy, fitted on the same frames: TorchRL's ``A2CLoss`` with the
    arbiter as the actor. With a scalar arbiter it is Eq. 19's ascent with the advantage
    in place of ``Q``; with :class:`~dcsc_torchrl.state_arbiter.StateDependentArbiter` the
    gradient reaches the network that makes theta depend on the frame.

    One gradient step per collected batch ``[envs, time]`` (GAE needs the time dimension),
    advantages standardised over the batch, the summed loss's gradient clipped. The batches
    should be ``segment_length`` frames long (the runs that feed it collect that many frames
    per env between updates): with λ = 1 the advantage is the return over the segment, less
    ``V``, so a short segment leaves a key's advantage to the next few frames' shaped reward.

    Args:
        policy: the discrete shared policy whose arbiter learns.
        value_net: ``observation -> state_value``, the shared policy's value critic.
        lr: Adam's step for the arbiter and the value critic.
        gamma: discount factor.
        gae_lambda: GAE's lambda.
        entropy_coeff: weight of the mixture's entropy bonus.
        critic_coeff: weight of the value critic's loss.
        max_grad_norm: the gradient norm a step is clipped to.
        segment_length: frames per env of the batches it should be fed.
    """

    def __init__(self, policy: SharedPolicyModule, value_net: torch.nn.Module, *, lr: float, gamma: float,
                 gae_lambda: float, entropy_coeff: float, critic_coeff: float, max_grad_norm: float,
                 segment_length: int) -> None:
        if int(segment_length) != segment_length or segment_length < 1:
            raise ValueError(f"segment_length must be an integer >= 1, got {segment_length!r}")
        self.policy, self.critic, self.segment_length = policy, value_net, int(segment_length)
        self.loss = A2CLoss(policy.authority_actor(), ValueOperator(value_net, in_keys=["observation"]),
                            entropy_coeff=entropy_coeff, critic_coeff=critic_coeff, loss_critic_type="l2")
        self.loss.make_value_estimator(ValueEstimators.GAE, gamma=gamma, lmbda=gae_lambda)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=lr, foreach=True)
        self.max_grad_norm = float(max_grad_norm)
        self.history: list[dict[str, Any]] = []

    def __call__(self, batch: TensorDictBase) -> None:
        if batch.ndim != 2:
            raise ValueError(f"the policy gradient needs batches [envs, time] (GAE runs along time), got {batch.shape}")
        batch = batch.copy()  # the advantages are this update's, not the run's frames
        with torch.no_grad():
            self.loss.value_estimator(batch)
        advantage = batch.get("advantage")
        batch.set("advantage", (advantage - advantage.mean()) / (advantage.std() + 1e-8))
        terms = self.loss(batch)
        total = terms["loss_objective"] + terms["loss_critic"] + terms.get("loss_entropy", torch.zeros(()))
        self.optim.zero_grad()
        total.backward()
        torch.nn.utils.clip_grad_norm_(list(self.loss.parameters()), self.max_grad_norm)
        self.optim.step()
        self.history.append({
            "update": len(self.history) + 1,
            "theta": self.policy["arbiter"].theta.detach().tolist(),
            "loss_objective": terms["loss_objective"].item(),
            "loss_critic": terms["loss_critic"].item(),
        })

    def state_dict(self) -> dict[str, Any]:
        """The arbiter, the value critic, the optimiser and the history (:meth:`load_state_dict` continues)."""
        return {"arbiter": self.policy["arbiter"].state_dict(), "value": self.critic.state_dict(),
                "optim": self.optim.state_dict(), "history": list(self.history)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restores a :meth:`state_dict` (of a learner of the same shapes)."""
        self.policy["arbiter"].load_state_dict(state["arbiter"])
        self.critic.load_state_dict(state["value"])
        self.optim.load_state_dict(state["optim"])
        self.history = list(state["history"])


def check_online_settings(*, theta_critic: str = "action", theta_optimizer: str = "sgd", critic_lr: float = 0.0,
                          **_: Any) -> None:
    """Refuses, before any work, the ``online`` settings :func:`make_online_learner` would refuse.

    Raises:
        ValueError: one line naming the bad value: an unknown ``theta_critic`` or
            ``theta_optimizer``, or an authority critic with ``critic_lr`` not 0.
    """
    if theta_critic not in THETA_CRITICS:
        raise ValueError(f"online.theta_critic must be one of {', '.join(THETA_CRITICS)}, got {theta_critic!r}")
    if theta_optimizer not in THETA_OPTIMIZERS:
        raise ValueError(f"online.theta_optimizer must be one of {sorted(THETA_OPTIMIZERS)}, got {theta_optimizer!r}")
    if theta_critic == "authority" and critic_lr != 0:
        raise ValueError("the authority critic is fitted on the calibration runs and held: online.critic_lr must be 0 "
                         f"with online.theta_critic=authority, got {critic_lr!r}")


def make_online_learner(policy: SharedPolicyModule, critic: torch.nn.Module, *, theta_critic: str = "action",
                        **settings: Any) -> OnlineLearner:
    """Algorithm 1's learner for ``policy``; ``settings`` are :class:`OnlineLearner`'s keywords.

    ``theta_critic="action"``: the critic of the key (discrete) or action (continuous),
    ``critic`` being the pretrained ``Q(s, .)`` / ``Q(s, a)``; ``"authority"``: the critic
    of the authority split, ``critic`` an :func:`~dcsc_torchrl.networks.authority_critic`.
    """
    check_online_settings(theta_critic=theta_critic, **settings)
    if theta_critic == "authority":
        return AuthorityOnlineLearner(policy, critic, **settings)
    learner = DiscreteOnlineLearner if policy.discrete else ContinuousOnlineLearner
    return learner(policy, critic, **settings)


def returns_to_go(frames: TensorDictBase, gamma: float) -> torch.Tensor:
    """``G_t = sum_k gamma^k r_{t+k}`` to the end of each env's recorded episode, per frame ``[N]``.

    ``frames`` is :attr:`dcsc_torchrl.episodes.EpisodeBatch.frames`: each env's first
    episode, frames tagged with ``env_index`` and ``frame_index`` (several runs' frames:
    :func:`dcsc_torchrl.episodes.concat_runs`, which keeps one ``env_index`` per episode).
    """
    reward = frames["next", "reward"].reshape(-1).double()
    env, step = frames["env_index"].reshape(-1), frames["frame_index"].reshape(-1)
    pairs = env.to(torch.int64) * (int(step.max()) + 1 if step.numel() else 1) + step.to(torch.int64)
    if pairs.unique().numel() != pairs.numel():
        raise ValueError(
            "returns_to_go: two frames share an (env_index, frame_index): frames of several runs were "
            "concatenated without renumbering their envs (use dcsc_torchrl.episodes.concat_runs)"
        )
    out = torch.zeros_like(reward)
    for e in env.unique().tolist():
        rows = (env == e).nonzero().reshape(-1)
        rows = rows[step[rows].argsort()]
        acc = 0.0
        for row in reversed(rows.tolist()):
            acc = reward[row].item() + gamma * acc
            out[row] = acc
    return out.to(torch.get_default_dtype())
