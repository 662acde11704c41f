"""A real person flies TargetLunarLander with the arrow keys or a joystick.

The pilot shows every frame at the env's 50 FPS (``pygame.time.Clock`` paces them) and
measures a reaction time (RT) per decision: the time from a frame being shown to the
next change of the controls. A person who changes nothing for longer than t_d is
overloaded (Eq. 6: RT > t_d): the pilot then reports the time elapsed so far (> t_d) as
the RT of a decision and starts timing again from the next frame.

The window, the clock, the event source and the time source are constructor arguments,
so tests drive the pilot headless (``SDL_VIDEODRIVER=dummy``, posted key events, a fake
clock) and get exact RTs.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Hashable, Iterable, Sequence
from typing import Protocol

import numpy as np
import torch
from gymnasium.envs.box2d.lunar_lander import FPS, VIEWPORT_H, VIEWPORT_W
from tensordict import TensorDict, TensorDictBase

from dcsc_torchrl.checks import check_in_range

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
import pygame  # noqa: E402  (after the prompt is silenced)

__all__ = ["KEY_ACTIONS", "KeyboardPilot", "NoDisplayError", "PygameScreen"]

N_KEYS = 4
KEY_ACTIONS = {
    pygame.K_UP: 2,
    pygame.K_w: 2,
    pygame.K_LEFT: 1,
    pygame.K_a: 1,
    pygame.K_RIGHT: 3,
    pygame.K_d: 3,
}
"""Keys and the TargetLunarLander action they fire: up = main engine (2), left = left
engine (1, leans the lander left), right = right engine (3); W, A, D likewise."""
QUIT_KEYS = (pygame.K_ESCAPE, pygame.K_q)
_STICK_DEADZONE = 0.5
_TEXT_COLOUR = (255, 255, 255)
_LINE_HEIGHT = 22

_HINT = "use a simulated operator instead, e.g. SimulatedPilot.from_preset('expert')"
_INVISIBLE_DRIVERS = ("offscreen", "dummy")


class NoDisplayError(RuntimeError):
    """There is no display to show the keyboard pilot its frames."""


class Screen(Protocol):
    """Where the pilot's frames are shown (a window, or a recorder in tests)."""

    def show(self, frame: np.ndarray | None, lines: Sequence[str]) -> None:
        """Draws an ``H x W x 3`` uint8 frame (or a blank one) with lines of text, and shows it."""

    def close(self) -> None:
        """Closes the window."""


class Clock(Protocol):
    """Paces the frames (``pygame.time.Clock``)."""

    def tick(self, framerate: float) -> int:
        """Waits until ``1 / framerate`` seconds have passed since the previous tick."""


def open_window(size: tuple[int, int], caption: str) -> pygame.Surface:
    """Opens the pygame window.

    Raises:
        NoDisplayError: on Linux with none of ``DISPLAY``, ``WAYLAND_DISPLAY``,
            ``SDL_VIDEODRIVER`` set, when pygame cannot open a display, or when SDL
            falls back to an invisible driver (``offscreen``, ``dummy``) that
            ``SDL_VIDEODRIVER`` did not ask for (a ``DISPLAY`` whose server is not
            running); the message says to use a simulated operator.
    """
    display_vars = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")
    if sys.platform.startswith("linux") and not any(os.environ.get(v) for v in display_vars):
        raise NoDisplayError(
            f"no display for the keyboard pilot: none of {', '.join(display_vars)} is set; {_HINT}"
        )
    try:
        pygame.display.init()
        pygame.font.init()
        window = pygame.display.set_mode(size)
    except pygame.error as error:
        raise NoDisplayError(f"no display for the keyboard pilot ({error}); {_HINT}") from error
    # SDL falls back to an invisible driver when the display named in DISPLAY does not
    # answer: refuse it unless SDL_VIDEODRIVER asked for it (the headless tests do)
    driver = pygame.display.get_driver()
    asked = [d.strip() for d in os.environ.get("SDL_VIDEODRIVER", "").split(",") if d.strip()]
    if driver in _INVISIBLE_DRIVERS and driver not in asked:
        pygame.display.quit()
        named = ", ".join(f"{v}={os.environ[v]}" for v in display_vars if os.environ.get(v)) or "no display"
        raise NoDisplayError(
            f"no display for the keyboard pilot: {named} is set but no display server answers there "
            f"(SDL fell back to its invisible {driver!r} driver); start one or {_HINT}"
        )
    pygame.display.set_caption(caption)
    return window


