"""LunarLander with a landing pad that moves between episodes (the paper's discrete task).

The pad is centred on one of the inner terrain chunks 1..9 of 11, drawn from the env's
seeded RNG at every reset, so its x takes nine values in [-0.8, 0.8] (the normalised
units of ``obs[0]``). The terrain is flat under the pad and the flags are drawn there.
The observation is gymnasium's eight values plus the pad's x; the shaping reward is
measured relative to the pad. This follows the moved-pad LunarLander of the
shared-autonomy work (Reddy et al., 2018, "deepassist"), with the success rule of
docs/envs.md: both legs down between the flags and at rest.

Examples:
    >>> import gymnasium as gym
    >>> import envs
    >>> env = gym.make("dcsc/TargetLunarLander-v0")
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, bool(info["success"])
    ((9,), False)
    >>> done = False
    >>> while not done:
    ...     obs, reward, terminated, truncated, info = env.step(target_heuristic(obs))
    ...     done = terminated or truncated
    >>> bool(info["success"])
    True
"""

from __future__ import annotations

import math
from typing import Any

import Box2D
import gymnasium as gym
import numba
import numpy as np
from Box2D.b2 import edgeShape, fixtureDef, polygonShape, revoluteJointDef
from gymnasium import spaces
from gymnasium.envs.box2d.lunar_lander import (
    INITIAL_RANDOM,
    LANDER_POLY,
    LEG_AWAY,
    LEG_DOWN,
    LEG_H,
    LEG_SPRING_TORQUE,
    LEG_W,
    SCALE,
    VIEWPORT_H,
    VIEWPORT_W,
    ContactDetector,
    LunarLander,
)
from gymnasium.utils import EzPickle

__all__ = [
    "CHUNKS",
    "PAD_CHUNKS",
    "PAD_HALF_WIDTH",
    "STAND_FRAMES",
    "TargetLunarLander",
    "pad_x_of_chunk",
    "heuristic_key",
    "target_heuristic",
]

CHUNKS = 11
"""Terrain chunks across the screen (gymnasium's value)."""
PAD_CHUNKS = tuple(range(1, CHUNKS - 1))
"""Chunks the pad may be centred on: the inner ones, 1..9."""
CENTRE_CHUNK = CHUNKS // 2
"""The chunk of gymnasium's fixed pad (``random_pad=False``)."""
PAD_HALF_WIDTH = 2 / (CHUNKS - 1)
"""Half the pad's width in the normalised units of ``obs[0]`` (the pad spans the chunk each side
of its centre): 0.2."""
STAND_FRAMES = 50
"""Consecutive frames standing on the pad that count as landed when Box2D keeps it awake."""
MAX_PARTICLES = 32
"""Flame particles kept alive when rendering (more than one render per frame ever shows)."""

_W = VIEWPORT_W / SCALE
_H = VIEWPORT_H / SCALE
_CHUNK_X = [_W / (CHUNKS - 1) * i for i in range(CHUNKS)]
_MAIN_ENGINE_COST = 0.30
_SIDE_ENGINE_COST = 0.03
_CRASH_REWARD = -100.0
_LANDING_REWARD = 100.0
_APPROACH_HEIGHT = 0.2
_ABOVE_PAD = 0.03


def pad_x_of_chunk(chunk: int) -> float:
    """Pad centre of a terrain chunk, in the normalised units of ``obs[0]``.

    Args:
        chunk: terrain chunk index in ``PAD_CHUNKS``.

    Returns:
        ``(chunk_x - W/2) / (W/2)``: -0.8 for chunk 1, 0 for chunk 5, 0.8 for chunk 9.
    """
    return (_CHUNK_X[chunk] - _W / 2) / (_W / 2)


