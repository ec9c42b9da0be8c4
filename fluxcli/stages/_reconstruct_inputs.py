"""reconstruct's images: from simulation.h5, image files named per pose, or a capture.

Each source is checked against what it claims to be (pixels, units, poses, saturation) and
turned into photons; :func:`photon_noise` gives the noise model every weight and σ come from.
Everything here takes parts of the run plan (:class:`~._reconstruct_plan.ImagesPlan`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import artefacts as A
from ..errors import UserError
from ..imaging import noise as N
from ..imaging.imagefiles import read_image, sample_type
from ..imaging.sensor_maps import below_bias, counts_to_photons_with_maps
from ..inverse.emission_checks import photons_medium_note
from .plans import emccd_model
from ._radiometric import read_radiometric_maps

@dataclass
class Inputs:
    images: np.ndarray  # (P, ny, nx) photons
    valid: np.ndarray  # (P, ny, nx) bool: not saturated, finite
    truth: np.ndarray | None  # (n_elements,) photons, or None
    source: str
    snr: np.ndarray | None = None  # (P,)
    files: dict[str, Path] | None = None  # name -> input file (image files or simulation.h5), for provenance
    noise_kind: str = "poisson"  # how the images are noisy: gaussian | poisson | emccd
    exposure_s: float = 1.0
    frames_averaged: int = 1
    exposure_recorded: bool = False  # exposure_s is what the image files record (not the config's default)


def simulation_path(im) -> Path:
    """simulation.h5, which must exist when the images come from it (``im``: ImagesPlan)."""
    path = im.simulation
    if not path.is_file():
        raise UserError(f"reconstruct: no images: {path} does not exist (run 'fluxmap simulate' first) and "
                        "reconstruct.images names no files.")
    return path



def from_capture(im, n_elements: int, filter_name: str | None = None) -> Inputs:
    """One image per pose (= stage height) from a capture: darks subtracted, counts -> photons
    (``filter_name``: this filter's frames; default the first of reconstruct.images.filters, else .filter)."""
    from ..artefacts.capture import read_capture

    path = im.capture
    src = im.source
    if filter_name is None:
        filter_name = src.filters[0] if src.filters else src.filter
    own = bool(filter_name) and filter_name in src.exposures_s  # the filter's own exposure, else the common one
    cap = read_capture(path, filter_name, src.exposures_s[filter_name] if own else src.exposure_s,
                       f"exposures_s.{filter_name}" if own else "exposure_s")
    order = cap.pose_order(list(im.heights_mm))
    photons, valid = N.capture_photons(cap, emccd_model(im.sensor, cap.exposure_s))
    nx, ny = im.pixels
    if photons.shape[1:] != (ny, nx):
        raise UserError(f"reconstruct.images.capture: {path} holds {photons.shape[2]} x {photons.shape[1]} pixel "
                        f"frames; system.camera.pixels is {nx} x {ny}.")
    truth = cap.truth_power if cap.truth_power is not None and len(cap.truth_power) == n_elements else None
    return Inputs(photons[order], valid[order] & np.isfinite(photons[order]), truth,
                  f"{path} filter {cap.filter}, {cap.repeats} repeat(s) averaged, {cap.n_darks} dark(s) subtracted",
                  files={"capture.h5": path}, noise_kind="emccd", exposure_s=float(cap.exposure_s),
                  frames_averaged=max(int(cap.repeats), 1))



def load_inputs(im, n_poses: int, n_elements: int, geometry: dict, config_path: Path,
                poses: list | None = None) -> Inputs:
    """The images of ``im`` (ImagesPlan); ``geometry``: what a simulation must have been made with."""
    rc = im
    if im.is_capture:
        return from_capture(im, n_elements)
    if im.source is not None:
        return _image_files(im, n_poses, poses)
    path = simulation_path(im)
    with A.open_artefact(path, "simulation") as f:
        # images simulated under another emission model are a model-mismatch experiment, not other
        # geometry: reconstructed, with a warning (_emission_checks); T itself is always this config's
        stored, now = _without_emission(A.read_provenance(f)), _without_emission(geometry)
        A.check_geometry(path, stored, now,
                         remedy=f"Run 'fluxmap simulate {config_path}' again, or reconstruct with the config it was made with")
        power = f["truth/power"][()]
        if len(power) != n_elements:
            raise UserError(f"reconstruct: {path} was simulated on {len(power)} elements; the subject now has "
                            f"{n_elements}. Run 'fluxmap simulate' again.")
        noisy = f["images/noisy"]
        L, R, P = noisy.shape[:3]
        if P != n_poses:
            raise UserError(f"reconstruct: {path} holds {P} pose(s); the config has {n_poses}. Simulate again.")
        if rc.level >= L or rc.repeat >= R:
            raise UserError(f"reconstruct.level/repeat: {path} holds {L} level(s) x {R} repeat(s); asked for "
                            f"level {rc.level}, repeat {rc.repeat}.")
        imgs = (f["images/noiseless"][rc.level] if rc.noiseless else noisy[rc.level, rc.repeat]).astype(float)
        valid = np.isfinite(imgs)
        if "counts" in f["images"] and not rc.noiseless:
            model = emccd_model(im.sensor, float(f["images"].attrs["exposure_s"]))
            sat = N.saturated(f["images/counts"][rc.level, rc.repeat], model)
            lit = f["images/noiseless"][rc.level] > 0
            for k in range(sat.shape[0]):
                if lit[k].any() and sat[k][lit[k]].mean() > MOSTLY_SATURATED:
                    raise UserError(f"reconstruct.level: at level {rc.level} ({path}) {sat[k][lit[k]].mean():.0%} of "
                                    f"the lit pixels of pose {k} are saturated; reconstruct a lower level or "
                                    "simulate with a lower simulate.noise.peaks_photons or system.camera.sensor.em_gain.")
            valid &= ~sat
        truth = power * f["truth/level_scale"][rc.level]
        snr = f["images/max_snr"][rc.level]
        kind = str(f["images"].attrs.get("noise_model", "poisson"))
        exposure_s = float(f["images"].attrs.get("exposure_s", 1.0))
    # named relative to the workdir: the artefact is the same in any clone
    return Inputs(imgs, valid, truth, f"{path.name} level {rc.level} " + ("noiseless" if rc.noiseless else f"repeat {rc.repeat}"),
                  snr, files={"simulation.h5": path}, noise_kind=kind if kind in N.NOISE_KINDS else "poisson",
                  exposure_s=exposure_s)


MOSTLY_SATURATED = 0.5  # refuse an image with more than this fraction of its pixels at full scale


def _image_files(plan_im, n_poses: int, poses: list | None) -> Inputs:
    """Images from files named per pose, each checked against what it claims to be."""
    im = plan_im.source
    nx, ny = plan_im.pixels
    if len(plan_im.files) != n_poses:
        raise UserError(f"reconstruct.images.files: {len(plan_im.files)} file(s) for {n_poses} pose(s) "
                        "(one file per pose, in subject.poses order: heights x rotations).")
    read = []
    for k, p in enumerate(plan_im.files):
        try:
            read.append(read_image(p))
        except ValueError as e:
            raise UserError(f"reconstruct.images.files[{k}]: {e}") from None
    exposure_s, recorded = _exposure_of(plan_im, [meta for _, meta in read])
    model = None
    if im.units == "counts":
        if not plan_im.sensor_given:
            raise UserError("reconstruct.images.units is counts, but system.camera.sensor is not given: converting "
                            "counts to photons needs the camera's bias, gain and quantum efficiency (give "
                            "system.camera.sensor, or images in photons).")
        model = emccd_model(plan_im.sensor, exposure_s)
    maps = {} if plan_im.calibration is None else read_radiometric_maps(  # per-pixel bias, dark, flat (radiometry)
        plan_im.calibration, "reconstruct.images.calibration", (ny, nx))
    imgs, valid = [], []
    for k, (p, (img, meta)) in enumerate(zip(plan_im.files, read)):
        where = f"reconstruct.images.files[{k}] ({p})"
        if img.shape != (ny, nx):
            raise UserError(f"{where} is {img.shape[1]} x {img.shape[0]} pixels; the camera has {nx} x {ny} "
                            "(system.camera.pixels).")
        said = meta.get("fluxmap:units", meta.get("fluxmap:unit"))  # 'unit': frames of rig snap before 27 Nov 2026
        stored = sample_type(p)
        if im.units == "photons" and stored.startswith(("uint", "int")) and not isinstance(said, str):
            raise UserError(f"{where} stores {stored} integers, which are camera counts, but reconstruct.images.units "
                            "is photons; set reconstruct.images.units: counts (with system.camera.sensor), or give "
                            "photons as floating-point images.")
        if isinstance(said, str) and said != im.units:
            raise UserError(f"{where} holds {said} (its metadata says fluxmap:units = {said}), but "
                            f"reconstruct.images.units is {im.units}.")
        if poses is not None:
            pose = poses[k]
            for key, want in (("fluxmap:height_mm", pose.height_mm), ("fluxmap:rotation_deg", pose.rotation_deg)):
                got = meta.get(key)
                if isinstance(got, (int, float)) and abs(float(got) - want) > 1e-6:
                    raise UserError(f"{where} was taken at {key.split(':')[1]} = {got:g} (its metadata), but it is "
                                    f"listed for pose {pose.label}: reconstruct.images.files must follow "
                                    "subject.poses (heights x rotations).")
        finite = np.isfinite(img)
        if not finite.any():
            raise UserError(f"{where}: every pixel is NaN or infinite.")
        ok = finite
        if model is not None:
            sat = N.saturated(np.where(finite, img, 0), model) & finite
            if sat.sum() > MOSTLY_SATURATED * finite.sum():
                raise UserError(f"{where}: {sat.sum() / finite.sum():.0%} of the pixels are saturated (at "
                                f"{2 ** model.bit_depth - 1} counts); shorten the exposure or lower the EM gain.")
            ok = finite & ~sat
            low = below_bias(img, model, ok, maps.get("bias_counts_map"))
            if low is not None:
                bias = (f"the bias map of {plan_im.calibration}, median {np.median(maps['bias_counts_map']):.6g}" if
                        maps.get("bias_counts_map") is not None else f"system.camera.sensor.bias_counts {model.bias_counts:g}")
                raise UserError(f"{where}: {low[0]:.0%} of its pixels lie more than {low[1]:.3g} counts (5 read-noise sigmas) "
                                f"below the bias ({bias}); its median is {low[2]:.6g} counts. Raw counts never fall that far "
                                "below the bias: was the image bias-subtracted or scaled already (give it as it left the camera, "
                                "or set system.camera.sensor.bias_counts: 0), or is the bias another camera's?")
            img = counts_to_photons_with_maps(np.where(finite, img, 0), model, **maps)
            ok &= np.isfinite(img)  # dead pixels of the flat map
            img = np.where(finite, img, np.nan)
        if not np.any(img[ok] > 0):
            raise UserError(f"{where}: no pixel holds a positive signal (all are zero or negative"
                            + (" after the bias is subtracted" if model is not None else "") + "); a reconstruction "
                            "from it would be zero everywhere.")
        imgs.append(img)
        valid.append(ok)
    files = {f"image pose {k}": p for k, p in enumerate(plan_im.files)}
    return Inputs(np.array(imgs), np.array(valid), None, "files", files=files,
                  noise_kind="emccd" if model is not None else "poisson", exposure_s=exposure_s,
                  exposure_recorded=recorded)


def _exposure_of(plan_im, metas: list[dict]) -> tuple[float, bool]:
    """The images' exposure (s) and whether the files record it: what they record (fluxmap's
    own frames, FITS EXPTIME, TIFF ExposureTime), which a stated reconstruct.images.exposure_s
    must match; else the config's.  A rate must not rest on a config default the frames
    contradict, nor poses taken at different exposures be fitted as one scene."""
    from ..imaging.imagefiles import recorded_exposure_s
    from .outputs import reconstruction_exposure_s

    im = plan_im.source
    stated = reconstruction_exposure_s(im, None)  # None: the config does not state it
    got = []
    for k, (p, meta) in enumerate(zip(plan_im.files, metas)):
        r = recorded_exposure_s(meta)
        if r is None:
            continue
        t, key = r
        if stated is not None and abs(t - stated) > 1e-6 * stated:
            raise UserError(f"reconstruct.images.files[{k}] ({p}) was exposed for {t:g} s ({key} in its metadata), but "
                            f"reconstruct.images.exposure_s is {stated:g} s: every rate (photons/s) would be off by "
                            f"{stated / t:.3g}x. Give the exposure the frames were taken at, or leave the key out to "
                            "take the frames'.")
        if got and abs(t - got[0][0]) > 1e-6 * t:
            k0, t0, key0 = got[0][1], got[0][0], got[0][2]
            raise UserError(f"reconstruct.images.files[{k}] ({p}) was exposed for {t:g} s ({key}) but "
                            f"reconstruct.images.files[{k0}] for {t0:g} s ({key0}): the poses are fitted as one scene "
                            "of photons per exposure, so they need one exposure. Scale the images to one exposure "
                            "and give it as reconstruct.images.exposure_s.")
        got.append((t, k, key))
    if stated is not None or not got:
        return float(im.exposure_s), False
    return got[0][0], True



def photon_noise(setting: str, read_noise_photons: float, sensor, kind: str, exposure_s: float,
                 frames_averaged: int = 1) -> N.PhotonNoise:
    """The noise model of the images (``setting``: reconstruct.noise, or ``auto``: what the simulation
    used, EMCCD for count images, Poisson otherwise): every weight, σ and χ² comes from it."""
    kind = (kind if kind in N.NOISE_KINDS else "poisson") if setting == "auto" else setting
    model = emccd_model(sensor, exposure_s) if kind == "emccd" else None
    return N.PhotonNoise(kind, read_noise_photons=read_noise_photons, sensor=model, frames_averaged=frames_averaged)


def check_sweep(sw, im, inp: Inputs) -> None:
    """Before any solving: a sweep (``sw``) needs the simulation's truth and levels that exist."""
    if inp.truth is None:
        raise UserError("reconstruct.sweep: a sweep needs a simulation (ground truth), not image files "
                        "(reconstruct.images).")
    path = simulation_path(im)
    with A.open_artefact(path, "simulation") as f:
        L, R = f["images/noisy"].shape[:2]
    if sw.repeats is not None and sw.repeats > R:
        raise UserError(f"reconstruct.sweep.repeats: {path} holds {R} noise repeat(s); asked for {sw.repeats} "
                        "(simulate more with simulate.noise.repeats).")
    bad = [li for li in (sw.levels or ()) if li >= L]
    if bad:
        raise UserError(f"reconstruct.sweep.levels: {path} holds {L} signal level(s) (0 to {L - 1}); asked for {bad}.")


def _without_emission(x):
    """A provenance (or a geometry dict) without ``subject.emission``."""
    import copy

    geo = copy.deepcopy(x.geometry if isinstance(x, A.Provenance) else x)
    if isinstance(geo.get("subject"), dict):
        geo["subject"].pop("emission", None)
    return replace(x, geometry=geo) if isinstance(x, A.Provenance) else geo


def simulated_emission(im, now) -> str | None:
    """How the images were simulated, when they come from simulation.h5 under another emission
    model than ``now`` (subject.emission as the geometry records it), or as Monte Carlo photons
    of another medium than ``now`` describes: a warning (None when the same, or not simulated)."""
    if im.source is not None:
        return None
    path = simulation_path(im)
    try:
        with A.open_artefact(path, "simulation") as f:
            prov = A.read_provenance(f)
            then = (prov.geometry.get("subject") or {}).get("emission")
            if f["truth"].attrs.get("kind") == "montecarlo":  # photons: no model to mismatch, but a medium
                return photons_medium_note(((prov.config or {}).get("simulate") or {}).get("flux"), now)
    except UserError:
        return None
    if then == now:
        return None
    what = lambda e: "lambertian" if e is None else e.get("model", "?") + (  # noqa: E731
        f" (refractive index {e['refractive_index']:g})" if "refractive_index" in e else "")
    return (f"the images were simulated with the emission model {what(then)} and are reconstructed with "
            f"{what(now)} (subject.emission): a model-mismatch experiment, unless the simulation's light does not "
            "depend on it (Monte Carlo photons).")
