"""``fluxmap <stage> CONFIG.yaml``: parse, load the config, call a stage, map errors to exit codes.

Exit codes: 0 success, 2 bad input (a ``UserError``: config, files, arguments; also out of memory and
an operating-system error naming a file or a full/read-only disk), 1 a bug (any other exception, with its
traceback), 130 interrupted, 143 terminated.
"""

from __future__ import annotations

import os
import signal
import sys
import textwrap
import traceback
from pathlib import Path
from typing import Callable, List, Optional

import typer

from . import __version__
from .errors import UserError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="fluxmap: quantitative light-flux maps on the surface of imaged subjects.\n\n"
    "Each stage reads a YAML config and the HDF5 artefacts of earlier stages, and writes its own.",
    context_settings={"help_option_names": ["-h", "--help"]},
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain click help: flags show as '--force', not '--force <bool>'
)

ConfigArg = typer.Argument(..., help="The experiment's YAML config.", show_default=False, metavar="CONFIG.yaml")
SetOpt = typer.Option(None, "--set", metavar="KEY=VALUE", help="Override a config key: dotted.key=value (repeatable).")
ForceOpt = typer.Option(False, "--force", help="Recompute even when an up-to-date artefact exists.")
JobsOpt = typer.Option(1, "--jobs", "-j", min=1, help="Worker processes.")
QuietOpt = typer.Option(False, "--quiet", "-q", help="Print nothing but errors.")
SchedulerOpt = typer.Option(None, "--scheduler", envvar="FLUXMAP_SCHEDULER", metavar="ADDRESS",
                            help="Send the run's independent tasks (T per pose, sweep cells) to the Dask scheduler "
                                 "at ADDRESS (e.g. tcp://host:8786); without it they run here (--jobs).")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"fluxmap {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Show the version and exit.")) -> None:
    pass


def _fail(message: str) -> None:
    text = textwrap.fill(f"fluxmap: error: {message}", width=100, break_long_words=False, break_on_hyphens=False)
    typer.echo(text, err=True)
    raise typer.Exit(2)


# What each stage needs from the config beyond its own defaults; a missing key is exit 2 naming it.
_GEOMETRY = ("system", "system.camera.lens", "system.camera.pose", "subject")
STAGE_REQUIRES: dict[str, tuple[str, ...]] = {
    "build-T": _GEOMETRY,
    "simulate": _GEOMETRY + ("simulate",),
    "reconstruct": _GEOMETRY,
    "report": (),  # the stage checks: geometry for a reconstruction, nothing for a calibrate-only workdir
    "calibrate": ("calibrate",),  # a grid needs system.camera (checked by the stage); radiometric alone does not
    "capture-surface": ("rig", "capture"),
    "summary": (),
}


class Terminated(BaseException):
    """SIGTERM: unwind like Ctrl-C (temporary files removed, workers killed), exit 143."""


def _on_sigint(signum, frame):
    sys.stderr.write("\nfluxmap: Ctrl-C: stopping (partial files are discarded) ...\n")
    sys.stderr.flush()
    raise KeyboardInterrupt


def _on_sigterm(signum, frame):
    raise Terminated


def _signals():
    """Install the Ctrl-C / SIGTERM handlers (main thread only); returns what to restore."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGINT, _on_sigint), signal.signal(signal.SIGTERM, _on_sigterm)


def _guard(body: Callable[[], None]) -> None:
    """Run a command body and map what it raises to exit codes: 2 bad input (one
    paragraph, no traceback), 130 Ctrl-C, 143 SIGTERM, 1 a bug (traceback + a request to report it)."""
    old = _signals()
    try:
        body()
    except UserError as e:  # the only exception that means "bad input"; a plain ValueError is a bug
        _fail(str(e))
    except MemoryError:
        _fail("out of memory: the problem is larger than this machine can hold; use fewer pixels "
              "(system.camera.pixels), fewer elements (subject.surface) or fewer poses (subject.poses).")
    except OSError as e:
        import errno

        if getattr(e, "filename", None) is not None:
            _fail(f"cannot use {e.filename}: {e.strerror or e} (check the path, its permissions and the free space).")
        if e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS):
            _fail(f"{e.strerror or e}: the workdir or the T cache (transfer.cache_dir) cannot take the file being "
                  "written; free some space or choose another folder.")
        _bug()
    except KeyboardInterrupt:
        typer.echo("fluxmap: interrupted; artefacts already written are complete, partial ones were discarded.", err=True)
        _stop(130)
    except Terminated:
        typer.echo("fluxmap: terminated; partial files were discarded.", err=True)
        _stop(143)
    except (typer.Exit, SystemExit):
        raise
    except Exception:
        _bug()
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old[0])
            signal.signal(signal.SIGTERM, old[1])


_WHOLE_PROCESS = [False]  # main(): this process is the command (not a test's in-process runner)


def _stop(code: int) -> None:
    """End an interrupted command with ``code``.  Everything it wrote is already complete or
    removed, and its workers are killed, when this runs.  As the whole process it ends here
    (streams flushed, no interpreter exit hooks): Python 3.11's hook for process pools wakes a
    pool's manager thread without the lock under which that thread closes its pipe (3.12 takes
    it), and about one interrupted build-T in 8 on a loaded machine printed "OSError: Bad file
    descriptor" with a traceback under the clean message above."""
    if _WHOLE_PROCESS[0]:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed stream: nothing left to flush
                pass
        os._exit(code)
    raise typer.Exit(code)


