"""Projector displays: what shows a structured-light pattern on a projector's panel.

The interface is :class:`fluxcli.structured.projector.PatternDisplay` (``show(pattern)``,
``blank()``).  Two backends:

- ``simulated``: :class:`~fluxcli.structured.projector.ImageSink` keeps the image; the
  simulated camera reads it (:meth:`shown`) and renders it on the true surface.
- ``window`` (the lab): :class:`WindowDisplay`, a borderless full-screen window on the
  projector's monitor drawn 1:1 with vsync (pyglet, the optional extra
  ``fluxmap[projector]``, imported only when used; not
  exercised in CI, where no display exists).  After a pattern is drawn it waits
  ``settle_s`` (a few refreshes plus the projector's own latency) before returning, so the
  exposure that follows sees the new pattern.
"""

from __future__ import annotations

import time

import numpy as np

from ..structured.projector import ImageSink, PatternDisplay, Projector
from .errors import DeviceError

__all__ = ["WindowDisplay", "open_display", "projector_model"]


class WindowDisplay(PatternDisplay):
    """A full-screen window on monitor ``screen`` showing patterns 1:1 (8-bit grey)."""

    def __init__(self, name: str, width_px: int, height_px: int, *, screen: int = 1, settle_s: float = 0.1):
        try:
            import pyglet
        except ImportError:
            raise DeviceError(f"rig.projectors.{name}.display", f"screen {screen}", "'window' needs pyglet, an "
                              "optional extra: pip install 'fluxmap[projector]' (and a graphical session); or use "
                              "display: simulated", show_said=False) from None
        screens = pyglet.display.get_display().get_screens()
        if screen >= len(screens):
            raise DeviceError(f"rig.projectors.{name}", f"screen {screen}",
                              f"there are only {len(screens)} monitors", show_said=False)
        s = screens[screen]
        if (s.width, s.height) != (width_px, height_px):
            raise DeviceError(f"rig.projectors.{name}", f"screen {screen}", f"the monitor is {s.width} x {s.height}, "
                              f"rig.projectors.{name}.pixels says {width_px} x {height_px}", show_said=False)
        self._pyglet = pyglet
        self._window = pyglet.window.Window(fullscreen=True, screen=s, vsync=True)
        self._shape = (height_px, width_px)
        self._settle_s = float(settle_s)
        self._image = None

    def show(self, pattern: np.ndarray) -> None:
        p = np.asarray(pattern, float)
        if p.shape != self._shape:
            raise ValueError(f"pattern shape {p.shape} is not the panel's {self._shape}")
        grey = np.round(np.clip(p, 0, 1) * 255).astype(np.uint8)
        # pyglet's image rows run bottom-up: flip so that row 0 is the panel's top
        data = np.ascontiguousarray(grey[::-1]).tobytes()
        self._image = self._pyglet.image.ImageData(self._shape[1], self._shape[0], "L", data)
        for _ in range(2):  # draw into both buffers: the next flip shows it whatever the swap state
            self._window.switch_to()
            self._window.dispatch_events()
            self._image.blit(0, 0)
            self._window.flip()
        time.sleep(self._settle_s)

    def close(self) -> None:
        self._window.close()


def projector_model(spec) -> Projector:
    """The pinhole-plus-distortion model of a ``rig.projectors`` entry (a validated config block)."""
    w, h = spec.pixels
    cx, cy = spec.principal_px if spec.principal_px is not None else (w / 2, h / 2)
    return Projector.from_pose(center_mm=spec.pose.center_mm, look=spec.pose.look, up=spec.pose.up, width_px=w,
                               height_px=h, fx_px=spec.focal_px[0], fy_px=spec.focal_px[1], cx_px=cx, cy_px=cy,
                               k1=spec.distortion[0], k2=spec.distortion[1], gamma=spec.gamma)


def open_display(name: str, spec) -> PatternDisplay:
    """The display of projector ``name`` (``rig.projectors.<name>``), showing black."""
    w, h = spec.pixels
    if spec.display == "window":
        d: PatternDisplay = WindowDisplay(name, w, h, screen=spec.screen, settle_s=spec.settle_s)
    else:
        d = ImageSink(projector_model(spec))
    d.show(np.zeros((h, w)))
    return d