class PygameScreen:
    """The pilot's pygame window: the env's frame with lines of text on top.

    Args:
        size: window size in pixels (default: LunarLander's viewport, 600 x 400).
        caption: the window title.

    Raises:
        NoDisplayError: see :func:`open_window`.
    """

    def __init__(
        self, size: tuple[int, int] = (VIEWPORT_W, VIEWPORT_H), caption: str = "dcsc play"
    ) -> None:
        self.window = open_window(size, caption)
        self.font = pygame.font.Font(None, 24)

    def show(self, frame: np.ndarray | None, lines: Sequence[str]) -> None:
        """Blits ``frame`` (scaled to the window) and ``lines``, then flips the display."""
        self.window.fill((0, 0, 0))
        if frame is not None:
            surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.swapaxes(0, 1)))
            self.window.blit(pygame.transform.scale(surface, self.window.get_size()), (0, 0))
        for row, line in enumerate(lines):
            text = self.font.render(line, True, _TEXT_COLOUR)
            self.window.blit(text, (10, 10 + _LINE_HEIGHT * row))
        pygame.display.flip()

    def close(self) -> None:
        """Closes the window."""
        pygame.display.quit()


def _open_joysticks() -> list[pygame.joystick.JoystickType]:
    pygame.joystick.init()
    return [pygame.joystick.Joystick(i) for i in range(pygame.joystick.get_count())]


