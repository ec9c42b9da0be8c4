"""``fluxmap rig snap CONFIG``: take frames with the configured camera and write them as TIFF.

Examples
--------
$ fluxmap rig snap configs/rig-sim.yaml                       # one lit frame, 0.1 s
$ fluxmap rig snap lab.yaml --exposure-s 2 --em-gain 100 --frames 5 --out focus.tif
$ fluxmap rig snap lab.yaml --dark                            # shutter closed

``--frames N`` takes one sequence of N frames (the camera's own sequence mode) and writes
``<out>-1.tif`` ... ``<out>-N.tif``; one frame goes to ``<out>`` (default
``<workdir>/snap.tif``).  The filter wheel and stage are not moved; the simulated camera
sees its test card through the filter in the beam.
"""

from __future__ import annotations

from pathlib import Path

from .. import config as C
from . import _rig
from .context import RunContext


def run(cfg: C.LoadedConfig, ctx: RunContext, *, exposure_s: float = 0.1, em_gain: float | None = None,
        frames: int = 1, dark: bool = False, out: Path | None = None) -> Path:
    out = Path(out) if out is not None else cfg.workdir / "snap.tif"
    rig = _rig.rig_of(cfg)
    with _rig.open_rig(rig, cfg.model.system, keep_going=False) as devices:
        camera = devices.camera
        camera.exposure_s = exposure_s
        camera.em_gain = _rig.lowest_gain(rig) if em_gain is None else float(em_gain)
        camera.shutter_open = not dark
        counts = camera.sequence(frames)
        camera.make_safe()
        paths = [out] if frames == 1 else [out.with_name(f"{out.stem}-{k + 1}{out.suffix}") for k in range(frames)]
        for k, (path, frame) in enumerate(zip(paths, counts)):
            _rig.write_frame(path, frame, camera, shutter_open=int(not dark), frame=k + 1, frames=frames)
            ctx.say(f"rig snap: {path}: {_rig.describe(frame)}")
    return paths[0] if frames == 1 else out.parent
