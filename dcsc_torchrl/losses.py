"""Losses of Algorithm 1: the Q critic's TD loss and the theta update of Eq. 19 (discrete).

Each loss's forward first reads the verdicts of the frame checks still pending on a device
(:func:`~dcsc_torchrl.checks.flush_frame_checks`, one sync per batch): a batch holding
a bad frame is refused before anything learns from it. The critics run with their
parameters through :func:`call_with_params`, which survives a Ctrl-C.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch.func import functional_call
from torchrl.objectives import LossModule, SoftUpdate
from torchrl.objectives.utils import distance_loss

from dcsc_torchrl.checks import check_in_range, check_values, flush_frame_checks
from dcsc_torchrl.policy import SharedPolicyModule, check_distribution


def call_with_params(module: TensorDictModule, params: TensorDictBase, tensordict: TensorDictBase) -> TensorDictBase:
    """``module(tensordict)`` run with ``params`` (a TensorDict of its parameters and buffers) in place of its own.

    :func:`torch.func.functional_call` swaps them in and back in a ``try``/``finally``, so
    the module gets its own back whatever ends the call. TensorDict's
    ``with params.to_module(module):`` does not: its ``__exit__`` returns without putting
    them back on an ``Exception``, and on a ``KeyboardInterrupt`` (not an ``Exception``) it
    returns a TensorDict, whose truth value Python then asks for to decide whether to
    swallow the interrupt: ``RuntimeError: Converting a tensordict to boolean value is not
    permitted`` replaced the Ctrl-C.

    Examples:
        >>> net = TensorDictModule(torch.nn.Linear(2, 1), ["x"], ["y"])
        >>> zeros = TensorDict.from_module(net).apply(torch.zeros_like)
        >>> call_with_params(net, zeros, TensorDict({"x": torch.ones(2)}))["y"]
        tensor([0.])
    """
    return functional_call(module, dict(params.flatten_keys(".").items()), (tensordict,))


class ForeachSoftUpdate(SoftUpdate):
    """TorchRL's :class:`~torchrl.objectives.SoftUpdate` (Polyak averaging of every target
    parameter, ``θ' ← θ' + τ (θ − θ')``, a ``lerp_`` each) with all the ``lerp_`` in one
    multi-tensor call.

    TorchRL's ``step`` looks every (source, target) pair up in the loss's TensorDicts on each
    call, which on this project's networks costs about ten times the arithmetic (0.35 against
    0.03 ms a step for the DDPG machine's and critic's 12 tensors). The first step is TorchRL's own
    (its checks, lazy targets); the pairs are then kept, since the loss keeps their storage for
    its life (``load_state_dict`` copies into it). The same values to the bit.

    Examples:
        >>> loss = QCriticLoss(TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["action_value"]))
        >>> targets = ForeachSoftUpdate(loss, tau=0.5)
        >>> with torch.no_grad():
        ...     _ = loss.qvalue_network_params.apply(lambda p: p.add_(1.0))
        >>> targets.step(); targets.step()
        >>> diff = loss.qvalue_network_params["module", "bias"] - loss.target_qvalue_network_params["module", "bias"]
        >>> bool(torch.allclose(diff, torch.full((2,), 0.25)))
        True
    """

    _pairs: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    def step(self) -> None:
        if self._pairs is None:
            super().step()
            sources: list[torch.Tensor] = []
            targets: list[torch.Tensor] = []
            for key, source in self._sources.items():
                target = self._targets.get(f"target_{key}")
                if isinstance(source, TensorDictBase):
                    for leaf, tensor in source.items(True, True):
                        sources.append(tensor.data)
                        targets.append(target.get(leaf).data)
                else:
                    sources.append(source.data)
                    targets.append(target.data)
            self._pairs = (targets, sources)
            return
        torch._foreach_lerp_(*self._pairs, 1.0 - self.eps)


class QCriticLoss(LossModule):
    """TD loss of a discrete Q critic, Algorithm 1 lines 8-12.

    ``y = r + gamma * (1 - terminated) * max_a Q'(s', a)`` with ``Q'`` a target copy of
    the critic (soft-updated with TorchRL's ``SoftUpdate(loss, tau=...)``), and
    ``loss_qvalue = distance(Q(s, a_t), y)``. Trained beside A2C in pretraining (Table A1's off-policy entries)
    and, through :class:`ThetaLoss`, online in DC-SC.

    Args:
        qvalue_network: maps the observation to ``action_value`` ``[*batch, n]``.
        gamma: discount factor in (0, 1].
        loss_function: ``"l2"``, ``"l1"`` or ``"smooth_l1"``.
        delay_qvalue: keep a target copy of the critic (``target_qvalue_network_params``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> qnet = TensorDictModule(torch.nn.Linear(8, 4), ["observation"], ["action_value"])
        >>> loss = QCriticLoss(qnet)
        >>> batch = TensorDict({"observation": torch.randn(3, 8),
        ...     "action": torch.eye(4)[[0, 1, 2]].long(),
        ...     "next": {"observation": torch.randn(3, 8), "reward": torch.randn(3, 1),
        ...              "done": torch.zeros(3, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(3, 1, dtype=torch.bool)}}, [3])
        >>> sorted(loss(batch).keys())
        ['loss_qvalue', 'pred_value', 'target_value']
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read by the loss; change them with ``loss.set_keys(...)``.

        Attributes:
            action_value: the critic's output, one value per action.
            action: the one-hot action taken.
            reward: the reward (under ``"next"``).
            done: the done flag (under ``"next"``).
            terminated: the terminated flag (under ``"next"``); bootstraps stop there.
        """

        action_value: NestedKey = "action_value"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_qvalue", "pred_value", "target_value"]

    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        qvalue_network: TensorDictModule,
        *,
        gamma: float = 0.99,
        loss_function: str = "l2",
        delay_qvalue: bool = True,
    ) -> None:
        super().__init__()
        check_in_range("gamma", gamma, 0.0, 1.0, low_inclusive=False, high_inclusive=True)
        self.gamma = float(gamma)
        self.loss_function = loss_function
        self.delay_qvalue = delay_qvalue
        self.convert_to_functional(qvalue_network, "qvalue_network", create_target_params=delay_qvalue)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        obs_keys = list(self.qvalue_network.in_keys)
        keys = self.tensor_keys
        return [
            *obs_keys,
            keys.action,
            *[("next", key) for key in obs_keys],
            ("next", keys.reward),
            ("next", keys.done),
            ("next", keys.terminated),
        ]

    def action_values(self, tensordict: TensorDictBase, params: TensorDictBase) -> torch.Tensor:
        """The critic's ``Q(s, .)`` on ``tensordict`` with the given parameters."""
        td = tensordict.select(*self.qvalue_network.in_keys, strict=True).copy()
        return call_with_params(self.qvalue_network, params, td).get(self.tensor_keys.action_value)

    def loss_qvalue(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Algorithm 1 lines 9-12 as a loss: ``distance(Q(s, a), r + gamma max_a Q'(s', a))``.

        Raises:
            ValueError: naming the key, for an action that is not one-hot per frame (of the
                critic's width: an action index would broadcast silently) or a NaN / inf reward.
        """
        keys = self.tensor_keys
        action = tensordict.get(keys.action)
        values = self.action_values(tensordict, self.qvalue_network_params)
        if action.shape != values.shape:
            raise ValueError(
                f"the batch's {keys.action!r} has shape {tuple(action.shape)} but the critic gives "
                f"{tuple(values.shape)} action values: store the one-hot action"
            )
        action = check_distribution(str(keys.action), action).to(torch.get_default_dtype())
        pred = (values * action).sum(-1, keepdim=True)
        next_td = tensordict.get("next")
        target_params = self.target_qvalue_network_params if self.delay_qvalue else self.qvalue_network_params
        with torch.no_grad():
            next_value = self.action_values(next_td, target_params).max(-1, keepdim=True).values
            not_terminal = (~next_td.get(keys.terminated)).to(next_value.dtype)
            reward = check_values(str(("next", keys.reward)), next_td.get(keys.reward))
            target = reward + self.gamma * not_terminal * next_value
        loss = distance_loss(pred, target, loss_function=self.loss_function).mean()
        return loss, {"pred_value": pred.detach().mean(), "target_value": target.mean()}

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        flush_frame_checks()
        loss, metadata = self.loss_qvalue(tensordict)
        return TensorDict({"loss_qvalue": loss, **metadata}, batch_size=[])


class ThetaLoss(QCriticLoss):
    """The theta update of Eq. 19 (discrete DC-SC), plus the critic's TD loss.

    ``loss_theta = -sum_a pi_theta(a|s) Q(s, a)`` averaged over the batch, with Q
    detached and ``pi_theta = beta(theta) pi_m + (1 - beta(theta)) pi_h`` (Eq. 14)
    recomputed from the batch's stored ``machine_probs``, ``human_action`` and
    confidences (the MC-dropout pass is not repeated). Its gradient w.r.t. theta is
    exactly Eq. 19, ``-b_t beta (1 - beta) (pi_m - pi_h) . Q``. ``loss_qvalue`` is the
    TD loss of :class:`QCriticLoss`, so Algorithm 1's two updates are one backward pass.

    Args:
        policy: the discrete :class:`~dcsc_torchrl.policy.SharedPolicyModule`; its
            ``arbiter`` and ``blend`` parts are reused (theta lives in the arbiter).
        qvalue_network: the Q critic, ``observation -> action_value [*batch, n]``.
        gamma, loss_function, delay_qvalue: as in :class:`QCriticLoss`.
    """

    out_keys = ["loss_theta", "loss_qvalue", "pred_value", "target_value", "beta"]

    def __init__(self, policy: SharedPolicyModule, qvalue_network: TensorDictModule, **kwargs) -> None:
        if not policy.discrete:
            raise ValueError(
                "ThetaLoss is the discrete theta update; for continuous actions use TorchRL's "
                "DDPGLoss with the SharedPolicyModule as actor (see docs/math.md)"
            )
        super().__init__(qvalue_network, **kwargs)
        self.arbiter = policy["arbiter"]
        self.blend = policy["blend"]

    @property
    def in_keys(self) -> list[NestedKey]:
        return sorted({*super().in_keys, *self.arbiter.in_keys, *self.blend.in_keys} - set(self.arbiter.out_keys), key=str)

    def loss_theta(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``-sum_a pi_theta(a|s) Q(s, a)`` with Q detached (gradient = -Eq. 19).

        Raises:
            ValueError: naming the key, for stored machine probabilities that are not a
                distribution per frame (the blend checks the operator's action).
        """
        machine_key = self.blend.in_keys[1]
        check_distribution(str(machine_key), tensordict.get(machine_key))
        td = tensordict.select(*self.arbiter.in_keys, *self.blend.in_keys, strict=False).copy()
        self.blend(self.arbiter(td))
        probs = td.get(self.blend.out_keys[0])
        with torch.no_grad():
            q = self.action_values(tensordict, self.qvalue_network_params)
        loss = -(probs * q).sum(-1).mean()
        return loss, {"beta": td.get(self.arbiter.out_keys[1]).detach().mean()}

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        flush_frame_checks()
        loss_q, metadata = self.loss_qvalue(tensordict)
        loss_theta, metadata_theta = self.loss_theta(tensordict)
        return TensorDict({"loss_theta": loss_theta, "loss_qvalue": loss_q, **metadata, **metadata_theta}, batch_size=[])


class AuthorityThetaLoss(LossModule):
    """The theta update of Eq. 19 through a critic of the authority, ``Q(s, beta)`` (both action kinds).

    Eq. 19 is the chain rule ``dJ/dtheta = dbeta/dtheta . dJ/dbeta``; Algorithm 1 takes
    ``dJ/dbeta`` one frame at a time from a critic of the *key* or *action*,
    ``(pi_m - pi_h) . Q(s, .)``. Here ``dJ/dbeta`` comes from a critic of the *authority
    split* itself: ``Q(s, beta)`` is the return that follows ``s`` when the machine holds
    ``beta`` of the authority from there on, fitted on recorded returns of runs at known
    betas (the operator alone at 0, the machine alone at 1; docs/math.md §6b).
    ``loss_theta = -Q(s, beta_theta(s))`` averaged over the batch, the critic held, so
    ``-dloss/dtheta = dbeta/dtheta . dQ/dbeta``: DDPG's actor gradient with the arbiter
    as the actor and beta as its action.

    Args:
        arbiter: the learned arbiter (holds theta); it reads the batch's stored confidences.
        authority_network: ``(observation, beta) -> state_value``
            (:func:`dcsc_torchrl.networks.authority_critic`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from dcsc_torchrl.arbiters import CentredConfidenceArbiter
        >>> from dcsc_torchrl.networks import authority_critic
        >>> critic = TensorDictModule(authority_critic(9, 1, [8]), ["observation", "beta"], ["state_value"])
        >>> loss = AuthorityThetaLoss(CentredConfidenceArbiter(), critic)
        >>> batch = TensorDict({"observation": torch.randn(3, 9), "machine_confidence": torch.rand(3, 1),
        ...                     "human_confidence": torch.rand(3, 1)}, [3])
        >>> sorted(loss(batch).keys())
        ['beta', 'loss_theta']
    """

    out_keys = ["loss_theta", "beta"]

    authority_network: TensorDictModule
    authority_network_params: TensorDictParams
    target_authority_network_params: None

    def __init__(self, arbiter: TensorDictModule, authority_network: TensorDictModule) -> None:
        super().__init__()
        self.arbiter = arbiter
        self.convert_to_functional(authority_network, "authority_network", create_target_params=False)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        return sorted({self.authority_network.in_keys[0], *self.arbiter.in_keys}, key=str)

    def authority_value(self, tensordict: TensorDictBase, beta: torch.Tensor | None = None) -> torch.Tensor:
        """``Q(s, beta)`` per frame ``[N]``: at the batch's stored ``beta``, or at ``beta`` given."""
        obs_key, beta_key = self.authority_network.in_keys
        td = tensordict.select(obs_key, *([] if beta is not None else [beta_key]), strict=True).copy()
        if beta is not None:
            td.set(beta_key, beta)
        call_with_params(self.authority_network, self.authority_network_params, td)
        return td.get(self.authority_network.out_keys[0]).reshape(-1)

    def loss_theta(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``-Q(s, beta_theta(s))`` with the critic held (gradient = -Eq. 19 through ``Q(s, beta)``)."""
        td = self.arbiter(tensordict.select(*self.arbiter.in_keys, strict=False).copy())
        beta = td.get(self.arbiter.out_keys[1])
        obs_key = self.authority_network.in_keys[0]
        frame = tensordict.select(obs_key).copy()
        frame.set(self.authority_network.in_keys[1], beta)
        call_with_params(self.authority_network, self.authority_network_params.detach(), frame)
        loss = -frame.get(self.authority_network.out_keys[0]).mean()
        return loss, {"beta": beta.detach().mean()}

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        flush_frame_checks()
        loss, metadata = self.loss_theta(tensordict)
        return TensorDict({"loss_theta": loss, **metadata}, batch_size=[])
