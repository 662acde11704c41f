"""A real person at the controls: :class:`PersonAtControls`, and :class:`KeyboardPilot`,
who flies TargetLunarLander with the arrow keys or a joystick.

:class:`PersonAtControls` is what every person at a keyboard shares: it paces the frames
(``pygame.time.Clock``), reads the control events, shows each frame in a window, handles
Esc / Q / closing the window, waits for the person between episodes (:meth:`~PersonAtControls.prompt`)
and measures a reaction time (RT) per decision: the time from a frame being shown to the
next change of the controls. A person who changes nothing for longer than t_d is
overloaded (Eq. 6: RT > t_d): the reported RT of that decision is then the time elapsed
so far (> t_d), and the timing starts again from the next frame. A subclass says only how
the events change its controls, what action the controls command and what the person sees:
:class:`KeyboardPilot` here, :class:`~dcsc_torchrl.humans.uav_keyboard.UAVKeyboardOperator`
for the UAV.

The window, the clock, the event source and the time source are constructor arguments,
so tests drive a person headless (``SDL_VIDEODRIVER=dummy``, posted key events, a fake
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

__all__ = [
    "KEY_ACTIONS",
    "QUIT_KEYS",
    "START_KEYS",
    "KeyboardPilot",
    "NoDisplayError",
    "PersonAtControls",
    "PygameScreen",
]

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
"""Keys that quit (as does closing the window)."""
START_KEYS = (pygame.K_SPACE, pygame.K_RETURN, pygame.K_KP_ENTER)
"""Keys that answer :meth:`PersonAtControls.prompt` (Space, Enter)."""
_STICK_DEADZONE = 0.5
_TEXT_COLOUR = (255, 255, 255)
_LINE_HEIGHT = 22

_PILOT_STAND_IN = "SimulatedPilot.from_preset('expert')"
_INVISIBLE_DRIVERS = ("offscreen", "dummy")


class NoDisplayError(RuntimeError):
    """There is no display to show the person at the keys their frames."""


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


def open_window(
    size: tuple[int, int], caption: str, stand_in: str = _PILOT_STAND_IN
) -> pygame.Surface:
    """Opens the pygame window.

    Args:
        size: width and height in pixels.
        caption: the window title.
        stand_in: the simulated operator an error message offers instead of a person.

    Raises:
        NoDisplayError: on Linux with none of ``DISPLAY``, ``WAYLAND_DISPLAY``,
            ``SDL_VIDEODRIVER`` set, when pygame cannot open a display, or when SDL
            falls back to an invisible driver (``offscreen``, ``dummy``) that
            ``SDL_VIDEODRIVER`` did not ask for (a ``DISPLAY`` whose server is not
            running); the message says to use ``stand_in``, a simulated operator.
    """
    hint = f"use a simulated operator instead, e.g. {stand_in}"
    display_vars = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")
    if sys.platform.startswith("linux") and not any(os.environ.get(v) for v in display_vars):
        raise NoDisplayError(
            f"no display for the window of the person at the keys: none of {', '.join(display_vars)} is set; {hint}"
        )
    try:
        pygame.display.init()
        pygame.font.init()
        window = pygame.display.set_mode(size)
    except pygame.error as error:
        raise NoDisplayError(f"no display for the window of the person at the keys ({error}); {hint}") from error
    # SDL falls back to an invisible driver when the display named in DISPLAY does not
    # answer: refuse it unless SDL_VIDEODRIVER asked for it (the headless tests do)
    driver = pygame.display.get_driver()
    asked = [d.strip() for d in os.environ.get("SDL_VIDEODRIVER", "").split(",") if d.strip()]
    if driver in _INVISIBLE_DRIVERS and driver not in asked:
        pygame.display.quit()
        named = ", ".join(f"{v}={os.environ[v]}" for v in display_vars if os.environ.get(v)) or "no display"
        raise NoDisplayError(
            f"no display for the window of the person at the keys: {named} is set but no display server answers there "
            f"(SDL fell back to its invisible {driver!r} driver); start one or {hint}"
        )
    pygame.display.set_caption(caption)
    return window


class PygameScreen:
    """The pilot's pygame window: the env's frame with lines of text on top.

    Args:
        size: window size in pixels (default: LunarLander's viewport, 600 x 400).
        caption: the window title.
        stand_in: the simulated operator a :class:`NoDisplayError` offers instead.

    Raises:
        NoDisplayError: see :func:`open_window`.
    """

    def __init__(
        self,
        size: tuple[int, int] = (VIEWPORT_W, VIEWPORT_H),
        caption: str = "dcsc play",
        stand_in: str = _PILOT_STAND_IN,
    ) -> None:
        self.window = open_window(size, caption, stand_in)
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


def _is_quit(event: pygame.event.Event) -> bool:
    return event.type == pygame.QUIT or (event.type == pygame.KEYDOWN and event.key in QUIT_KEYS)


class PersonAtControls:
    """A person at the controls of one env, as a :class:`~dcsc_torchrl.transforms.HumanOperator`.

    On every frame (each call) it waits on the clock (``fps`` frames per second), reads
    the events since the previous frame, shows what the person sees (:meth:`_view`), and
    answers:

    - ``human_action``: what the controls command now (:meth:`_action`), ``[*batch, n]``;
    - ``human_decided``: True on a frame where the controls changed (:meth:`_handle_event`
      said so for one of the frame's events), and when they have not changed for longer
      than ``t_d``;
    - ``human_rt``: at a decision, the seconds from the first frame shown after the
      previous decision (or the episode's start) to now; between decisions, the last
      decision's RT. Resolution: one frame (1/fps s).

    ``is_init`` (an episode's first frame) restarts the timing and calls
    :meth:`_begin_episode` before the frame's events are read. Escape, Q or closing the
    window set :attr:`quit_requested`. One person flies one vehicle: the batch must hold
    one env (shape ``[]`` or ``[1]``).

    A subclass defines :meth:`_handle_event` (how an event changes its controls),
    :meth:`_action` (the action they command) and :meth:`_view` (the frame and lines the
    person sees), and, where an episode starts from a default, :meth:`_begin_episode`; its
    class attributes name the :attr:`vehicle`, the :attr:`window_size` and the simulated
    operator to use without a display (:attr:`stand_in`).

    Args:
        t_d: seconds without a change that count as a decision with RT > t_d (the
            t_d of :class:`~dcsc_torchrl.transforms.HumanConfidenceTransform`), > 0 and finite.
        fps: frames per second, > 0 and finite.
        screen: where frames go (default: a :class:`PygameScreen` of :attr:`window_size`).
        clock: paces the frames (default: ``pygame.time.Clock()``).
        events: returns the pygame events since the last call (default
            ``pygame.event.get``).
        time_source: seconds, monotonic (default ``time.perf_counter``).
        joystick: open the joysticks pygame finds.

    Raises:
        ValueError: for a ``t_d`` or ``fps`` that is not > 0 and finite.
        NoDisplayError: no display (without an injected ``screen``); the message
            points to :attr:`stand_in`.
    """

    vehicle = "vehicle"
    """What one person flies (named by the one-env error)."""
    window_size: tuple[int, int] = (VIEWPORT_W, VIEWPORT_H)
    """The default screen's size in pixels."""
    stand_in = _PILOT_STAND_IN
    """The simulated operator to use where no display is found."""

    def __init__(
        self,
        *,
        t_d: float,
        fps: float,
        screen: Screen | None = None,
        clock: Clock | None = None,
        events: Callable[[], Iterable[pygame.event.Event]] | None = None,
        time_source: Callable[[], float] = time.perf_counter,
        joystick: bool = True,
    ) -> None:
        check_in_range("t_d", t_d, 0.0, math.inf, low_inclusive=False, high_inclusive=False)
        check_in_range("fps", fps, 0.0, math.inf, low_inclusive=False, high_inclusive=False)
        self.screen = PygameScreen(self.window_size, stand_in=self.stand_in) if screen is None else screen
        self.clock = pygame.time.Clock() if clock is None else clock
        self.events = pygame.event.get if events is None else events
        self.time_source = time_source
        self.t_d = float(t_d)
        self.fps = float(fps)
        self.joysticks = _open_joysticks() if joystick else []
        self.status: list[str] = []
        """Lines of text drawn on the next frames (e.g. b_h, b_m, beta)."""
        self.quit_requested = False
        self._stimulus: float | None = None
        self._rt = 0.0

    def reset(self, seed: int | None) -> None:
        """Restarts the RT timing and the episode's controls (a person has no seed)."""
        self._stimulus = None
        self._rt = 0.0
        self._begin_episode()

    def close(self) -> None:
        """Closes the screen."""
        self.screen.close()

    def prompt(self, lines: Sequence[str]) -> bool:
        """Shows ``lines`` on a blank frame until the person presses Space or Enter.

        The frames are paced by the clock and the events read from the event source, as
        in an episode; control events still change the controls (a key released while
        the prompt shows is released), but nothing is timed.

        Args:
            lines: what to tell the person, e.g. ``["Episode 3 of 10: DC-SC shares
                control", "press Space to start"]``.

        Returns:
            True on Space or Enter, False when a quit is requested (Escape, Q, closing
            the window; also at once if one was requested before).
        """
        while not self.quit_requested:
            self.screen.show(None, lines)
            self.clock.tick(self.fps)
            started = False
            for event in self.events():
                started |= event.type == pygame.KEYDOWN and event.key in START_KEYS
                self._read_event(event)
            if started:
                return not self.quit_requested
        return False

    def _read_event(self, event: pygame.event.Event) -> bool:
        """Notes a quit or applies a control event; True if the controls changed."""
        if _is_quit(event):
            self.quit_requested = True
            return False
        return self._handle_event(event)

    def _handle_event(self, event: pygame.event.Event) -> bool:
        """Applies ``event`` to the controls; True if it is a change of the controls."""
        raise NotImplementedError

    def _action(self) -> torch.Tensor:
        """The action ``[n]`` the controls command now."""
        raise NotImplementedError

    def _view(self, tensordict: TensorDictBase) -> tuple[np.ndarray | None, Sequence[str]]:
        """The frame (``H x W x 3`` uint8, or ``None`` for a blank one) and the lines of this frame."""
        raise NotImplementedError

    def _begin_episode(self) -> None:
        """Sets the controls an episode starts with (at ``is_init`` and :meth:`reset`); none here."""

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Paces, reads the controls, shows the frame; see the class docstring."""
        batch = tensordict.batch_size
        if batch.numel() != 1:
            raise ValueError(
                f"one person flies one {self.vehicle}: {type(self).__name__} needs a batch of one env "
                f"(shape [] or [1]), got {tuple(batch)}"
            )
        is_init = bool(tensordict.get("is_init").any())
        if is_init:
            self._begin_episode()
        self.clock.tick(self.fps)
        changed = False
        for event in self.events():
            changed |= self._read_event(event)
        now = self.time_source()
        decided = False
        if self._stimulus is not None and not is_init:
            elapsed = now - self._stimulus
            if changed or elapsed > self.t_d:
                decided = True
                self._rt = elapsed
        self.screen.show(*self._view(tensordict))
        if decided or is_init or self._stimulus is None:
            self._stimulus = self.time_source()
        action = self._action()
        return TensorDict(
            {
                "human_action": action.reshape(*batch, -1),
                "human_rt": torch.full((*batch, 1), self._rt),
                "human_decided": torch.full((*batch, 1), decided),
            },
            batch,
        )


class KeyboardPilot(PersonAtControls):
    """A person at the keyboard (or a joystick) flies TargetLunarLander.

    A :class:`PersonAtControls` (pacing, RT per decision, quit, :meth:`prompt`) whose
    controls are held keys: on every frame it shows the frame from ``frame_source`` with
    the lines of :attr:`status`, and its ``human_action`` is the one-hot ``[*batch, 4]``
    of the key held; of several, the last pressed wins; none = no-op (0). The arrow keys
    (or W/A/D) per :data:`KEY_ACTIONS`; a joystick's hat or stick (up = main engine;
    left/right) and button 0 (main engine) where pygame finds one. A press or a release
    is a change of the controls (a decision). ``is_init`` restarts the timing; the held
    keys stay as the person holds them.

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

    vehicle = "lander"

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
        super().__init__(
            t_d=t_d,
            fps=fps,
            screen=screen,
            clock=clock,
            events=events,
            time_source=time_source,
            joystick=joystick,
        )
        self.frame_source = frame_source
        self._held: dict[Hashable, int] = {}  # control -> action, in order of pressing

    @property
    def action(self) -> int:
        """The action the controls command now."""
        return next(reversed(self._held.values()), 0)

    def _set(self, control: Hashable, action: int | None) -> None:
        self._held.pop(control, None)
        if action is not None:
            self._held[control] = action

    def _handle_event(self, event: pygame.event.Event) -> bool:
        if event.type in (pygame.KEYDOWN, pygame.KEYUP) and event.key in KEY_ACTIONS:
            pressed = event.type == pygame.KEYDOWN
            self._set(("key", event.key), KEY_ACTIONS[event.key] if pressed else None)
        elif event.type == pygame.JOYHATMOTION:
            x, y = event.value
            self._set(("hat", "x"), {-1: 1, 1: 3}.get(x))
            self._set(("hat", "y"), 2 if y == 1 else None)
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
        elif event.type in (pygame.JOYBUTTONDOWN, pygame.JOYBUTTONUP) and event.button == 0:
            self._set(("button", 0), 2 if event.type == pygame.JOYBUTTONDOWN else None)
        else:
            return False
        return True

    def _action(self) -> torch.Tensor:
        return torch.nn.functional.one_hot(torch.tensor(self.action), N_KEYS)

    def _view(self, tensordict: TensorDictBase) -> tuple[np.ndarray | None, Sequence[str]]:
        return None if self.frame_source is None else self.frame_source(), self.status
