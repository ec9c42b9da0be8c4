"""What ``fluxmap rig check`` and ``rig snap`` share: the devices of ``rig:`` opened one by
one (simulators started for ``pty`` / ``socket://HOST:0`` ports), the simulated camera's
test card, and frames written as TIFF."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import config as C
from ..errors import UserError

# The simulated camera's test card: photons/s per pixel at the right edge (x the filter's
# transmission), falling linearly to half at the left edge, so a frame shows its orientation.
TEST_CARD_PHOTONS_PER_S = 20000.0


@dataclass
class Rig:
    """The opened devices (None where not configured or not answering) and who did not answer."""

    sims: dict = field(default_factory=dict)
    wheel: object = None
    stage: object = None
    camera: object = None
    failed: dict = field(default_factory=dict)  # config key -> DeviceError (or UserError) text

    def where(self, key: str, port: str) -> str:
        name = key.split(".")[-1]
        return f"{self.sims[name].url} (simulator)" if name in self.sims else port


def rig_of(cfg: C.LoadedConfig) -> C.Rig:
    """``rig:`` of the config, refused (exit 2) when it names no device: the commands' one look at the config."""
    rig = cfg.model.rig
    if rig is None or (rig.filter_wheel is None and rig.stage is None and rig.camera is None and not rig.projectors):
        raise UserError(f"config {cfg.path}: 'rig' names no device (filter_wheel, stage, camera, projectors).")
    return rig


@contextlib.contextmanager
def open_rig(rig: C.Rig, system: C.System | None, *, keep_going: bool):
    """Open every configured device.  ``keep_going``: a device that does not answer is noted
    in ``Rig.failed`` (by its config key) and the others are still opened; otherwise its
    DeviceError propagates (exit 2).  Everything opened is closed, simulators stopped, the
    camera's shutter closed on the way out.  ``rig`` as :func:`rig_of` checked it; ``system``
    gives the simulated camera its sensor and pixels."""
    from ..hardware.rig import open_filter_wheel, open_stage, start_simulators

    out = Rig()
    with contextlib.ExitStack() as stack:
        out.sims = start_simulators(rig)
        stack.callback(lambda: [s.stop() for s in out.sims.values()])

        def attempt(key: str, opener):
            try:
                return opener()
            except UserError as e:  # DeviceError is one
                if not keep_going:
                    raise
                out.failed[key] = str(e)
                return None

        if rig.filter_wheel is not None:
            out.wheel = attempt("rig.filter_wheel", lambda: open_filter_wheel(
                rig, out.sims["filter_wheel"].url if "filter_wheel" in out.sims else None))
            if out.wheel is not None:
                stack.callback(out.wheel.close)
        if rig.stage is not None:
            out.stage = attempt("rig.stage", lambda: open_stage(
                rig, out.sims["stage"].url if "stage" in out.sims else None))
            if out.stage is not None:
                stack.callback(out.stage.close)
        cc = rig.camera or C.RigCamera()
        out.camera = attempt("rig.camera", lambda: _camera(rig, system, cc, out))
        if out.camera is not None:
            stack.callback(out.camera.close)
            stack.callback(lambda: _safe(out.camera))
        yield out


def _safe(camera) -> None:
    with contextlib.suppress(UserError):
        camera.make_safe()


def _camera(rig: C.Rig, system: C.System | None, cc: C.RigCamera, devices: Rig):
    if cc.backend != "simulated":
        from ..hardware.cameras import open_real_camera

        return open_real_camera(cc)
    return card_camera(rig, system, cc, devices)


def card_camera(rig: C.Rig, system: C.System | None, cc: C.RigCamera, devices: Rig):
    """The simulated EMCCD looking at a test card (not the subject: no T is built), through
    the filter physically in the wheel (``rig.camera.filters.<name>.transmission``), with the
    EMCCD chain of ``system.camera.sensor`` (defaults without a ``system``)."""
    from ..hardware.camera import SimulatedEmccd
    from .plans import emccd_model

    sensor = system.camera.sensor if system is not None else C.Sensor()
    nx, ny = system.camera.pixels if system is not None else (64, 48)
    ramp = TEST_CARD_PHOTONS_PER_S * np.broadcast_to(0.5 + 0.5 * np.arange(nx) / max(nx - 1, 1), (ny, nx))
    names = {p: n for n, p in rig.filter_wheel.filters.items()} if rig.filter_wheel is not None else {}
    if "filter_wheel" in devices.sims:
        position = lambda: devices.sims["filter_wheel"].position  # noqa: E731
    elif devices.wheel is not None:
        position = lambda: devices.wheel.position  # noqa: E731
    else:
        position = lambda: None  # noqa: E731
    if "stage" in devices.sims:
        height = lambda: devices.sims["stage"].position_mm  # noqa: E731
    elif devices.stage is not None:
        height = devices.stage.position_mm
    else:
        height = lambda: 0.0  # noqa: E731

    def filter_name() -> str:
        p = position()
        return "open" if p is None else names.get(p, f"position {p}")

    def render(height_mm: float, name: str) -> np.ndarray:
        spec = cc.filters.get(name)
        return ramp * (1.0 if spec is None else spec.transmission)

    return SimulatedEmccd(render, stage_height_mm=height, filter_name=filter_name,
                          sensor=emccd_model(sensor, 0.1), seed=0, native_binning=cc.binning,
                          setpoint_c=cc.setpoint_c, ambient_c=cc.ambient_c, dark_doubling_c=cc.dark_doubling_c,
                          em_gain_range=tuple(cc.em_gain_range), time_scale=rig.time_scale, shape=(ny, nx))


def lowest_gain(rig: C.Rig) -> float:
    """The smallest EM gain the configured camera accepts (1 at least)."""
    cc = rig.camera or C.RigCamera()
    return max(1.0, float(cc.em_gain_range[0]))


def write_frame(path: Path, counts: np.ndarray, camera, **metadata) -> Path:
    """``counts`` as a 16-bit TIFF (atomically), with the settings the camera reports."""
    from ..imaging.imagefiles import write_image

    ident = camera.identity()
    meta = {"fluxmap:units": "counts", "fluxmap:exposure_s": float(camera.exposure_s),
            "fluxmap:em_gain": float(camera.em_gain), "fluxmap:binning": int(camera.binning),
            "fluxmap:temperature_c": float(camera.temperature_c), "fluxmap:camera": ident.model,
            "fluxmap:camera_serial": ident.serial}
    meta.update({f"fluxmap:{k}": v for k, v in metadata.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.asarray(counts, np.uint16), metadata=meta)
    return path


def describe(counts: np.ndarray) -> str:
    c = np.asarray(counts, float)
    return f"mean {c.mean():.1f} counts (min {c.min():.0f}, max {c.max():.0f})"
