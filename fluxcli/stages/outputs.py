"""Results people can open elsewhere: the flux on the 3-D surface as ``.vtp`` files.

``<workdir>/reconstruction.vtp`` is made from ``reconstruction.h5`` and
``<workdir>/simulation_truth.vtp`` from ``simulation.h5`` (the artefacts only, so that
what ParaView shows is what the HDF5 file holds). The stages call :func:`export_simulation` or
:func:`export_reconstruction` once, at their end.

With an exposure time (``reconstruct.images.exposure_s`` or ``simulate.noise.exposure_s``
given in the config) the files also hold rates and the Lambertian radiance in
photons s⁻¹ cm⁻² sr⁻¹ (see :mod:`fluxcli.surface.units`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..errors import UserError
from ..surface import export as X
from ..surface.units import UNITS, element_quantities


def _given(model, key: str) -> bool:
    return model is not None and key in model.model_fields_set


def simulation_exposure_s(sim) -> float | None:
    """The simulated exposure when the config states it (the schema's default is not a measurement);
    ``sim``: the config's ``simulate`` section, or None."""
    return float(sim.noise.exposure_s) if sim is not None and _given(sim.noise, "exposure_s") else None


def reconstruction_exposure_s(images, sim) -> float | None:
    """The exposure of the images reconstructed: the image files', else the simulation's
    (``images``: reconstruct.images or None; ``sim``: the ``simulate`` section or None)."""
    if images is not None:  # image files, or a capture (whose exposure_s picks one of its exposures)
        first = (getattr(images, "filters", None) or (getattr(images, "filter", None),))[0]
        own = getattr(images, "exposures_s", None) or {}
        if first in own:  # the first filter's own exposure: what /flux is made of
            return float(own[first])
        t = getattr(images, "exposure_s", None)
        return float(t) if t is not None and _given(images, "exposure_s") else None
    return simulation_exposure_s(sim)


def recorded_rate_exposure_s(stated: float | None, rec_path: Path, config_path: Path) -> float | None:
    """The exposure that turns a reconstruction's photons into photons/s, as ``reconstruct``
    recorded it (a capture's frames, else the config's stated exposure), not as the config says
    now: a rate must not change when the config is edited after the fact.

    A config that now states another exposure than the one recorded is refused (UserError
    naming both); an artefact from before the exposure was recorded falls back to the config.
    ``stated``: the exposure the config states now (s, None: none).
    """
    from ..artefacts.reconstruction import recorded_exposure

    if not rec_path.is_file():
        return stated
    got = recorded_exposure(rec_path)
    if got is None:
        return stated
    recorded, source = got
    recorded_t = None if not np.isfinite(recorded) else recorded
    if stated is not None and (recorded_t is None or abs(stated - recorded_t) > 1e-9 * max(stated, recorded_t)):
        was = f"{recorded_t:g} s ({source})" if recorded_t is not None else "no exposure time (per exposure, no rates)"
        raise UserError(f"the config states an exposure of {stated:g} s (reconstruct.images.exposure_s or "
                        f"simulate.noise.exposure_s) but {rec_path} was reconstructed with {was}: a rate cannot be "
                        f"changed after the fact. Remove the override, or run 'fluxmap reconstruct {config_path} --force' "
                        f"with the exposure the images were taken at.")
    return recorded_t


def _quantities(prefix: str, power, areas, exposure_s, sigma=None) -> tuple[dict, dict]:
    q = element_quantities(power, areas, exposure_s=exposure_s, sigma_photons=sigma)
    return {prefix + k: v for k, v in q.items()}, {prefix + k: UNITS[k] for k in q}


def reconstruction_vtp(rec_path: Path, out_path: Path, *, exposure_s: float | None) -> Path:
    """Write the reconstruction (joint over poses when there are several) and, where the
    artefact holds them, the ground truth and each pose's own reconstruction."""
    from ..artefacts.reconstruction import read_maps

    r = read_maps(rec_path)
    surface, power, observed, sigma, truth = r.surface, r.power, r.observed, r.sigma, r.truth
    pose_power, pose_obs, method, joint = r.pose_power, r.pose_observed, r.method, r.joint_over_poses
    rois, per_filter, headline = r.rois, r.per_filter, r.headline
    areas = surface.element_areas_mm2
    arrays, units = _quantities("", power, areas, exposure_s, sigma)
    if truth is not None:
        a, u = _quantities("truth_", truth, areas, exposure_s)
        arrays |= a
        units |= u
    if pose_power is not None and pose_obs is not None and len(pose_power) > 1:
        for k, (pw, ob) in enumerate(zip(pose_power, pose_obs)):
            arrays[f"pose{k + 1}_power_photons"] = np.where(ob, pw, np.nan)
            units[f"pose{k + 1}_power_photons"] = f"photons per exposure, pose {k + 1} alone"
            arrays[f"pose{k + 1}_observed_state"] = ob.astype(np.int8)
            units[f"pose{k + 1}_observed_state"] = "1 observed, 0 unobserved in this pose, -1 not an element"
    for name, pw in per_filter.items():
        arrays[f"filter_{name}_power_photons"] = pw
        units[f"filter_{name}_power_photons"] = f"photons per exposure, per element, before filter {name}"
    for i, name in enumerate(rois["names"] if rois is not None else ()):
        arrays[f"roi_{name}"] = rois["members"][i, -1].astype(np.int8)
        units[f"roi_{name}"] = f"1 in region of interest '{name}', 0 outside ({rois['maps'][-1]} map)"
    field = {"method": method, "joint_over_poses": int(joint), "source": rec_path.name,
             "exposure_s": exposure_s if exposure_s is not None else np.nan}
    if headline is not None:  # the total to read first, and why when it is not over all observed elements
        field |= {"headline_total_photons": headline[0], "headline_over": headline[1],
                  "headline_reason": headline[2] or "-"}
    mesh = X.polydata(surface.vertices_mm, surface.faces, surface.element_of_face, arrays, observed=observed,
                      units=units, field=field)
    return X.write_vtp(out_path, mesh)


def simulation_vtp(sim_path: Path, out_path: Path, *, exposure_s: float | None) -> Path:
    """Write the simulated ground truth (every element observed by construction), per level."""
    with A.open_artefact(sim_path, "simulation") as f:
        surface = A.read_surface(f["surface"])
        power = f["truth/power"][()]
        scale = f["truth/level_scale"][()] if "level_scale" in f["truth"] else np.ones(1)
        kind = str(f["truth"].attrs.get("kind", ""))
    areas = surface.element_areas_mm2
    arrays, units = _quantities("", power * scale[0], areas, exposure_s)
    for li in range(1, len(scale)):
        arrays[f"level{li}_power_photons"] = power * scale[li]
        units[f"level{li}_power_photons"] = f"photons per exposure, signal level {li}"
    field = {"truth_kind": kind, "source": sim_path.name, "level": 0,
             "exposure_s": exposure_s if exposure_s is not None else np.nan}
    mesh = X.polydata(surface.vertices_mm, surface.faces, surface.element_of_face, arrays,
                      observed=np.ones(surface.n_elements, bool), units=units, field=field)
    return X.write_vtp(out_path, mesh)


def export_simulation(ctx, artefact: Path, exposure_s: float | None) -> Path:
    """``simulation_truth.vtp`` beside ``artefact`` (``exposure_s``: the simulated exposure the config states)."""
    out = simulation_vtp(artefact, artefact.parent / "simulation_truth.vtp", exposure_s=exposure_s)
    ctx.say(f"3-D surface for ParaView/pyvista: {out}")
    return out


def export_reconstruction(ctx, artefact: Path, stated_exposure_s: float | None, config_path: Path) -> Path:
    """``reconstruction.vtp`` beside ``artefact``, in rates at the exposure it recorded."""
    out = reconstruction_vtp(artefact, artefact.with_suffix(".vtp"),
                             exposure_s=recorded_rate_exposure_s(stated_exposure_s, artefact, config_path))
    ctx.say(f"3-D surface for ParaView/pyvista: {out}")
    return out


# ------------------------------------------------------------------ what the report records
def rig_of(system: C.System):
    """The camera and mirrors (``system``: the config's rig) as the report's 3-D view draws them."""
    from ..report.view3d import Rig
    from ..scene import camera_from_config, mirror_names, plane_mirrors

    cam = camera_from_config(system.camera)
    mirrors = []
    for name, m in zip(mirror_names(system), plane_mirrors(system)):
        u, v = m.axis_u * m.half_size_mm[0], m.axis_v * m.half_size_mm[1]
        mirrors.append((name, np.array([m.center_mm - u - v, m.center_mm + u - v, m.center_mm + u + v,
                                        m.center_mm - u + v])))
    return Rig(cam.center_mm, cam.axis, -cam.down, cam.aperture_radius_mm, cam.focus_distance_mm,
               (cam.nx * cam.focal_pixel_mm, cam.ny * cam.focal_pixel_mm), mirrors)


def record_of(cfg: C.LoadedConfig, digests: dict[str, str], exposure_s: float | None) -> list[tuple[str, str]]:
    """(label, value) rows: the settings and files a result was made with, for the report's record
    (the whole config: it is the record of the config; ``exposure_s``: the rate's, as recorded)."""
    m = cfg.model
    cam = m.system.camera
    lens = cam.lens
    # paths relative to the workdir (as the artefacts store them): the same run in two clones
    # gives the same page, byte for byte
    rows = [("config", f"{A.portable_path(cfg.path, cfg.workdir)} (sha256 {cfg.sha256[:16]}…)"),
            ("camera", f"{cam.pixels[0]} × {cam.pixels[1]} pixels of {cam.pixel_pitch_mm:g} mm (binned); "
                       f"lens centre {list(cam.pose.lens_center_mm)} mm looking {list(cam.pose.look)}, "
                       f"up {list(cam.pose.up)}"),
            ("lens", f"f = {lens.focal_length_mm:g} mm, aperture radius {lens.aperture_radius_mm:.3g} mm"
                     + (f" (f/{lens.f_number:g})" if lens.f_number else "")
                     + f", focused {lens.focus_distance_mm:g} mm in front"),
            ("apertures", ", ".join(f"⌀{a.diameter_mm:g} mm at {a.distance_mm:g} mm" for a in cam.apertures) or "none"),
            sensor_row(cam.sensor, m.reconstruct.images,
                       cfg.images_capture_path() if hasattr(m.reconstruct.images, "capture") else None),
            ("mirrors", "; ".join(f"{mm.name or f'mirror{k}'}: centre {list(mm.center_mm)} mm, normal "
                                  f"{list(mm.normal)}, {mm.size_mm[0]:g} × {mm.size_mm[1]:g} mm, reflectance "
                                  f"{mm.reflectance:g}" for k, mm in enumerate(m.system.mirrors)) or "none"),
            ("poses", f"heights {list((m.subject.poses or C.Poses()).heights_mm)} mm × rotations "
                      f"{list((m.subject.poses or C.Poses()).rotations_deg)}°")]
    t = exposure_s
    rows.append(("exposure", f"{t:g} s" if t is not None else "not given (quantities per exposure; no rates)"))
    rc = m.reconstruct
    if rc.images is not None and not hasattr(rc.images, "files"):  # a capture artefact
        rows.append(("images", f"capture {rc.images.capture}, filter {rc.images.filter or '(its only one)'}"))
    elif rc.images is not None:
        for k, p in enumerate(rc.images.files):
            path = cfg.resolve(p)
            shown = A.portable_path(path, cfg.workdir)
            rows.append((f"image, pose {k + 1}", f"{shown} (sha256 {A.file_sha256(path)[:16]}…)" if path.is_file()
                         else f"{shown} (missing now)"))
    elif m.simulate is not None:
        rows.append(("images", f"simulated: truth '{m.simulate.flux.kind}', noise '{m.simulate.noise.model}' "
                               f"(seed {m.simulate.noise.seed}); level {rc.level}, "
                               + ("noiseless" if rc.noiseless else f"repeat {rc.repeat}")))
    for name, digest in digests.items():
        rows.append((f"artefact {name}", f"sha256 {digest}"))
    return rows


def frames_settings(capture: Path, filter_name: str | None) -> dict:
    """The sensor settings the light frames of ``capture`` (capture.h5) were read out at, as the
    camera reported them per frame: {em_gain, exposure_s, temperature_c: sorted distinct values}
    over the frames of ``filter_name`` (all light frames when None); {} when unreadable."""
    try:
        with A.open_artefact(capture, "capture") as f:
            fr = f["frames"]
            light = ~f["plan/dark"][()].astype(bool)
            if filter_name is not None and "plan/filter" in f:
                light &= np.char.decode(f["plan/filter"][()]) == filter_name
            done = fr["committed"][()].astype(bool) & light
            return {k: sorted({round(float(x), 6) for x in fr[k][()][done]}) for k in ("em_gain", "exposure_s", "temperature_c")
                    if k in fr}
    except (OSError, KeyError, UserError):
        return {}


def sensor_row(sensor_settings: C.Sensor, images, capture: Path | None) -> tuple[str, str]:
    """The record's sensor row: the settings as used.  For a capture (``images``: reconstruct.images,
    ``capture``: its capture.h5), the EM gain, exposure and temperature the frames were read out at
    (per frame); the config's sensor model for the rest (QE, conversion gain, noise), which is what
    converts counts to photons."""
    sensor = sensor_settings.model_dump()
    if images is not None and hasattr(images, "capture"):
        src = images
        used = frames_settings(capture, src.filters[0] if src.filters else src.filter)
        if used.get("em_gain"):
            sensor.pop("em_gain", None)
            shown = "; ".join(f"{k} {', '.join(f'{v:g}' for v in vals)}" for k, vals in used.items() if vals)
            return ("sensor", f"as the frames were taken (capture.h5): {shown}; model: "
                    + ", ".join(f"{k} {v:g}" for k, v in sensor.items()))
    return ("sensor", ", ".join(f"{k} {v:g}" for k, v in sensor.items()))