def _bug() -> None:
    traceback.print_exc()
    typer.echo(f"fluxmap {__version__}: internal error (a bug, not your input). Please report it with the "
               "command line, the config and the traceback above.", err=True)
    raise typer.Exit(1)


def _run(name: str, stage: Callable, config: Path, overrides: Optional[List[str]], force: bool, jobs: int,
         quiet: bool, scheduler: Optional[str] = None) -> None:
    def body() -> None:
        import contextlib

        from .config import load_config, require
        from .stages.context import RunContext

        cfg = load_config(config, overrides or [])
        if not getattr(stage, "not_built", False):
            require(cfg, name, STAGE_REQUIRES.get(name, ()))
        with contextlib.ExitStack() as stack:
            client = None
            if scheduler:  # reach the cluster before any work (an unreachable address is exit 2)
                from .cluster import connect

                client = stack.enter_context(connect(scheduler))
            ctx = RunContext(force=force, jobs=jobs, quiet=quiet, overrides=tuple(overrides or ()), client=client)
            out = stage(cfg, ctx)
        if not quiet and out is not None:
            typer.echo(f"output: {out}")

    _guard(body)


def _not_built(name: str, issue: str) -> Callable:
    def stage(cfg, ctx):
        raise UserError(f"the '{name}' stage is not built yet in fluxmap {__version__} ({issue}); "
                        f"config {cfg.path} was read and is valid.")
    stage.not_built = True  # type: ignore[attr-defined]
    return stage


# stage name -> the module under fluxcli.stages that runs it (None: registered but not built)
STAGE_MODULES: dict[str, str | None] = {}


def _stage_command(name: str, module: str | None, doc: str, cluster: bool = False) -> None:
    """Register ``fluxmap <name> CONFIG`` running ``fluxcli.stages.<module>.run`` (one lifecycle for all);
    ``cluster``: the stage takes ``--scheduler`` (its tasks can run on a Dask cluster)."""
    STAGE_MODULES[name] = module

    def stage_of():
        if module is None:
            return _not_built(name, "not built yet")
        import importlib

        return importlib.import_module(f".stages.{module}", __package__).run

    def command(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt, force: bool = ForceOpt,
                jobs: int = JobsOpt, quiet: bool = QuietOpt) -> None:
        _run(name, stage_of(), config, set_, force, jobs, quiet)

    def cluster_command(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt, force: bool = ForceOpt,
                        jobs: int = JobsOpt, quiet: bool = QuietOpt, scheduler: Optional[str] = SchedulerOpt) -> None:
        _run(name, stage_of(), config, set_, force, jobs, quiet, scheduler)

    chosen = cluster_command if cluster else command
    chosen.__doc__ = doc
    app.command(name)(chosen)


_stage_command("build-T", "build_t", """Compute the transfer matrix T of each pose (cached by content).

    $ fluxmap build-T configs/paper-3d.yaml --jobs 2
    """, cluster=True)
_stage_command("simulate", "simulate", """Make ground-truth surface fluxes and realistic camera images.

    $ fluxmap simulate configs/paper-2d.yaml
    """, cluster=True)
_stage_command("reconstruct", "reconstruct", """Invert images into surface flux (photons per element).

    $ fluxmap reconstruct configs/paper-2d.yaml --jobs 2
    """, cluster=True)
_stage_command("report", "report", """Figures, summary.json and a self-contained HTML page, from the artefacts.

    $ fluxmap report configs/paper-3d.yaml
    """)
_stage_command("summary", "summary", """Per-pose totals, their spread, the truth, and where the report is, from the artefacts.

    $ fluxmap summary configs/demo.yaml
    """)
_stage_command("calibrate", "calibrate", """Derive the camera model from grid images (and the sensor from radiometric frames).

    $ fluxmap calibrate configs/calibrate.yaml
    """)