class TargetLunarLander(LunarLander):
    """Discrete LunarLander whose landing pad sits at a random x per episode.

    Rewards (docs/envs.md): the change of the shaping
    ``-100 |(x - pad_x, y)| - 100 |v| - 100 |angle| + 10 (leg_l + leg_r)``, minus 0.3 per
    frame of main engine and 0.03 per frame of side engine; −100 replaces it on a crash
    (body contact or leaving the screen) and +100 on landing on the pad.

    Termination: success when both legs are between the flags and the lander is at rest
    there (Box2D's "not awake"; a body at rest without a crash stands on its legs) or has
    stood there on both legs for ``STAND_FRAMES`` consecutive frames; at rest anywhere
    else ends the episode with no bonus (``landed_outside``); a crash ends it with
    ``crashed``. ``info`` always holds ``success``, ``crashed`` and ``landed_outside`` as
    numpy bools (so TorchRL's ``auto_register_info_dict`` can read them). The 1000-frame
    timeout is the ``TimeLimit`` of the registered id.

    Args:
        render_mode: ``None`` (fast: no flame particles), ``"rgb_array"`` or ``"human"``.
        gravity: as gymnasium's LunarLander.
        enable_wind: as gymnasium's LunarLander.
        wind_power: as gymnasium's LunarLander.
        turbulence_power: as gymnasium's LunarLander.
        random_pad: if ``False`` the pad stays at the centre, as in the standard task.
    """

    def __init__(
        self,
        render_mode: str | None = None,
        gravity: float = -10.0,
        enable_wind: bool = False,
        wind_power: float = 15.0,
        turbulence_power: float = 1.5,
        random_pad: bool = True,
    ) -> None:
        super().__init__(
            render_mode=render_mode,
            continuous=False,
            gravity=gravity,
            enable_wind=enable_wind,
            wind_power=wind_power,
            turbulence_power=turbulence_power,
        )
        EzPickle.__init__(
            self, render_mode, gravity, enable_wind, wind_power, turbulence_power, random_pad
        )
        self.random_pad = random_pad
        low = np.append(self.observation_space.low, -1.0).astype(np.float32)
        high = np.append(self.observation_space.high, 1.0).astype(np.float32)
        self.observation_space = spaces.Box(low, high)
        self.pad_chunk = CENTRE_CHUNK
        self.pad_x = 0.0
        self._pad_prev_shaping: float | None = None
        self._frames_on_pad = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, np.bool_]]:
        """Draws the pad, builds terrain and lander, and takes gymnasium's first no-op step.

        Args:
            seed: seeds ``self.np_random`` (the same seed gives the same pad, terrain and
                initial push).
            options: unused; accepted for the gymnasium API.

        Returns:
            The first observation (9 values) and the info dict.
        """
        gym.Env.reset(self, seed=seed)
        self._destroy()
        # A fresh world each episode, as gymnasium does (Gymnasium issue #728).
        self.world = Box2D.b2World(gravity=(0, self.gravity))
        self.world.contactListener_keepref = ContactDetector(self)
        self.world.contactListener = self.world.contactListener_keepref
        self.game_over = False
        self.prev_shaping = None
        self._pad_prev_shaping = None
        self._frames_on_pad = 0

        self.pad_chunk = (
            int(self.np_random.integers(PAD_CHUNKS[0], PAD_CHUNKS[-1] + 1))
            if self.random_pad
            else CENTRE_CHUNK
        )
        self.pad_x = pad_x_of_chunk(self.pad_chunk)
        self._create_terrain()
        self._create_lander()
        if self.render_mode == "human":
            self.render()
        obs, *_ = self.step(0)
        return obs, _info()

    def _create_terrain(self) -> None:
        """Random hills as gymnasium's, flat over the pad's chunk and its two neighbours."""
        self.helipad_x1 = _CHUNK_X[self.pad_chunk - 1]
        self.helipad_x2 = _CHUNK_X[self.pad_chunk + 1]
        self.helipad_y = _H / 4
        height = self.np_random.uniform(0, _H / 2, size=(CHUNKS,))
        height[max(self.pad_chunk - 2, 0) : self.pad_chunk + 3] = self.helipad_y
        padded = np.concatenate([height[:1], height, height[-1:]])
        smooth_y = (padded[:-2] + padded[1:-1] + padded[2:]) / 3
        smooth_y[self.pad_chunk - 1 : self.pad_chunk + 2] = self.helipad_y

        self.moon = self.world.CreateStaticBody(shapes=edgeShape(vertices=[(0, 0), (_W, 0)]))
        self.sky_polys = []
        for i in range(CHUNKS - 1):
            p1 = (_CHUNK_X[i], float(smooth_y[i]))
            p2 = (_CHUNK_X[i + 1], float(smooth_y[i + 1]))
            self.moon.CreateEdgeFixture(vertices=[p1, p2], density=0, friction=0.1)
            self.sky_polys.append([p1, p2, (p2[0], _H), (p1[0], _H)])
        self.moon.color1 = (0.0, 0.0, 0.0)
        self.moon.color2 = (0.0, 0.0, 0.0)

    def _create_lander(self) -> None:
        """Lander body and legs at the top centre with a random push (gymnasium's)."""
        initial_x, initial_y = _W / 2, _H
        self.lander = self.world.CreateDynamicBody(
            position=(initial_x, initial_y),
            angle=0.0,
            fixtures=fixtureDef(
                shape=polygonShape(vertices=[(x / SCALE, y / SCALE) for x, y in LANDER_POLY]),
                density=5.0,
                friction=0.1,
                categoryBits=0x0010,
                maskBits=0x001,
                restitution=0.0,
            ),
        )
        self.lander.color1 = (128, 102, 230)
        self.lander.color2 = (77, 77, 128)
        self.lander.ApplyForceToCenter(
            (
                self.np_random.uniform(-INITIAL_RANDOM, INITIAL_RANDOM),
                self.np_random.uniform(-INITIAL_RANDOM, INITIAL_RANDOM),
            ),
            True,
        )
        if self.enable_wind:
            self.wind_idx = self.np_random.integers(-9999, 9999)
            self.torque_idx = self.np_random.integers(-9999, 9999)

        self.legs = []
        for i in (-1, +1):
            leg = self.world.CreateDynamicBody(
                position=(initial_x - i * LEG_AWAY / SCALE, initial_y),
                angle=i * 0.05,
                fixtures=fixtureDef(
                    shape=polygonShape(box=(LEG_W / SCALE, LEG_H / SCALE)),
                    density=1.0,
                    restitution=0.0,
                    categoryBits=0x0020,
                    maskBits=0x001,
                ),
            )
            leg.ground_contact = False
            leg.color1 = (128, 102, 230)
            leg.color2 = (77, 77, 128)
            joint = revoluteJointDef(
                bodyA=self.lander,
                bodyB=leg,
                localAnchorA=(0, 0),
                localAnchorB=(i * LEG_AWAY / SCALE, LEG_DOWN / SCALE),
                enableMotor=True,
                enableLimit=True,
                maxMotorTorque=LEG_SPRING_TORQUE,
                motorSpeed=+0.3 * i,
            )
            joint.lowerAngle, joint.upperAngle = (0.4, 0.9) if i == -1 else (-0.9, -0.4)
            leg.joint = self.world.CreateJoint(joint)
            self.legs.append(leg)
        self.drawlist = [self.lander, *self.legs]

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, np.bool_]]:
        """Advances the physics one frame (gymnasium's) and scores it relative to the pad.

        Args:
            action: 0 no-op, 1 left engine, 2 main engine, 3 right engine.

        Returns:
            ``(obs, reward, terminated, truncated, info)``; ``truncated`` is always
            ``False`` here (the registered id adds the 1000-frame ``TimeLimit``).
        """
        state, _, _, _, _ = super().step(action)
        if len(self.particles) > MAX_PARTICLES:
            self._trim_particles()
        obs = np.empty(9, dtype=np.float32)
        obs[:8] = state
        obs[8] = self.pad_x

        x, y, vx, vy, angle, _, leg_l, leg_r = state.tolist()
        shaping = (
            -100 * math.hypot(x - self.pad_x, y)
            - 100 * math.hypot(vx, vy)
            - 100 * abs(angle)
            + 10 * leg_l
            + 10 * leg_r
        )
        reward = 0.0 if self._pad_prev_shaping is None else shaping - self._pad_prev_shaping
        self._pad_prev_shaping = shaping
        if action == 2:
            reward -= _MAIN_ENGINE_COST
        elif action in (1, 3):
            reward -= _SIDE_ENGINE_COST

        over_pad = self._legs_over_pad()
        standing = over_pad and leg_l > 0 and leg_r > 0
        self._frames_on_pad = self._frames_on_pad + 1 if standing else 0
        at_rest = not self.lander.awake
        crashed = self.game_over or abs(x) >= 1.0
        success = not crashed and over_pad and (at_rest or self._frames_on_pad >= STAND_FRAMES)
        landed_outside = not crashed and not success and at_rest
        if crashed:
            reward = _CRASH_REWARD
        elif success:
            reward = _LANDING_REWARD
        terminated = crashed or success or landed_outside
        return obs, float(reward), terminated, False, _info(success, crashed, landed_outside)

    def _legs_over_pad(self) -> bool:
        """Both legs are between the flags."""
        return all(self.helipad_x1 <= leg.position.x <= self.helipad_x2 for leg in self.legs)

    def _trim_particles(self) -> None:
        """Drops the oldest flame particles that ``render`` has not yet retired.

        Gymnasium removes particles only in ``render``; an ``rgb_array`` env stepped
        without rendering would otherwise pile up one physics body per engine frame.
        """
        while len(self.particles) > MAX_PARTICLES:
            self.world.DestroyBody(self.particles.pop(0))


