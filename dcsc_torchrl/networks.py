"""The networks of both tasks, built in one place for pretraining and shared control."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

if TYPE_CHECKING:
    from dcsc_torchrl.task import Task


LUNAR_OBS_DIMS = 9
"""TargetLunarLander's observation: the 8 standard LunarLander values and the pad's x."""

LUNAR_MACHINE_VIEWS: dict[str, int] = {"blind": 8, "target": LUNAR_OBS_DIMS}
"""What TargetLunarLander's machine observes (``network.observes``), as the number of leading
observation values its actor and A2C's V critic read: ``target``, all 9, the pad's x included
(the paper's state ``s_t``, §6.1); ``blind``, the 8 standard values (the peers' goal-masked
copilot, which sees the pilot's action instead: docs/envs.md)."""


def machine_view(network: Mapping[str, Any]) -> str:
    """What the machine of a checkpoint's ``network`` config observes; one written before
    ``network.observes`` existed holds a goal-blind machine.

    Examples:
        >>> machine_view({"hidden": [64, 64]}), machine_view({"observes": "target"})
        ('blind', 'target')
    """
    return network.get("observes", "blind")


def view_recipe_settings(observes: str) -> list[str]:
    """The pretraining recipe's settings of a machine that ``observes``: one that sees the pad
    trains on random pads, a goal-blind one on the centre pad.

    Examples:
        >>> view_recipe_settings("target")
        ['network.observes=target', 'env.random_pad=true']
    """
    return [f"network.observes={observes}", f"env.random_pad={str(observes == 'target').lower()}"]


def lunar_machine_dims(observes: str) -> int:
    """How many observation values a TargetLunarLander machine that ``observes`` reads (:data:`LUNAR_MACHINE_VIEWS`).

    Examples:
        >>> lunar_machine_dims("target"), lunar_machine_dims("blind")
        (9, 8)
        >>> lunar_machine_dims("pad")
        Traceback (most recent call last):
        ...
        ValueError: network.observes: expected one of blind, target, got 'pad'
    """
    if observes not in LUNAR_MACHINE_VIEWS:
        raise ValueError(f"network.observes: expected one of {', '.join(LUNAR_MACHINE_VIEWS)}, got {observes!r}")
    return LUNAR_MACHINE_VIEWS[observes]


class FirstDims(nn.Module):
    """Keeps the first ``n`` of the ``in_dims`` entries of the last dim (the machine's view of the state).

    On TargetLunarLander the machine sees the 8 standard values, not the pad's x
    (docs/architecture.md: the operator knows the target, the machine does not). With
    ``in_dims`` the input's width is checked on every call (a shape comparison, free): an
    observation of another width is refused, never cut to its first ``n`` values.

    Args:
        n: how many leading values are kept (>= 1, at most ``in_dims``).
        in_dims: the width of the input it was built for; ``None``: any width >= ``n``
            (the first ``n`` values are kept, unchecked).

    Examples:
        >>> FirstDims(2, in_dims=3)(torch.tensor([1.0, 2.0, 3.0]))
        tensor([1., 2.])
        >>> FirstDims(8, in_dims=9)(torch.zeros(20))
        Traceback (most recent call last):
        ...
        ValueError: the network's input has 20 values per frame but it was built for 9 (FirstDims(8, in_dims=9))
    """

    def __init__(self, n: int, *, in_dims: int | None = None) -> None:
        super().__init__()
        if in_dims is not None and (int(in_dims) != in_dims or in_dims < 1):
            raise ValueError(f"in_dims must be an integer >= 1, got {in_dims!r}")
        if int(n) != n or n < 1 or (in_dims is not None and n > in_dims):
            raise ValueError(f"n must be an integer in [1, in_dims={in_dims}], got {n!r}")
        self.n = int(n)
        self.in_dims = None if in_dims is None else int(in_dims)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.in_dims is not None and x.shape[-1:] != (self.in_dims,):
            width = x.shape[-1] if x.dim() else "no"
            raise ValueError(
                f"the network's input has {width} values per frame but it was built for {self.in_dims} "
                f"(FirstDims({self.n}, in_dims={self.in_dims}))"
            )
        return x[..., : self.n]

    def extra_repr(self) -> str:
        return f"n={self.n}, in_dims={self.in_dims}"


class ScaledTanh(nn.Module):
    """Maps R to the box ``[low, high]`` with a tanh (the DDPG actor's output layer)."""

    def __init__(self, low: float | torch.Tensor, high: float | torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.low + (torch.tanh(x) + 1) * 0.5 * (self.high - self.low)


class ConcatInputs(nn.Module):
    """Concatenates its inputs on the last dim, then applies ``net`` (Q(s, a) critics)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat(inputs, dim=-1))


def mlp(
    in_dims: int,
    out_dims: int,
    hidden: Sequence[int],
    *,
    dropout: float = 0.0,
    activation: type[nn.Module] = nn.Tanh,
) -> nn.Sequential:
    """An MLP; with ``dropout > 0`` a dropout layer follows every hidden activation.

    The dropout layers are what MC dropout samples (Eq. 10); the paper's Tables A1/A2
    give their probability (0.01 for the A2C actor, 0.05 for the DDPG actor).
    """
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"dropout must be in [0, 1), got {dropout!r}")
    layers: list[nn.Module] = []
    width = in_dims
    for size in hidden:
        layers += [nn.Linear(width, size), activation()]
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        width = size
    layers.append(nn.Linear(width, out_dims))
    return nn.Sequential(*layers)


def orthogonal_init_(net: nn.Module, *, out_gain: float, hidden_gain: float = 2.0**0.5) -> nn.Module:
    """Orthogonal weights and zero biases for every ``nn.Linear`` of ``net``, in place; returns ``net``.

    The hidden layers get ``hidden_gain`` (sqrt 2, for ReLU-like units), the last layer
    ``out_gain``: 0.01 for a policy head (a near-uniform first policy), 1 for a value head
    (Stable-Baselines3's ``ortho_init``; Andrychowicz et al. 2021 measure the small policy
    head among the choices that matter most in on-policy RL).
    """
    linears = [module for module in net.modules() if isinstance(module, nn.Linear)]
    if not linears:
        raise ValueError(f"orthogonal_init_: {type(net).__name__} has no nn.Linear layer")
    for index, layer in enumerate(linears):
        nn.init.orthogonal_(layer.weight, gain=out_gain if index == len(linears) - 1 else hidden_gain)
        nn.init.zeros_(layer.bias)
    return net


def lunar_actor(hidden: Sequence[int], dropout: float, *, obs_dims: int = 8, n_actions: int = 4,
                in_dims: int | None = LUNAR_OBS_DIMS) -> nn.Sequential:
    """TargetLunarLander actor: the first ``obs_dims`` of the ``in_dims`` observation values -> action logits.

    ``in_dims`` is the observation's width (TargetLunarLander's 9); another width is
    refused by the leading :class:`FirstDims` (and by :class:`~dcsc_torchrl.machine.MCDropoutPolicy`,
    which reads it as its ``observation_size``). For another env pass its width (CartPole: 4).
    """
    return nn.Sequential(FirstDims(obs_dims, in_dims=in_dims), mlp(obs_dims, n_actions, hidden, dropout=dropout))


def lunar_critic(hidden: Sequence[int], out_dims: int, *, obs_dims: int = 8,
                 in_dims: int | None = None) -> nn.Sequential:
    """TargetLunarLander critic: V(s) (``out_dims=1``) or Q(s, .) (``out_dims=4``) on the first ``obs_dims`` values.

    With ``in_dims`` (TargetLunarLander's :data:`LUNAR_OBS_DIMS`) the observation's width
    is checked as the actor's is (:func:`lunar_actor`); by default any width ``>= obs_dims``.

    A2C's V critic sees what the actor sees (8 values); the Q critic behind theta's update
    (Algorithm 1's ``Q(s, a; omega)``) sees the whole 9-value state, pad included
    (:data:`LUNAR_QVALUE_DIMS`): otherwise Eq. 19 could never credit the operator for
    steering towards a pad the critic cannot see.
    """
    return nn.Sequential(FirstDims(obs_dims, in_dims=in_dims), mlp(obs_dims, out_dims, hidden))


LUNAR_QVALUE_DIMS = LUNAR_OBS_DIMS
"""The TargetLunarLander Q critic's input: the 8 standard values and the pad's x."""


def uav_actor(hidden: Sequence[int], dropout: float, *, low: float = 0.0, high: float = 3.0) -> nn.Sequential:
    """UAV actor: the 9-value observation -> (rho0, sigma0, tau) in ``[low, high]``."""
    return nn.Sequential(mlp(9, 3, hidden, dropout=dropout, activation=nn.ReLU), ScaledTanh(low, high))


def uav_critic(hidden: Sequence[int]) -> ConcatInputs:
    """UAV critic Q(s, a) on the concatenated observation (9) and action (3)."""
    return ConcatInputs(mlp(12, 1, hidden, activation=nn.ReLU))


class SeparableAuthorityValue(nn.Module):
    """``Q(s, beta) = V(s) + A(beta)``: a state's value plus a value of the authority split alone.

    ``A`` does not read the state, so the slope ``dQ/dbeta`` that theta follows is the same
    on every frame: it is learned where the calibration runs put the two partners on the
    same states (their shared starts), not extrapolated to states only one of them visited.
    """

    def __init__(self, state: nn.Module, authority: nn.Module) -> None:
        super().__init__()
        self.state = state
        self.authority = authority

    def forward(self, observation: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
        return self.state(observation) + self.authority(beta)


def authority_critic(obs_dims: int, beta_dims: int, hidden: Sequence[int] = (64, 64), *,
                     separable: bool = True) -> nn.Module:
    """The authority critic ``Q(s, beta)`` behind theta's update (docs/math.md §6b): the whole
    observation (the LunarLander pad included) and the machine's share of authority -> one value.

    ``separable``: :class:`SeparableAuthorityValue`, ``V(s) + A(beta)`` (two MLPs of
    ``hidden``); otherwise one MLP on the concatenated ``(s, beta)``. Built fresh in every
    cell and fitted on the calibration runs' returns
    (:meth:`dcsc_torchrl.online.OnlineLearner.warm_up`); nothing pretrained feeds it.
    """
    if separable:
        return SeparableAuthorityValue(mlp(obs_dims, 1, hidden), mlp(beta_dims, 1, hidden))
    return ConcatInputs(mlp(obs_dims + beta_dims, 1, hidden))


def machine_from_checkpoint(data: dict, task: Task) -> tuple[nn.Module, nn.Module]:
    """The pretrained machine actor and its critic from a loaded pretraining checkpoint.

    ``data`` is what :func:`dcsc_torchrl.checkpoint.load_checkpoint` returned for
    ``task``; the networks are rebuilt by :attr:`Task.make_networks` from the checkpoint's
    own config, loaded (state dicts :attr:`Task.checkpoint_modules`), and put in eval mode.
    For LunarLander the critic is the Q network ``Q(s, .)`` trained beside A2C; for the
    UAV it is DDPG's ``Q(s, a)``.
    """
    from dcsc_torchrl.checkpoint import load_module_state

    actor, critic = task.make_networks(data["config"]["network"])
    for module, name in zip((actor, critic), task.checkpoint_modules, strict=True):
        load_module_state(module, data["state"][name], name=name)
    return actor.eval(), critic.eval()


def machine_fingerprint(machine_net: nn.Module) -> str:
    """A short hash of the machine's weights: which machine an arbiter was pretrained next to, and a
    cell or a study ran next to (they refuse to be resumed next to another)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(machine_net.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]