@app.command("capture-surface")
def capture_surface(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt,
                    force: bool = typer.Option(False, "--force", help="Start the capture over (replaces capture.h5)."),
                    resume: bool = typer.Option(False, "--resume", help="Continue capture.h5: take only the frames it lacks."),
                    jobs: int = JobsOpt, quiet: bool = QuietOpt) -> None:
    """Drive the rig (or its simulators) and acquire the emission images of the plan in 'capture:'.

    $ fluxmap capture-surface configs/demo-rig.yaml --resume
    """
    from functools import partial

    from .stages import capture as stage

    _run("capture-surface", partial(stage.run, resume=resume), config, set_, force, jobs, quiet)


@app.command("study")
def study(study_file: Path = typer.Argument(..., help="A study file: sessions (reconstruction artefacts with subject "
                                            "and day) and regions of interest.", show_default=False),
          quiet: bool = QuietOpt) -> None:
    """Regions of interest over sessions, subjects and filters: study.csv and a page with error bars.

    $ fluxmap study studies/tumour.yaml
    """
    def body() -> None:
        from .stages import study as stage
        from .stages.context import RunContext

        out = stage.run(study_file, RunContext(quiet=quiet))
        if not quiet:
            typer.echo(f"output: {out}")

    _guard(body)


@app.command("info")
def info(artefact: Path = typer.Argument(..., help="An HDF5 artefact (transfer.h5, simulation.h5, a T-cache file, ...).",
                                         show_default=False)) -> None:
    """Print what an artefact holds and how it was made (config, geometry, input files).

    $ fluxmap info runs/demo/simulation.h5
    """
    from .artefacts.info import describe

    _guard(lambda: typer.echo(describe(artefact)))


# --------------------------------------------------------------------------- fluxmap rig ... (issue 11)
rig_app = typer.Typer(no_args_is_help=True, help="The rig's devices: check them, snap frames, serve simulators on the real "
                                                 "wire protocols.")
app.add_typer(rig_app, name="rig")
STAGE_REQUIRES["rig serve"] = ("rig",)


@rig_app.command("serve")
def rig_serve(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt) -> None:
    """Serve simulators of the devices in `rig` until SIGINT/SIGTERM.

    Prints one line per device, `<device> <url-or-pty-path>`, then `ready`.  A port `pty`
    makes a new pseudo terminal, `socket://HOST:PORT` listens there (PORT 0: any free port).

    $ fluxmap rig serve configs/rig-sim.yaml
    """
    from .stages import rig_serve as stage

    _run("rig serve", stage.run, config, set_, False, 1, False)


STAGE_REQUIRES["rig check"] = ("rig",)
STAGE_REQUIRES["rig snap"] = ("rig",)
STAGE_MODULES["rig check"] = "rig_check"
STAGE_MODULES["rig snap"] = "rig_snap"
ExposureOpt = typer.Option(0.1, "--exposure-s", min=1e-6, help="Exposure of each frame (s).")
GainOpt = typer.Option(None, "--em-gain", min=1.0, help="EM gain (default: the lowest of rig.camera.em_gain_range).")


@rig_app.command("check")
def rig_check(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt,
              move: bool = typer.Option(True, "--move/--no-move", help="Move the wheel and the stage (0.5 mm) and back."),
              exposure_s: float = ExposureOpt, em_gain: Optional[float] = GainOpt, quiet: bool = QuietOpt) -> None:
    """Talk to every device in `rig`: model, serial, firmware; move the wheel and the stage a
    little and back; sensor temperature and cooler; one dark and one lit frame as TIFF.
    Exit 2 naming each device that does not answer.

    $ fluxmap rig check configs/rig-sim.yaml
    """
    from functools import partial

    from .stages import rig_check as stage

    _run("rig check", partial(stage.run, move=move, exposure_s=exposure_s, em_gain=em_gain), config, set_, False, 1,
         quiet)


@rig_app.command("snap")
def rig_snap(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt, exposure_s: float = ExposureOpt,
             em_gain: Optional[float] = GainOpt,
             frames: int = typer.Option(1, "--frames", min=1, help="Frames in one sequence (one TIFF each)."),
             dark: bool = typer.Option(False, "--dark", help="Shutter closed."),
             out: Optional[Path] = typer.Option(None, "--out", help="TIFF to write (default <workdir>/snap.tif)."),
             quiet: bool = QuietOpt) -> None:
    """Take frames with the configured camera and write them as TIFF (counts, 16 bit).

    $ fluxmap rig snap configs/rig-sim.yaml --exposure-s 0.5 --frames 3
    """
    from functools import partial

    from .stages import rig_snap as stage

    _run("rig snap", partial(stage.run, exposure_s=exposure_s, em_gain=em_gain, frames=frames, dark=dark, out=out),
         config, set_, False, 1, quiet)

def main() -> None:
    _WHOLE_PROCESS[0] = True
    app()


if __name__ == "__main__":
    sys.exit(main())
