"""The ``simulation`` artefact (``<workdir>/simulation.h5``, made by ``fluxmap simulate``): the
ground-truth surface flux and the camera images made from it.

:class:`Simulation` is the container (every field with its unit and meaning: the kind's
schema is made from it); :func:`write` and :func:`read` are the only code that touches the
file's layout.  A Monte Carlo simulation adds a :class:`MonteCarloRecord`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..surface.mesh import Surface
from .kinds import SURFACE_DATASETS, Dataset, Kind, attribute, datasets_of, quantity, register
from .pieces import read_surface, write_surface
from .store import Provenance, open_artefact, put, write_artefact

FILE_NAME = "simulation.h5"  # in the workdir
IMAGE_LAYOUT = "noisy[level, repeat, pose, row, col]; noiseless[level, pose, row, col]"
_PACKED = dict(compression="gzip", fletcher32=True)


@dataclass
class MonteCarloRecord:
    """What one photon run says besides the truth and the images (``simulate.flux.kind: montecarlo``)."""

    photons_per_element: np.ndarray = quantity(
        "montecarlo/photons_per_element", "photons", "Monte Carlo truth: photons that left through each element",
        required=False)
    exit_angle_histogram: np.ndarray = quantity(
        "montecarlo/exit_angle_histogram", "photons", "escaped photons per bin of angle from the normal (in air)",
        required=False)
    exit_angle_edges_deg: np.ndarray = quantity(
        "montecarlo/exit_angle_edges_deg", "deg", "bin edges of the exit-angle histogram", required=False)
    reached_lens: np.ndarray = quantity(
        "montecarlo/reached_lens", "photons", "[pose, view] photons that crossed the lens unobstructed", required=False)
    on_sensor: np.ndarray = quantity("montecarlo/on_sensor", "photons", "[pose, view] ... and landed on a pixel",
                                     required=False)
    view_names: list = attribute("montecarlo@views", "", "the views of reached_lens and on_sensor (JSON)")
    launched: int = attribute("montecarlo@launched", "photons", "photons launched")
    escaped: int = attribute("montecarlo@escaped", "photons", "photons that left the phantom")
    absorbed: int = attribute("montecarlo@absorbed", "photons", "photons absorbed")
    lost: int = attribute("montecarlo@lost", "photons", "photons lost to numerical limits")
    not_on_elements: float = attribute("montecarlo@not_on_elements", "photons",
                                       "photons that left through faces of no element (cylinder caps)")
    rest_shift_mm: np.ndarray = attribute("montecarlo@rest_shift_mm", "mm",
                                          "the phantom's own frame to its place at rest on the stage")
    photons: dict | None = quantity("montecarlo/photons", "", "every escaping photon (simulate.flux.keep_photons): "
                                    "position_mm, direction, face", required=False, default=None)


_PHOTON_DATASETS = (
    ("montecarlo/photons/position_mm", "mm", "exit point of every escaping photon, phantom's own frame"),
    ("montecarlo/photons/direction", "", "its unit direction in air, phantom's own frame"),
    ("montecarlo/photons/face", "", "face of the refined surface it left through (-1: none)"),
)


@dataclass
class Simulation:
    """Ground truth per element of the subject at rest and the images of every pose at every
    signal level (``a = T_fwd b`` with noise, or a Monte Carlo run's photons)."""

    surface: Surface = quantity("surface", "mm", "the subject at rest: the reconstruction's elements")
    power: np.ndarray = quantity("truth/power", "photons per exposure, per element", "ground truth at rest")
    exitance: np.ndarray = quantity("truth/exitance", "photons mm^-2 per exposure", "power / element area")
    levels_peak_photons: np.ndarray = quantity("truth/levels_peak_photons", "photons",
                                               "brightest element's power at each signal level")
    level_scale: np.ndarray = quantity("truth/level_scale", "", "truth at level l = power * level_scale[l]")
    power_fine: np.ndarray = quantity(
        "truth/power_fine", "photons per exposure, per fine face",
        "the truth on the refined surface the images were made from (summed per element = truth/power)",
        required=False)
    fine_parent: np.ndarray = quantity("truth/fine_parent", "", "element of each fine face", required=False)
    heights_mm: np.ndarray = quantity("poses/heights_mm", "mm", "stage height of each pose")
    rotations_deg: np.ndarray = quantity("poses/rotations_deg", "deg", "rotation of each pose")
    T_fwd_keys: np.ndarray = quantity("poses/T_fwd_keys", "", "forward T of each pose (T-cache key)")
    noiseless: np.ndarray = quantity("images/noiseless", "photons", "noiseless[level, pose, row, col]")
    noisy: np.ndarray = quantity("images/noisy", "photons", "noisy[level, repeat, pose, row, col]")
    counts: np.ndarray | None = quantity("images/counts", "ADC counts", "EMCCD counts[level, repeat, pose, row, col]",
                                         required=False)
    max_snr: np.ndarray = quantity("images/max_snr", "", "sqrt(max a) per level and pose (the paper's Table 1)")
    truth_kind: str = attribute("truth@kind", "", "simulate.flux.kind")
    truth_notes: dict = attribute("truth@notes", "", "what the truth's model reports (JSON)")
    noise_model: str = attribute("images@noise_model", "", "simulate.noise.model (or how Monte Carlo photons count)")
    seed: int = attribute("images@seed", "", "the noise's (or the photon run's) seed")
    exposure_s: float = attribute("images@exposure_s", "s", "exposure of the images")
    inputs_digest: str = attribute("@inputs_digest", "", "sha256 of what the simulation depends on")
    truth_seconds: float = attribute("@truth_seconds", "s", "time to make the truth (NaN: reproducible run)")
    transfer_fwd: dict | None = attribute("@transfer_fwd", "", "the forward T's sampling (JSON)", default=None)
    transfer_fwd_cache: str | None = attribute("@transfer_fwd_cache", "",
                                               "the T cache holding the forward T, relative to this file", default=None)
    montecarlo: MonteCarloRecord | None = None


KIND = register(Kind("simulation", 2, "fluxmap simulate", "ground-truth surface flux and simulated images", (
    *SURFACE_DATASETS, *(d for d in datasets_of(Simulation) if d.name != "surface"),
    *(d for d in datasets_of(MonteCarloRecord) if d.name != "montecarlo/photons"),
    *(Dataset(n, u, m, required=False) for n, u, m in _PHOTON_DATASETS),
)))


def write(path: Path, sim: Simulation, *, config_sha256: str = "", inputs: dict[str, str] | None = None,
          provenance: Provenance | None = None) -> Path:
    """Write ``sim`` atomically as ``path``."""
    P, ny, nx = sim.noiseless.shape[1:]
    with write_artefact(path, "simulation", config_sha256=config_sha256, inputs=inputs, provenance=provenance) as f:
        f.attrs["inputs_digest"] = sim.inputs_digest
        write_surface(f.create_group("surface"), sim.surface)
        put(f, "truth/power", sim.power)
        put(f, "truth/exitance", sim.exitance)
        if sim.power_fine is not None:
            put(f, "truth/power_fine", sim.power_fine)
            put(f, "truth/fine_parent", sim.fine_parent)
        g = f["truth"]
        g.attrs["kind"] = sim.truth_kind
        g.attrs["notes"] = json.dumps(sim.truth_notes)
        put(f, "truth/levels_peak_photons", sim.levels_peak_photons)
        put(f, "truth/level_scale", sim.level_scale)
        put(f, "poses/heights_mm", sim.heights_mm)
        put(f, "poses/rotations_deg", sim.rotations_deg)
        put(f, "poses/T_fwd_keys", np.asarray(sim.T_fwd_keys, dtype="S64"))
        put(f, "images/noiseless", sim.noiseless, chunks=(1, 1, ny, nx), **_PACKED)
        put(f, "images/noisy", sim.noisy, chunks=(1, 1, 1, ny, nx), **_PACKED)
        if sim.counts is not None:
            put(f, "images/counts", sim.counts, chunks=(1, 1, 1, ny, nx), **_PACKED)
        put(f, "images/max_snr", sim.max_snr)
        ig = f["images"]
        ig.attrs["layout"] = IMAGE_LAYOUT
        ig.attrs["noise_model"] = sim.noise_model
        ig.attrs["seed"] = sim.seed
        ig.attrs["exposure_s"] = sim.exposure_s
        mc = sim.montecarlo
        if mc is not None:
            mg = f.create_group("montecarlo")
            put(f, "montecarlo/photons_per_element", mc.photons_per_element)
            put(f, "montecarlo/exit_angle_histogram", mc.exit_angle_histogram)
            put(f, "montecarlo/exit_angle_edges_deg", mc.exit_angle_edges_deg)
            put(f, "montecarlo/reached_lens", mc.reached_lens)
            put(f, "montecarlo/on_sensor", mc.on_sensor)
            mg.attrs["views"] = json.dumps(list(mc.view_names))
            for k in ("launched", "escaped", "absorbed", "lost"):
                mg.attrs[k] = int(getattr(mc, k))
            mg.attrs["not_on_elements"] = mc.not_on_elements
            mg.attrs["rest_shift_mm"] = mc.rest_shift_mm
            for k, v in (mc.photons or {}).items():
                put(f, f"montecarlo/photons/{k}", v, **_PACKED)
        if sim.transfer_fwd is not None:
            f.attrs["transfer_fwd"] = json.dumps(sim.transfer_fwd)
        if sim.transfer_fwd_cache is not None:
            f.attrs["transfer_fwd_cache"] = sim.transfer_fwd_cache
        f.attrs["truth_seconds"] = sim.truth_seconds
    return Path(path)


def read(path: Path, *, images: bool = True) -> Simulation:
    """The simulation in ``path`` (a UserError naming the file when it is not one); with
    ``images=False`` the image arrays are left out (None): the truth and poses only."""
    with open_artefact(path, "simulation") as f:
        def opt(name):
            return f[name][()] if name in f else None

        def img(name):
            return f[name][()] if images and name in f else None

        mc = None
        if "montecarlo" in f:
            g = f["montecarlo"]
            photons = ({k: g["photons"][k][()] for k in g["photons"]} if "photons" in g else None)
            mc = MonteCarloRecord(g["photons_per_element"][()], g["exit_angle_histogram"][()],
                                  g["exit_angle_edges_deg"][()], g["reached_lens"][()], g["on_sensor"][()],
                                  json.loads(g.attrs["views"]), *(int(g.attrs[k]) for k in
                                                                  ("launched", "escaped", "absorbed", "lost")),
                                  float(g.attrs["not_on_elements"]), np.asarray(g.attrs["rest_shift_mm"]), photons)
        t, ig = f["truth"], f["images"]
        return Simulation(
            surface=read_surface(f["surface"]), power=f["truth/power"][()], exitance=f["truth/exitance"][()],
            levels_peak_photons=f["truth/levels_peak_photons"][()], level_scale=f["truth/level_scale"][()],
            power_fine=opt("truth/power_fine"), fine_parent=opt("truth/fine_parent"),
            heights_mm=f["poses/heights_mm"][()], rotations_deg=f["poses/rotations_deg"][()],
            T_fwd_keys=np.array([k.decode() for k in f["poses/T_fwd_keys"][()]]),
            noiseless=img("images/noiseless"), noisy=img("images/noisy"), counts=img("images/counts"),
            max_snr=f["images/max_snr"][()], truth_kind=str(t.attrs.get("kind", "")),
            truth_notes=json.loads(t.attrs.get("notes", "{}")), noise_model=str(ig.attrs.get("noise_model", "")),
            seed=int(ig.attrs.get("seed", 0)), exposure_s=float(ig.attrs.get("exposure_s", np.nan)),
            inputs_digest=str(f.attrs.get("inputs_digest", "")),
            truth_seconds=float(f.attrs.get("truth_seconds", np.nan)),
            transfer_fwd=json.loads(f.attrs["transfer_fwd"]) if "transfer_fwd" in f.attrs else None,
            transfer_fwd_cache=str(f.attrs["transfer_fwd_cache"]) if "transfer_fwd_cache" in f.attrs else None,
            montecarlo=mc)