class KeyboardPilot:
    """A person at the keyboard (or a joystick) as a :class:`HumanOperator`.

    On every frame (each call) the pilot waits on the clock (``fps`` frames per
    second), reads the control events since the previous frame, shows the frame from
    ``frame_source`` with the lines of :attr:`status`, and answers:

    - ``human_action``: one-hot of the key held; of several, the last pressed wins;
      none = no-op (0). The arrow keys (or W/A/D) per :data:`KEY_ACTIONS`; a
      joystick's hat or stick (up = main engine; left/right) and button 0 (main
      engine) where pygame finds one.
    - ``human_decided``: True on a frame where the controls changed (a press or a
      release), and when they have not changed for longer than ``t_d``.
    - ``human_rt``: at a decision, the seconds from the first frame shown after the
      previous decision (or the episode's start) to now; between decisions, the last
      decision's RT. Resolution: one frame (1/fps s).

    ``is_init`` (an episode's first frame) restarts the timing; the held keys stay
    as the person holds them. Escape, Q or closing the window set
    :attr:`quit_requested`. One person flies one lander: the batch must hold one env
    (shape ``[]`` or ``[1]``).

    Args:
        frame_source: returns the frame to show (e.g. a ``render_mode="rgb_array"``
            env's ``render``); ``None`` shows a blank frame.
        t_d: seconds without a change that count as a decision with RT > t_d (the
            t_d of :class:`~dcsc_torchrl.transforms.HumanConfidenceTransform`), > 0 and finite.
        fps: frames per second (the env's 50), > 0 and finite.
        screen: where frames go (default: a :class:`PygameScreen`).
        clock: paces the frames (default: ``pygame.time.Clock()``).
        events: returns the pygame events since the last call (default
            ``pygame.event.get``).
        time_source: seconds, monotonic (default ``time.perf_counter``).
        joystick: open the joysticks pygame finds.

    Raises:
        ValueError: for a ``t_d`` or ``fps`` that is not > 0 and finite.
        NoDisplayError: no display (without an injected ``screen``); the message
            points to :class:`~dcsc_torchrl.humans.SimulatedPilot`.
    """

    def __init__(
        self,
        *,
        frame_source: Callable[[], np.ndarray | None] | None = None,
        t_d: float = 1.0,
        fps: float = FPS,
        screen: Screen | None = None,
        clock: Clock | None = None,
        events: Callable[[], Iterable[pygame.event.Event]] | None = None,
        time_source: Callable[[], float] = time.perf_counter,
        joystick: bool = True,
    ) -> None:
        check_in_range("t_d", t_d, 0.0, math.inf, low_inclusive=False, high_inclusive=False)
        check_in_range("fps", fps, 0.0, math.inf, low_inclusive=False, high_inclusive=False)
        self.screen = PygameScreen() if screen is None else screen
        self.clock = pygame.time.Clock() if clock is None else clock
        self.events = pygame.event.get if events is None else events
        self.time_source = time_source
        self.frame_source = frame_source
        self.t_d = float(t_d)
        self.fps = float(fps)
        self.joysticks = _open_joysticks() if joystick else []
        self.status: list[str] = []
        """Lines of text drawn on the next frames (e.g. b_h, b_m, beta)."""
        self.quit_requested = False
        self._held: dict[Hashable, int] = {}  # control -> action, in order of pressing
        self._stimulus: float | None = None
        self._rt = 0.0

    def reset(self, seed: int | None) -> None:
        """Restarts the RT timing (a person has no seed)."""
        self._stimulus = None
        self._rt = 0.0

    def close(self) -> None:
        """Closes the screen."""
        self.screen.close()

    @property
    def action(self) -> int:
        """The action the controls command now."""
        return next(reversed(self._held.values()), 0)

    def _set(self, control: Hashable, action: int | None) -> None:
        self._held.pop(control, None)
        if action is not None:
            self._held[control] = action

    def _read_events(self) -> bool:
        """Applies the pending events to the held controls; True if any control changed."""
        changed = False
        for event in self.events():
            if event.type == pygame.QUIT or (
                event.type == pygame.KEYDOWN and event.key in QUIT_KEYS
            ):
                self.quit_requested = True
            elif event.type in (pygame.KEYDOWN, pygame.KEYUP) and event.key in KEY_ACTIONS:
                pressed = event.type == pygame.KEYDOWN
                self._set(("key", event.key), KEY_ACTIONS[event.key] if pressed else None)
                changed = True
            elif event.type == pygame.JOYHATMOTION:
                x, y = event.value
                self._set(("hat", "x"), {-1: 1, 1: 3}.get(x))
                self._set(("hat", "y"), 2 if y == 1 else None)
                changed = True
            elif event.type == pygame.JOYAXISMOTION and event.axis in (0, 1):
                if event.axis == 0:
                    side = (
                        1
                        if event.value < -_STICK_DEADZONE
                        else 3
                        if event.value > _STICK_DEADZONE
                        else None
                    )
                    self._set(("axis", 0), side)
                else:
                    self._set(("axis", 1), 2 if event.value < -_STICK_DEADZONE else None)
                changed = True
            elif event.type in (pygame.JOYBUTTONDOWN, pygame.JOYBUTTONUP) and event.button == 0:
                self._set(("button", 0), 2 if event.type == pygame.JOYBUTTONDOWN else None)
                changed = True
        return changed

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Paces, reads the controls, shows the frame; see the class docstring."""
        batch = tensordict.batch_size
        if batch.numel() != 1:
            raise ValueError(
                f"one person flies one lander: the keyboard pilot needs a batch of one env "
                f"(shape [] or [1]), got {tuple(batch)}"
            )
        is_init = bool(tensordict.get("is_init").any())
        self.clock.tick(self.fps)
        changed = self._read_events()
        now = self.time_source()
        decided = False
        if self._stimulus is not None and not is_init:
            elapsed = now - self._stimulus
            if changed or elapsed > self.t_d:
                decided = True
                self._rt = elapsed
        self.screen.show(None if self.frame_source is None else self.frame_source(), self.status)
        if decided or is_init or self._stimulus is None:
            self._stimulus = self.time_source()
        action = torch.nn.functional.one_hot(torch.tensor(self.action), N_KEYS)
        return TensorDict(
            {
                "human_action": action.reshape(*batch, N_KEYS),
                "human_rt": torch.full((*batch, 1), self._rt),
                "human_decided": torch.full((*batch, 1), decided),
            },
            batch,
        )
