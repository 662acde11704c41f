"""Counter-based random streams, one per environment (SplitMix64), so a simulated operator
draws the same numbers for an env whatever batch it sits in."""

from __future__ import annotations

import math

import torch


def _signed(value: int) -> int:
    """A 64-bit constant as the int64 torch stores."""
    return value - (1 << 64) if value >= 1 << 63 else value


_GOLDEN = _signed(0x9E3779B97F4A7C15)
_MIX1 = _signed(0xBF58476D1CE4E5B9)
_MIX2 = _signed(0x94D049BB133111EB)


def _shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def _mix(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64's finaliser (Steele, Lea and Flood, 2014), wrapping int64 arithmetic."""
    x = (x ^ _shift_right(x, 30)) * _MIX1
    x = (x ^ _shift_right(x, 27)) * _MIX2
    return x ^ _shift_right(x, 31)


class EnvStreams:
    """One counter-based random stream per environment (SplitMix64 keyed by seed and env).

    Draw ``j`` of env ``i``'s call ``c`` is a hash of ``(seed, i, c, j)``, where ``c``
    counts the calls in which env ``i`` took part (``active``), so env ``i`` gets the
    same numbers whatever the batch it sits in (its size, its shape, its other envs and
    when they take part), on any device, in one vectorised op.

    Args:
        seed: the operator's seed.
        draws: uniforms per env per call.

    Examples:
        >>> streams = EnvStreams(0, draws=2)
        >>> a = streams.uniform(torch.Size([8]))
        >>> EnvStreams(0, draws=2).uniform(torch.Size([3]))[2].equal(a[2])
        True
    """

    def __init__(self, seed: int, draws: int) -> None:
        self.draws = draws
        self.calls = torch.zeros(0, dtype=torch.int64)
        """Per env, the calls it took part in."""
        self._key = int(_mix(torch.tensor(_signed(int(seed) % (1 << 64)))))
        self._env_keys: tuple[int, torch.device | None, torch.Tensor, torch.Tensor] | None = None
        """(envs, device, each env's key (a hash of the seed and its index), the draw indices): kept between calls."""

    def uniform(self, batch_shape: torch.Size, device: torch.device | None = None,
                active: torch.Tensor | None = None) -> torch.Tensor:
        """The next ``[*batch_shape, draws]`` uniforms in [0, 1) (float64), one call's worth.

        Only the envs of ``active`` (bool, ``batch_shape``; default all) take part: the
        others get numbers too, but their stream does not move on.
        """
        n_envs = math.prod(batch_shape)
        if len(self.calls) < n_envs:
            self.calls = torch.cat([self.calls, self.calls.new_zeros(n_envs - len(self.calls))])
        if self._env_keys is None or self._env_keys[:2] != (n_envs, device):
            env = torch.arange(n_envs, dtype=torch.int64, device=device).unsqueeze(-1)
            draw = torch.arange(self.draws, dtype=torch.int64, device=device)
            self._env_keys = (n_envs, device, _mix(self._key + _GOLDEN * env), draw)
        env_key, draw = self._env_keys[2:]
        counter = self.calls[:n_envs].to(device).unsqueeze(-1) * self.draws + draw
        bits = _mix(env_key + _GOLDEN * (counter + 1)).reshape(*batch_shape, self.draws)
        self.calls[:n_envs] += 1 if active is None else active.reshape(n_envs).to(self.calls.device, torch.int64)
        return _shift_right(bits, 11).to(torch.float64) * 2.0**-53
