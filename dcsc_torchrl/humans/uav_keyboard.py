"""A real person flies the UAV at the keyboard: :class:`UAVKeyboardOperator` and its view,
:func:`uav_frame` (docs/operators.md, "UAVKeyboardOperator").

The UAV's actions are the three IIFDS flow coefficients ``(rho0, sigma0, tau)``, which
nobody can drive continuously. A person commands two things instead, which persist until
changed: the *way round* the obstacles (``tau``: pass them on the right, climb over them,
pass them on the left) and the *margin* kept from them (``rho0 = sigma0``: tight, medium,
wide). Every command is a point of the simulated operator's candidate grid,
:data:`~dcsc_torchrl.humans.uav_operator.DEFAULT_GRID`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import pygame
import torch
from tensordict import TensorDictBase

from dcsc_torchrl.envs.uav import (
    ARENA_HIGH,
    ARENA_LOW,
    DT,
    GOAL_RADIUS,
    N_OBSTACLE_PARAMS,
    obstacle_states,
)
from dcsc_torchrl.humans.keyboard import Clock, PersonAtControls, Screen
from dcsc_torchrl.humans.uav_operator import DEFAULT_GRID

__all__ = [
    "DEFAULT_COMMAND",
    "FRAME_SIZE",
    "HAT_WAYS",
    "MARGINS",
    "MARGIN_KEYS",
    "NEXT_MARGIN_KEYS",
    "WAYS",
    "WAY_KEYS",
    "UAVCommand",
    "UAVKeyboardOperator",
    "map_pixel",
    "uav_frame",
]

WAYS = dict(zip(("right", "over", "left"), sorted({tau for _, _, tau in DEFAULT_GRID}), strict=True))
"""``tau`` of each way round an obstacle, the grid's three: ``right`` (0) circles it
anticlockwise seen from above, so the UAV passes it on the right of its flight; ``over``
(1.5) climbs over it; ``left`` (3) circles it clockwise."""
MARGINS = dict(zip(("tight", "medium", "wide"), sorted({rho0 for rho0, _, _ in DEFAULT_GRID}), strict=True))
"""``rho0 = sigma0`` of each margin, the grid's three levels: the larger, the stronger the
flow's repulsion and turn, the farther from the obstacles the UAV passes."""
WAY_KEYS = {
    pygame.K_LEFT: "left",
    pygame.K_a: "left",
    pygame.K_UP: "over",
    pygame.K_w: "over",
    pygame.K_RIGHT: "right",
    pygame.K_d: "right",
}
"""Keys and the way round they command: left (A), up (W) = over, right (D)."""
MARGIN_KEYS = {
    pygame.K_1: "tight",
    pygame.K_2: "medium",
    pygame.K_3: "wide",
    pygame.K_KP1: "tight",
    pygame.K_KP2: "medium",
    pygame.K_KP3: "wide",
}
"""Keys and the margin they command: 1, 2, 3 (top row or keypad)."""
NEXT_MARGIN_KEYS = (pygame.K_DOWN, pygame.K_s)
"""Keys that step the margin on: tight -> medium -> wide -> tight (one hand on the arrows)."""
HAT_WAYS = {(-1, 0): "left", (0, 1): "over", (1, 0): "right"}
"""A joystick hat's positions and the way round they command; down steps the margin on."""
_HAT_DOWN = (0, -1)
HEADING_SECONDS = 2.0
"""An obstacle's arrow shows where it will be in this many seconds."""
_KEY_HINT = "Left/A, Up/W, Right/D: way round   1, 2, 3 or Down/S: margin   Esc: quit"

_SCALE = 30  # pixels per unit of the top-down map
_TEXT_BAND = 150  # rows above the map left free for the status lines
_BORDER = 10
_STRIP_WIDTH = 80  # the altitude strip right of the map
_MAP_WIDTH = round((ARENA_HIGH[0] - ARENA_LOW[0]) * _SCALE)
_MAP_HEIGHT = round((ARENA_HIGH[1] - ARENA_LOW[1]) * _SCALE)
_STRIP_LEFT = _BORDER + _MAP_WIDTH + 2 * _BORDER
_Z_SCALE = _MAP_HEIGHT / (ARENA_HIGH[2] - ARENA_LOW[2])  # the strip spans the arena's height
FRAME_SIZE = (_STRIP_LEFT + _STRIP_WIDTH + _BORDER, _TEXT_BAND + _MAP_HEIGHT + _BORDER)
"""Width and height in pixels of :func:`uav_frame` (and of the operator's window)."""