def _info(
    success: bool = False, crashed: bool = False, landed_outside: bool = False
) -> dict[str, np.bool_]:
    """The episode flags as numpy bools (TorchRL's info-dict readers need a ``dtype``)."""
    return {
        "success": np.bool_(success),
        "crashed": np.bool_(crashed),
        "landed_outside": np.bool_(landed_outside),
    }


@numba.njit(cache=True)
def heuristic_key(obs: np.ndarray) -> int:
    """:func:`target_heuristic`'s key for one observation row (float64, 9 values), compiled
    (numba) so the simulated pilot's planning loops can call it per frame."""
    dx = obs[0] - obs[8]
    angle_targ = min(max(dx * 0.5 + obs[2] * 1.0, -0.4), 0.4)
    hover_targ = 0.55 * abs(dx) + (_APPROACH_HEIGHT if abs(dx) > _ABOVE_PAD else 0.0)
    angle_todo = (angle_targ - obs[4]) * 0.5 - obs[5] * 1.0
    hover_todo = (hover_targ - obs[1]) * 0.5 - obs[3] * 0.5
    if obs[6] != 0 or obs[7] != 0:  # touching: only cut the fall
        angle_todo = 0.0
        hover_todo = -obs[3] * 0.5
    if hover_todo > abs(angle_todo) and hover_todo > 0.05:
        return 2
    if angle_todo < -0.05:
        return 3
    if angle_todo > 0.05:
        return 1
    return 0


