"""The machine side of DC-SC: MC-dropout policy mean, uncertainty and confidence (Eqs. 10, 13)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torch.nn.parameter import is_lazy

from dcsc_torchrl.checks import check_finite, check_in_range, check_values
from dcsc_torchrl.confidence import machine_confidence, mc_dropout_uncertainty
from dcsc_torchrl.networks import FirstDims

_DROPOUT_TYPES = (nn.Dropout, nn.Dropout1d, nn.Dropout2d, nn.Dropout3d, nn.AlphaDropout)

_OUT_KEYS = {
    "probs": ["machine_probs", "machine_uncertainty", "machine_confidence"],
    "action": ["machine_action", "machine_uncertainty", "machine_confidence"],
}


def machine_mean_key(discrete: bool) -> str:
    """Where the MC-dropout machine writes its mean output: ``machine_probs`` (keys) or ``machine_action``."""
    return _OUT_KEYS["probs" if discrete else "action"][0]


def dropout_layers(network: nn.Module) -> list[nn.Module]:
    """Returns the dropout layers of ``network`` (those MC dropout switches on)."""
    return [m for m in network.modules() if isinstance(m, _DROPOUT_TYPES)]


def linear_widths(network: nn.Module) -> tuple[int | None, int | None]:
    """``(input width, output width)`` of ``network`` where its layers say them, else None.

    The input width is known when the network (or its first ``nn.Sequential`` child,
    recursively) starts with an ``nn.Linear`` (its ``in_features``; not a lazy one, whose
    width is set by its first input) or a :class:`~dcsc_torchrl.networks.FirstDims` (its
    ``in_dims``); a network that starts with anything else has no known input width. The
    output width is the last ``nn.Linear``'s ``out_features`` (an MLP, maybe followed by an
    activation).
    """
    first: nn.Module = network
    while isinstance(first, nn.Sequential) and len(first) > 0:
        first = first[0]
    in_width = None
    if isinstance(first, nn.Linear) and not is_lazy(first.weight):
        in_width = first.in_features
    elif isinstance(first, FirstDims):
        in_width = first.in_dims
    linears = [m for m in network.modules() if isinstance(m, nn.Linear)]
    return in_width, (linears[-1].out_features if linears else None)


@contextmanager
def mc_dropout_active(layers: Sequence[nn.Module]) -> Iterator[None]:
    """Switches the dropout ``layers`` (a network's :func:`dropout_layers`) on, then back to eval mode.

    The network's other layers (e.g. batch norm) keep their mode, so the M-sample pass
    samples dropout masks and nothing else.
    """
    for layer in layers:
        layer.train()
    try:
        yield
    finally:
        for layer in layers:
            layer.eval()


class MCDropoutPolicy(TensorDictModuleBase):
    """Machine policy with MC-dropout uncertainty (Eq. 10) and confidence (Eq. 13).

    Draws ``num_samples`` (M) dropout samples of the wrapped actor network in ONE
    batched forward pass (the input is expanded to ``[M, *batch, ...]``; each row gets
    its own dropout mask), and writes

    - the mean policy output: ``machine_probs`` (discrete: softmax of the network's
      logits) or ``machine_action`` (continuous: the network's action),
    - ``machine_uncertainty``: ``c_t = trace(Cov) + d * tau_inv`` (Eq. 10),
    - ``machine_confidence``: ``b_m(c_t)`` (Eq. 13).

    The machine is frozen in DC-SC (Algorithm 1: its parameters phi stay fixed), so the
    pass runs without autograd. Outside the M-sample pass the wrapped network stays in
    eval mode, whatever ``.train()`` is called on this module.

    Every frame is checked where it enters, at one reduction per tensor and no device sync
    (:func:`~dcsc_torchrl.checks.check_values`): the observation's width (a shape
    comparison) and dtype (the network's), its values finite, and the network's M samples
    finite (NaN weights show there).

    Args:
        network: the machine actor; must contain at least one dropout layer with
            ``p > 0`` (otherwise the uncertainty would be 0 on every frame). For
            ``output="probs"`` it maps observations to logits ``[*batch, n]``; for
            ``output="action"`` to actions ``[*batch, d]``.
        output: ``"probs"`` (discrete actions) or ``"action"`` (continuous actions).
        num_samples: M, the number of dropout samples (>= 2: one sample has no variance).
        lam: lambda of Eq. 11, in (0, 1).
        delta2: delta_2 of Eq. 12, > 1.
        tau_inv: the observation noise tau^-1 of Eq. 10, >= 0.
        uncertainty_scale: the unit in which Eq. 13 reads the uncertainty,
            ``b_m = b_m(c_t / uncertainty_scale)`` (> 0; 1: as printed). Eq. 11's tolerance
            C is dimensionless with mean ``1 / ln(1/lambda)`` (about 2 for lambda = 0.6),
            while a small dropout rate gives variances of order 1e-4: read raw, ``b_m`` is
            about 1 on every frame. :func:`calibrated_uncertainty_scale` picks the unit
            from frames seen (the experiments: the operator-alone runs, as HULA's
            threshold is). ``machine_uncertainty`` is written raw either way.
        observation_size: the width of the observation (last dim of ``in_keys[0]``) the
            network was built for; default: the first ``nn.Linear``'s input width, where
            the network starts with one, or the ``in_dims`` of a leading
            :class:`~dcsc_torchrl.networks.FirstDims` (see :func:`linear_widths`).
        in_keys: the observation key(s) fed to ``network``.
        out_keys: where to write mean, uncertainty and confidence; defaults to
            ``["machine_probs" | "machine_action", "machine_uncertainty",
            "machine_confidence"]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> net = torch.nn.Sequential(torch.nn.Linear(8, 32), torch.nn.Tanh(),
        ...                           torch.nn.Dropout(0.1), torch.nn.Linear(32, 4))
        >>> machine = MCDropoutPolicy(net, output="probs", num_samples=10)
        >>> td = machine(TensorDict({"observation": torch.randn(5, 8)}, [5]))
        >>> td["machine_probs"].shape, td["machine_confidence"].shape
        (torch.Size([5, 4]), torch.Size([5, 1]))
    """

    def __init__(
        self,
        network: nn.Module,
        *,
        output: str = "probs",
        num_samples: int = 10,
        lam: float = 0.6,
        delta2: float = 1.05,
        tau_inv: float = 0.0,
        uncertainty_scale: float = 1.0,
        observation_size: int | None = None,
        in_keys: Sequence[NestedKey] = ("observation",),
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        if output not in _OUT_KEYS:
            raise ValueError(f"output must be 'probs' or 'action', got {output!r}")
        if int(num_samples) != num_samples or num_samples < 2:
            raise ValueError(
                f"num_samples must be an integer >= 2 (Eq. 10's variance of one dropout sample is 0 on every "
                f"frame), got {num_samples!r}"
            )
        check_in_range("lam", lam, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
        check_in_range("delta2", delta2, 1.0, float("inf"), low_inclusive=False, high_inclusive=False)
        check_in_range("tau_inv", tau_inv, 0.0, float("inf"), low_inclusive=True, high_inclusive=False)
        check_in_range("uncertainty_scale", uncertainty_scale, 0.0, float("inf"), low_inclusive=False,
                       high_inclusive=False)
        layers = dropout_layers(network)
        if not layers:
            raise ValueError(
                "network has no dropout layer: its MC-dropout uncertainty would always be 0; "
                "add nn.Dropout to the machine actor"
            )
        if all(layer.p == 0 for layer in layers):
            raise ValueError(
                f"network's dropout layers all have p=0 ({len(layers)} of them): its MC-dropout uncertainty "
                "would always be 0; build the machine actor with dropout > 0"
            )
        self.network = network.eval()
        self.dropouts = layers
        """The network's dropout layers, found once (the forward of every frame switches them on)."""
        self.output = output
        self.num_samples = int(num_samples)
        self.lam = lam
        self.delta2 = delta2
        self.tau_inv = tau_inv
        self.uncertainty_scale = float(uncertainty_scale)
        self.in_keys = list(in_keys)
        self.out_keys = list(out_keys) if out_keys is not None else list(_OUT_KEYS[output])
        if len(self.out_keys) != 3:
            raise ValueError(f"out_keys must name 3 entries (mean, uncertainty, confidence), got {self.out_keys}")
        in_width, self.output_size = linear_widths(network)
        if observation_size is not None and (int(observation_size) != observation_size or observation_size < 1):
            raise ValueError(f"observation_size must be an integer >= 1, got {observation_size!r}")
        if observation_size is not None and in_width is not None and observation_size != in_width:
            raise ValueError(
                f"observation_size={observation_size} but the network's first layer reads {in_width} values"
            )
        self.observation_size = observation_size if observation_size is not None else in_width
        """Observation width the network was built for (None: not known)."""

    def check_inputs(self, inputs: Sequence[torch.Tensor]) -> None:
        """The checks of every frame: the observation's width and dtype (free), its values finite.

        Raises:
            ValueError: for an observation of the wrong width or dtype, or with NaN / inf
                values (on a device: a few frames later, see
                :func:`~dcsc_torchrl.checks.check_values`).
        """
        key = self.in_keys[0]
        width = inputs[0].shape[-1] if inputs[0].dim() else 1
        if self.observation_size is not None and width != self.observation_size:
            raise ValueError(
                f"{key!r} has {width} values per frame but the machine network was built for "
                f"{self.observation_size} (observation_size): the env and the checkpoint disagree"
            )
        weight = next(self.network.parameters(), None)
        for name, value in zip(self.in_keys, inputs, strict=True):
            if weight is not None and value.dtype != weight.dtype:
                raise ValueError(
                    f"{name!r} is {value.dtype} but the machine network's parameters are {weight.dtype}: "
                    "convert one of them (e.g. torchrl's DoubleToFloat transform on the env)"
                )
            check_values(str(name), value)

    def train(self, mode: bool = True) -> MCDropoutPolicy:
        super().train(mode)
        self.network.eval()
        return self

    def sample(self, *inputs: torch.Tensor) -> torch.Tensor:
        """M dropout samples of the policy output, ``[M, *batch, d]``, in one forward pass."""
        expanded = [x.expand(self.num_samples, *x.shape) for x in inputs]
        with mc_dropout_active(self.dropouts):
            out = self.network(*expanded)
        return torch.softmax(out, dim=-1) if self.output == "probs" else out

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = []
        for key in self.in_keys:
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(f"the machine reads {key!r}, which is missing from the TensorDict")
            inputs.append(value)
        self.check_inputs(inputs)
        samples = check_values(
            f"the machine network's output ({self.output}, observation finite: look at its weights)", self.sample(*inputs)
        )
        mean, uncertainty = mc_dropout_uncertainty(samples, tau_inv=self.tau_inv)
        confidence = machine_confidence(uncertainty / self.uncertainty_scale, self.lam, self.delta2, validate=False)
        mean_key, uncertainty_key, confidence_key = self.out_keys
        tensordict.set(mean_key, mean)
        tensordict.set(uncertainty_key, uncertainty)
        tensordict.set(confidence_key, confidence)
        return tensordict


def calibrated_uncertainty_scale(
    uncertainty: torch.Tensor, lam: float, delta2: float, *, quantile: float = 0.5
) -> float:
    """The ``uncertainty_scale`` at which the ``quantile`` of ``uncertainty`` gets ``b_m = 1/2``.

    ``b_m`` (Eq. 13) falls from 1 at ``c = 0`` to 0; with this unit the frames seen
    spread over its range: half of them (for the median) above ``b_m = 1/2``, half
    below. The ``c`` of ``b_m(c) = 1/2`` is found by bisection (``b_m`` is strictly
    decreasing, Property 3).

    Args:
        uncertainty: machine uncertainties ``c_t`` seen (any shape, >= 0, some > 0).
        lam: lambda of Eq. 11.
        delta2: delta_2 of Eq. 12.
        quantile: which quantile of ``uncertainty`` maps to ``b_m = 1/2``, in (0, 1).

    Examples:
        >>> c = torch.tensor([1e-4, 2e-4, 3e-4])
        >>> scale = calibrated_uncertainty_scale(c, lam=0.6, delta2=1.05)
        >>> round(machine_confidence(torch.tensor(2e-4 / scale), 0.6, 1.05).item(), 4)
        0.5
    """
    check_in_range("quantile", quantile, 0.0, 1.0, low_inclusive=False, high_inclusive=False)
    values = torch.as_tensor(uncertainty, dtype=torch.float64).reshape(-1)
    check_finite("uncertainty", values)
    reference = float(torch.quantile(values, quantile))
    if not reference > 0:
        raise ValueError(
            f"the {quantile} quantile of the machine's uncertainty is {reference}: the machine "
            "is certain on those frames, there is no scale to calibrate"
        )
    low, high = 0.0, 1.0
    while machine_confidence(torch.tensor(high, dtype=torch.float64), lam, delta2) > 0.5:
        high *= 2.0
    for _ in range(60):
        middle = 0.5 * (low + high)
        if machine_confidence(torch.tensor(middle, dtype=torch.float64), lam, delta2) > 0.5:
            low = middle
        else:
            high = middle
    return reference / (0.5 * (low + high))