_BACKGROUND = (15, 15, 25)
_PANEL = (30, 30, 45)
_GRID_LINE = (45, 45, 65)
_ARENA_EDGE = (150, 150, 170)
_UAV = (255, 255, 255)
_PATH = (120, 200, 255)
_GOAL = (255, 215, 0)
_OBSTACLE_COLOURS = (
    (255, 127, 14),
    (214, 39, 40),
    (148, 103, 189),
    (227, 119, 194),
    (44, 160, 44),
    (23, 190, 207),
    (196, 156, 148),
    (31, 119, 180),
)


@dataclass(frozen=True)
class UAVCommand:
    """What a person commands the UAV: the way round the obstacles and the margin kept.

    Attributes:
        way: ``"right"``, ``"over"`` or ``"left"`` (:data:`WAYS`).
        margin: ``"tight"``, ``"medium"`` or ``"wide"`` (:data:`MARGINS`).

    Raises:
        ValueError: for a way or margin not named there.

    Examples:
        >>> UAVCommand("left", "wide").action
        (2.5, 2.5, 3.0)
        >>> UAVCommand().describe()
        'over, medium margin: (rho0, sigma0, tau) = (1.5, 1.5, 1.5)'
    """

    way: str = "over"
    margin: str = "medium"

    def __post_init__(self) -> None:
        if self.way not in WAYS:
            raise ValueError(f"way must be one of {list(WAYS)}, got {self.way!r}")
        if self.margin not in MARGINS:
            raise ValueError(f"margin must be one of {list(MARGINS)}, got {self.margin!r}")

    @property
    def action(self) -> tuple[float, float, float]:
        """The grid point ``(rho0, sigma0, tau)`` commanded."""
        level = MARGINS[self.margin]
        return level, level, WAYS[self.way]

    def describe(self) -> str:
        """One line for the screen: the command and its coefficients."""
        return f"{self.way}, {self.margin} margin: (rho0, sigma0, tau) = {self.action}"


DEFAULT_COMMAND = UAVCommand()
"""Every episode starts with it: over, medium margin, the centre of the grid (1.5, 1.5, 1.5)."""


def _next_margin(margin: str) -> str:
    names = list(MARGINS)
    return names[(names.index(margin) + 1) % len(names)]


# --- the view ---------------------------------------------------------------------------


def map_pixel(x: float, y: float) -> tuple[int, int]:
    """Column and row of the arena's point ``(x, y)`` on :func:`uav_frame`'s map (x to the right, y up).

    Examples:
        >>> map_pixel(-2.0, 14.0)  # the arena's top-left corner, under the text band
        (10, 150)
    """
    return (
        round(_BORDER + (x - ARENA_LOW[0]) * _SCALE),
        round(_TEXT_BAND + (ARENA_HIGH[1] - y) * _SCALE),
    )


def _strip_row(z: float) -> int:
    """Pixel row of altitude ``z`` on the altitude strip (the arena's floor to its ceiling)."""
    return round(_TEXT_BAND + (ARENA_HIGH[2] - z) * _Z_SCALE)


def _arrow(surface: pygame.Surface, colour: tuple[int, int, int], start: tuple[int, int],
           end: tuple[int, int], head: float = 7.0) -> None:
    """A line ``start -> end`` with a head at ``end`` (just the line when shorter than the head,
    nothing when shorter than a pixel: a still obstacle has no arrow)."""
    direction = np.subtract(end, start, dtype=float)
    length = float(np.hypot(*direction))
    if length < 1:
        return
    pygame.draw.line(surface, colour, start, end, 2)
    if length <= head:
        return
    unit = direction / length
    normal = np.array([-unit[1], unit[0]])
    base = np.asarray(end) - head * unit
    corners = [tuple(base + head / 2 * normal), tuple(base - head / 2 * normal)]
    pygame.draw.polygon(surface, colour, [end, *corners])