@numba.njit(cache=True)
def _heuristic_keys(obs: np.ndarray) -> np.ndarray:
    keys = np.empty(obs.shape[0], dtype=np.int64)
    for row in range(obs.shape[0]):
        keys[row] = heuristic_key(obs[row])
    return keys


def target_heuristic(obs: np.ndarray) -> int | np.ndarray:
    """Hand-written pilot that lands on the pad at ``obs[..., 8]`` (discrete actions).

    Gymnasium's ``heuristic`` steered to x = ``obs[8]`` instead of 0: tilt toward the
    pad and against the drift, hover at a height that shrinks as the lander closes in,
    and once a leg touches only cut the fall. One change makes it land on a moved pad:
    until it is within ``0.03`` of the pad's x it holds ``0.2`` higher, so it neither
    clips the hills between the start and a far pad (they can rise above the pad's
    height) nor settles on the slope beside the flags. Over seeds 0..999 of
    ``dcsc/TargetLunarLander-v0`` it lands on the pad in 99% of the episodes.

    Args:
        obs: a TargetLunarLander observation (9 values; ``obs[8]`` is the pad's x), or a
            batch of them ``[..., 9]``.

    Returns:
        The action: 0 no-op, 1 left engine, 2 main engine, 3 right engine; an ``int``
        for one observation, an int64 array of the batch's shape for a batch.
    """
    obs = np.asarray(obs, dtype=np.float64)
    keys = _heuristic_keys(np.ascontiguousarray(obs.reshape(-1, obs.shape[-1]))).reshape(obs.shape[:-1])
    return int(keys) if keys.ndim == 0 else keys
