"""The simulated operators' reaction times: an ex-Gaussian whose mean grows with the
workload of the moment (docs/operators.md)."""

from __future__ import annotations

import math

import torch

from dcsc_torchrl.humans.traits import OperatorTraits


def ex_gaussian_rt(
    traits: OperatorTraits, workload: torch.Tensor, uniforms: torch.Tensor
) -> torch.Tensor:
    """Ex-Gaussian reaction times whose Gaussian mean grows with the workload.

    ``RT = rt_mu (1 + workload_gain * workload) + rt_sigma * z + rt_tau * e`` with
    ``z ~ N(0, 1)`` (Box-Muller) and ``e ~ Exp(1)`` (inverse CDF), floored at 0.

    Args:
        traits: the RT parameters.
        workload: ``[...]``, >= 0.
        uniforms: ``[..., 3]`` uniforms in [0, 1) (two for z, one for e).

    Returns:
        RT in seconds, ``[...]``, float32.

    Examples:
        >>> rt = ex_gaussian_rt(OperatorTraits(), torch.zeros(4), torch.full((4, 3), 0.5))
        >>> rt.shape
        torch.Size([4])
    """
    u1, u2, u3 = (1.0 - uniforms).unbind(-1)  # in (0, 1]: finite logs
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    e = -torch.log(u3)
    mu = traits.rt_mu * (1.0 + traits.workload_gain * workload.to(z.dtype))
    return (mu + traits.rt_sigma * z + traits.rt_tau * e).clamp_min(0.0).to(torch.float32)