def _lighter(colour: tuple[int, int, int], share: float) -> tuple[int, int, int]:
    """``colour`` mixed with white (``share`` > 0) or black (``share`` < 0)."""
    target = 255 if share > 0 else 0
    return tuple(round(c + abs(share) * (target - c)) for c in colour)


def _obstacle_colour(k: int) -> tuple[int, int, int]:
    return _OBSTACLE_COLOURS[k % len(_OBSTACLE_COLOURS)]


def _draw_map(surface: pygame.Surface, position: list[float], goal: list[float],
              obstacles: tuple[list, list, list], path: np.ndarray | None, heading_seconds: float) -> None:
    """The top-down map: grid, obstacles (slices, rings, arrows), goal, path, UAV."""
    rect = pygame.Rect(_BORDER, _TEXT_BAND, _MAP_WIDTH, _MAP_HEIGHT)
    surface.set_clip(rect)  # obstacles outside the arena stay off the strip
    for x in range(math.ceil(ARENA_LOW[0] / 2) * 2, int(ARENA_HIGH[0]) + 1, 2):
        pygame.draw.line(surface, _GRID_LINE, map_pixel(x, ARENA_LOW[1]), map_pixel(x, ARENA_HIGH[1]))
    for y in range(math.ceil(ARENA_LOW[1] / 2) * 2, int(ARENA_HIGH[1]) + 1, 2):
        pygame.draw.line(surface, _GRID_LINE, map_pixel(ARENA_LOW[0], y), map_pixel(ARENA_HIGH[0], y))
    centres, velocities, radii = obstacles
    for k, (centre, radius) in enumerate(zip(centres, radii, strict=True)):  # slices first: no ring hidden
        dz = centre[2] - position[2]
        if abs(dz) < radius:
            slice_radius = round(math.sqrt(radius**2 - dz**2) * _SCALE)
            shade = _lighter(_obstacle_colour(k), -0.45)
            pygame.draw.circle(surface, shade, map_pixel(*centre[:2]), slice_radius)
    for k, (centre, velocity, radius) in enumerate(zip(centres, velocities, radii, strict=True)):
        middle = map_pixel(*centre[:2])
        pygame.draw.circle(surface, _obstacle_colour(k), middle, round(radius * _SCALE), 2)
        ahead = [c + v * heading_seconds for c, v in zip(centre[:2], velocity[:2], strict=True)]
        _arrow(surface, _lighter(_obstacle_colour(k), 0.5), middle, map_pixel(*ahead))
    goal_point = map_pixel(*goal[:2])
    pygame.draw.circle(surface, _GOAL, goal_point, max(round(GOAL_RADIUS * _SCALE), 4))
    pygame.draw.circle(surface, _GOAL, goal_point, 12, 1)
    if path is not None and len(path) >= 2:
        pygame.draw.lines(surface, _PATH, False, [map_pixel(x, y) for x, y, _ in path], 2)
    pygame.draw.circle(surface, _UAV, map_pixel(*position[:2]), 6)
    pygame.draw.circle(surface, _BACKGROUND, map_pixel(*position[:2]), 6, 1)
    surface.set_clip(None)
    pygame.draw.rect(surface, _ARENA_EDGE, rect, 1)


