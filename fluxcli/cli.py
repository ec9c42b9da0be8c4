"""``fluxmap <stage> CONFIG.yaml``: parse, load the config, call a stage, map errors to exit codes.

Exit codes: 0 success, 2 bad input (config, files, arguments), 130 interrupted.
"""

from __future__ import annotations

import sys
import textwrap
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
)

ConfigArg = typer.Argument(..., help="The experiment's YAML config.", show_default=False)
SetOpt = typer.Option(None, "--set", help="Override a config key: dotted.key=value (repeatable).")
ForceOpt = typer.Option(False, "--force", help="Recompute even when an up-to-date artefact exists.")
JobsOpt = typer.Option(1, "--jobs", "-j", min=1, help="Worker processes.")
QuietOpt = typer.Option(False, "--quiet", "-q", help="Print nothing but errors.")


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
    "report": _GEOMETRY,
    "calibrate": ("system", "system.camera", "calibrate"),
    "capture-surface": ("rig", "capture"),
}


def _run(name: str, stage: Callable, config: Path, overrides: Optional[List[str]], force: bool, jobs: int,
         quiet: bool) -> None:
    from .config import load_config, require
    from .stages.context import RunContext

    try:
        cfg = load_config(config, overrides or [])
        if not getattr(stage, "not_built", False):
            require(cfg, name, STAGE_REQUIRES.get(name, ()))
        ctx = RunContext(force=force, jobs=jobs, quiet=quiet, overrides=tuple(overrides or ()))
        out = stage(cfg, ctx)
        if not quiet and out is not None:
            typer.echo(f"output: {out}")
    except UserError as e:
        _fail(str(e))
    except ValueError as e:  # the science packages' word for "these numbers cannot be used"
        _fail(f"invalid input: {e}")
    except KeyboardInterrupt:
        typer.echo("fluxmap: interrupted; artefacts already written are complete, partial ones were discarded.", err=True)
        raise typer.Exit(130)


def _not_built(name: str, issue: str) -> Callable:
    def stage(cfg, ctx):
        raise UserError(f"the '{name}' stage is not built yet in fluxmap {__version__} ({issue}); "
                        f"config {cfg.path} was read and is valid.")
    stage.not_built = True  # type: ignore[attr-defined]
    return stage


def _stage_command(name: str, module: str | None, doc: str) -> None:
    """Register ``fluxmap <name> CONFIG`` running ``fluxcli.stages.<module>.run`` (one lifecycle for all)."""

    def command(config: Path = ConfigArg, set_: Optional[List[str]] = SetOpt, force: bool = ForceOpt,
                jobs: int = JobsOpt, quiet: bool = QuietOpt) -> None:
        if module is None:
            stage = _not_built(name, "not built yet")
        else:
            import importlib

            stage = importlib.import_module(f".stages.{module}", __package__).run
        _run(name, stage, config, set_, force, jobs, quiet)

    command.__doc__ = doc
    app.command(name)(command)


_stage_command("build-T", "build_t", """Compute the transfer matrix T of each pose (cached by content).

    $ fluxmap build-T configs/paper-3d.yaml --jobs 2
    """)
_stage_command("simulate", "simulate", """Make ground-truth surface fluxes and realistic camera images.

    $ fluxmap simulate configs/paper-2d.yaml
    """)
_stage_command("reconstruct", "reconstruct", """Invert images into surface flux (photons per element).

    $ fluxmap reconstruct configs/paper-2d.yaml --jobs 2
    """)
_stage_command("report", "report", """Figures, summary.json and a self-contained HTML page, from the artefacts.

    $ fluxmap report configs/paper-3d.yaml
    """)
_stage_command("calibrate", None, """(Not built yet.) Derive the camera model from grid images.""")
_stage_command("capture-surface", None, """(Not built yet.) Drive the rig (or its simulator) and capture the surface and images.""")



# --------------------------------------------------------------------------- fluxmap rig ... (issue 11)
rig_app = typer.Typer(no_args_is_help=True, help="The rig's devices: simulators on the real wire protocols.")
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

def main() -> None:
    app()


if __name__ == "__main__":
    sys.exit(main())
