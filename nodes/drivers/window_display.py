"""A projector as a full-screen window (X11/Wayland) or straight on a DRM connector (KMSDRM), via pygame-ce.

pygame-ce is the optional extra ``display`` (``pip install 'polarstripe[display]'``): plain ``pygame`` lacks
the KMSDRM video driver. ``driver="kmsdrm"`` draws with no desktop (the user in group ``video``, no other DRM
master); ``display_index`` picks the output (the projector is usually 1 next to a desktop). Each ``show``
renders the pattern with :func:`~.display.render_pattern`, blits it and flips; the returned time is taken
after the flip. Tests use ``SDL_VIDEODRIVER=dummy`` (or ``offscreen``), which draws into memory only.
"""

from __future__ import annotations

import os
import time

import numpy as np
from polarstripe.msgs.patterns import PatternSpec
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.display import Display, render_pattern
from polarstripe.nodes.drivers.errors import BackendUnavailable, DriverError


def _import_pygame():
    try:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame
    except ImportError as exc:
        raise BackendUnavailable(
            "display backend 'window' needs pygame-ce (module pygame), which is not installed; "
            "install the extra: pip install 'polarstripe[display]'"
        ) from exc
    return pygame


class WindowDisplay(Display):
    """A borderless full-screen window (or a KMSDRM output) showing the pattern in white on black.

    :param width, height: the output size [pixels]; ``None`` takes the output's native size.
    :param display_index: which monitor/connector.
    :param driver: SDL video driver (``"kmsdrm"``, ``"x11"``, ``"wayland"``, ``"dummy"``); None: SDL's choice.
    :param fullscreen: False opens an ordinary window (for a look on the desktop).
    :param level: the lit grey level (0-255); the projector's black level is what it shows for 0.
    """

    class Options(BackendOptions):
        width: int | None = None  # output size [px]; None: the output's native size
        height: int | None = None
        display_index: int = 0  # which monitor/connector
        driver: str | None = None  # SDL video driver: kmsdrm, x11, wayland, dummy; None: SDL's choice
        fullscreen: bool = True  # false: an ordinary window
        level: int = 255  # the lit grey level (0-255)

    def __init__(
        self,
        width: int | None = None,
        height: int | None = None,
        *,
        display_index: int = 0,
        driver: str | None = None,
        fullscreen: bool = True,
        level: int = 255,
    ):
        pygame = _import_pygame()
        if driver is not None:
            os.environ["SDL_VIDEODRIVER"] = driver
        try:
            pygame.display.init()
            if width is None or height is None:
                sizes = pygame.display.get_desktop_sizes()
                if display_index >= len(sizes):
                    raise DriverError(
                        f"window display: display_index={display_index} but only {len(sizes)} outputs exist"
                    )
                width, height = sizes[display_index]
            flags = (pygame.FULLSCREEN | pygame.NOFRAME) if fullscreen else 0
            self._screen = pygame.display.set_mode((width, height), flags, display=display_index)
            pygame.mouse.set_visible(False)
        except pygame.error as exc:
            pygame.display.quit()
            raise DriverError(
                f"window display on output {display_index} "
                f"(SDL_VIDEODRIVER={os.environ.get('SDL_VIDEODRIVER', 'auto')}): {exc}"
            ) from exc
        super().__init__(width, height, name=f"window display {display_index}")
        self._pygame, self.level = pygame, int(level)

    def _show(self, pattern: PatternSpec) -> float:
        pygame = self._pygame
        grey = render_pattern(pattern, self.width, self.height, lit=self.level)
        rgb = np.repeat(grey.T[:, :, None], 3, axis=2)  # pygame's surfarray is (width, height, 3)
        try:
            pygame.surfarray.blit_array(self._screen, rgb)
            pygame.display.flip()
            pygame.event.pump()  # keep the window responsive
        except pygame.error as exc:
            raise DriverError(f"{self.name}: drawing {pattern} failed: {exc}") from exc
        return time.monotonic()

    def screenshot(self) -> np.ndarray:
        """The grey levels on the output now, (height, width) uint8 (for tests and checks)."""
        return self._pygame.surfarray.array3d(self._screen)[:, :, 0].T.copy()

    def _close(self) -> None:
        self._pygame.display.quit()