def _draw_strip(surface: pygame.Surface, position: list[float], goal: list[float],
                obstacles: tuple[list, list, list], heading_seconds: float) -> None:
    """The altitude strip: each obstacle's extent (bar) and climb (arrow), the goal's and UAV's altitudes."""
    rect = pygame.Rect(_STRIP_LEFT, _TEXT_BAND, _STRIP_WIDTH, _MAP_HEIGHT)
    surface.fill(_PANEL, rect)
    surface.set_clip(rect)
    centres, velocities, radii = obstacles
    bar_width = max((_STRIP_WIDTH - 8) // max(len(radii), 1) - 2, 2)
    for k, (centre, velocity, radius) in enumerate(zip(centres, velocities, radii, strict=True)):
        left = _STRIP_LEFT + 4 + k * (bar_width + 2)
        top, bottom = _strip_row(centre[2] + radius), _strip_row(centre[2] - radius)
        surface.fill(_obstacle_colour(k), pygame.Rect(left, top, bar_width, bottom - top))
        middle = left + bar_width // 2
        ahead = (middle, _strip_row(centre[2] + velocity[2] * heading_seconds))
        _arrow(surface, _lighter(_obstacle_colour(k), 0.5), (middle, _strip_row(centre[2])), ahead, head=5.0)
    for z, colour, width in ((goal[2], _GOAL, 1), (position[2], _UAV, 2)):
        row = _strip_row(z)
        pygame.draw.line(surface, colour, (_STRIP_LEFT, row), (_STRIP_LEFT + _STRIP_WIDTH, row), width)
    surface.set_clip(None)
    pygame.draw.rect(surface, _ARENA_EDGE, rect, 1)


def uav_frame(
    tensordict: TensorDictBase,
    path: np.ndarray | None = None,
    *,
    heading_seconds: float = HEADING_SECONDS,
) -> np.ndarray:
    """Draws one UAV env's state for a person: ``H x W x 3`` uint8, ``FRAME_SIZE`` pixels.

    Under a band left free for text (the status lines), a top-down map of the arena
    (x to the right, y up, a faint line every 2 units, its edge where leaving ends the
    episode) and, to its right, an altitude strip from the arena's floor to its ceiling:

    - each obstacle in its own colour: on the map a ring of its radius, filled (darker)
      where it cuts the UAV's altitude (the disc ``sqrt(r^2 - dz^2)`` the UAV would hit
      flying level; no fill when it is wholly above or below), and an arrow to where it
      will be in ``heading_seconds`` at its present velocity; on the strip a bar from its
      bottom to its top, with the same arrow for its climb or descent;
    - the goal (yellow, a ring round it) and its altitude (a yellow line on the strip);
    - the UAV (white) with its ``path`` so far (blue), and its altitude across the strip.

    Args:
        tensordict: one env's keys (batch ``[]`` or ``[1]``): ``position [3]``, ``goal
            [3]``, ``time [1]``, ``obstacle_params [K, N_OBSTACLE_PARAMS]``.
        path: the UAV's positions so far, ``[T, 3]`` (none drawn for ``None`` or T < 2).
        heading_seconds: seconds of motion an obstacle's arrow shows.

    Returns:
        The frame, ``FRAME_SIZE[1] x FRAME_SIZE[0] x 3`` uint8.

    Examples:
        >>> from dcsc_torchrl.envs.uav import UAVPathPlanningEnv
        >>> td = UAVPathPlanningEnv(scenario_seeds=[0]).reset()
        >>> uav_frame(td).shape
        (640, 600, 3)
    """
    position = tensordict.get("position").reshape(3).tolist()
    goal = tensordict.get("goal").reshape(3).tolist()
    now = float(tensordict.get("time").reshape(()))
    params = tensordict.get("obstacle_params").reshape(-1, N_OBSTACLE_PARAMS).detach().cpu()
    obstacles = tuple(x.tolist() for x in obstacle_states(params, now))
    surface = pygame.Surface(FRAME_SIZE)
    surface.fill(_BACKGROUND)
    _draw_map(surface, position, goal, obstacles, None if path is None else np.asarray(path), heading_seconds)
    _draw_strip(surface, position, goal, obstacles, heading_seconds)
    return np.ascontiguousarray(pygame.surfarray.array3d(surface).swapaxes(0, 1))


# --- the operator -----------------------------------------------------------------------


class UAVKeyboardOperator(PersonAtControls):
    """A person at the keyboard (or a joystick's hat) flies the UAV.

    A :class:`~dcsc_torchrl.humans.keyboard.PersonAtControls` (pacing, RT per decision,
    quit, :meth:`prompt`) whose controls are a :class:`UAVCommand`, kept until changed
    (keys are pressed, not held; releases change nothing):

    - the way round the obstacles, :data:`WAY_KEYS`: Left or A = pass them on the left
      (tau 3), Up or W = climb over them (tau 1.5), Right or D = pass them on the right
      (tau 0);
    - the margin, :data:`MARGIN_KEYS`: 1, 2, 3 = tight, medium, wide (rho0 = sigma0 =
      0.5, 1.5, 2.5); Down or S steps it on (tight -> medium -> wide -> tight);
    - a joystick's hat: left, up, right = the way round; down steps the margin on.

    Every press of one of these keys is a change of the controls (a decision), even one
    that commands what was commanded already: the person answered the frame. An episode
    starts (``is_init``, :meth:`reset`) with :data:`DEFAULT_COMMAND` (over, medium) and an
    empty path. ``human_action`` is the command's grid point, float32 ``[*batch, 3]``.

    Each frame is :func:`uav_frame` of the env's keys with the path flown so far, under
    the lines of :attr:`status` (set by the caller, e.g. b_h, b_m, beta per action
    dimension), the command (:meth:`UAVCommand.describe`) and the keys.

    Args:
        t_d: seconds without a change that count as a decision with RT > t_d (the
            t_d of :class:`~dcsc_torchrl.transforms.HumanConfidenceTransform`), > 0 and finite.
        fps: frames per second (default ``1 / DT`` = 10: the env's own time, so a
            500-step episode lasts at most 50 s), > 0 and finite.
        screen: where frames go (default: a ``PygameScreen`` of :data:`FRAME_SIZE`).
        clock: paces the frames (default: ``pygame.time.Clock()``).
        events: returns the pygame events since the last call (default
            ``pygame.event.get``).
        time_source: seconds, monotonic (default ``time.perf_counter``).
        joystick: open the joysticks pygame finds.

    Raises:
        ValueError: for a ``t_d`` or ``fps`` that is not > 0 and finite.
        NoDisplayError: no display (without an injected ``screen``); the message
            points to :class:`~dcsc_torchrl.humans.SimulatedOperator`.
    """

    vehicle = "UAV"
    window_size = FRAME_SIZE
    stand_in = "SimulatedOperator.from_preset('expert')"

    def __init__(
        self,
        *,
        t_d: float = 1.0,
        fps: float = 1 / DT,
        screen: Screen | None = None,
        clock: Clock | None = None,
        events: Callable[[], Iterable[pygame.event.Event]] | None = None,
        time_source: Callable[[], float] = time.perf_counter,
        joystick: bool = True,
    ) -> None:
        super().__init__(
            t_d=t_d,
            fps=fps,
            screen=screen,
            clock=clock,
            events=events,
            time_source=time_source,
            joystick=joystick,
        )
        self.command = DEFAULT_COMMAND
        """The command in force."""
        self._path: list[list[float]] = []

    def _begin_episode(self) -> None:
        self.command = DEFAULT_COMMAND
        self._path = []

    def _handle_event(self, event: pygame.event.Event) -> bool:
        if event.type == pygame.KEYDOWN and event.key in WAY_KEYS:
            self.command = replace(self.command, way=WAY_KEYS[event.key])
        elif event.type == pygame.KEYDOWN and event.key in MARGIN_KEYS:
            self.command = replace(self.command, margin=MARGIN_KEYS[event.key])
        elif event.type == pygame.KEYDOWN and event.key in NEXT_MARGIN_KEYS:
            self.command = replace(self.command, margin=_next_margin(self.command.margin))
        elif event.type == pygame.JOYHATMOTION and event.value in HAT_WAYS:
            self.command = replace(self.command, way=HAT_WAYS[event.value])
        elif event.type == pygame.JOYHATMOTION and event.value == _HAT_DOWN:
            self.command = replace(self.command, margin=_next_margin(self.command.margin))
        else:
            return False
        return True

    def _action(self) -> torch.Tensor:
        return torch.tensor(self.command.action, dtype=torch.float32)

    def _view(self, tensordict: TensorDictBase) -> tuple[np.ndarray, Sequence[str]]:
        self._path.append(tensordict.get("position").reshape(3).tolist())
        frame = uav_frame(tensordict, np.array(self._path))
        return frame, [*self.status, f"you: {self.command.describe()}", _KEY_HINT]
