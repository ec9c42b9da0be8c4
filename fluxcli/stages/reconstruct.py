"""``fluxmap reconstruct CONFIG``: from images to the flux leaving each surface element.

Examples
--------
$ fluxmap reconstruct configs/paper-3d.yaml
$ fluxmap reconstruct configs/paper-2d.yaml --jobs 2        # runs the configured sweep too
$ fluxmap reconstruct configs/demo.yaml --set reconstruct.method=paper --set reconstruct.lambda=1

Images come from ``<workdir>/simulation.h5`` (a chosen level and repeat) or from image
files named per pose (``reconstruct.images``).  Each pose is reconstructed on its own and,
with several poses, all of them jointly (their T and images stacked).  Saturated pixels
are masked.  Elements no camera sees are reported as unobserved (NaN), never as zero.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse as sp

from .. import artefacts as A
from .. import config as C
from ..errors import UserError
from ..imaging import noise as N
from ..imaging.imagefiles import read_image, sample_type
from ..artefacts.transfer import load_T, load_T_tangent, load_view
from ..inverse import backprojection, error_l1, reconstruct as solve, total_ratio
from ..inverse.matfree import DENSE_MAX_UNKNOWNS, memory_estimate_bytes as matfree_bytes
from ..pipeline import check_folders, check_memory, emccd_model, ensure_T, geometry_of, plan, provenance
from ..workers import blas_threads, pool_for
from ..imaging.sensor_maps import counts_to_photons_with_maps
from ._radiometric import read_radiometric_maps
from . import budget as B
from .context import RunContext
from .outputs import export_3d


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


def _simulation(cfg: C.LoadedConfig) -> Path:
    path = cfg.workdir / "simulation.h5"
    if not path.is_file():
        raise UserError(f"reconstruct: no images: {path} does not exist (run 'fluxmap simulate' first) and "
                        "reconstruct.images names no files.")
    return path


def _capture_path(cfg: C.LoadedConfig) -> Path:
    p = cfg.model.reconstruct.images.capture
    first = cfg.resolve(p)
    return first if first.is_file() or p.is_absolute() else cfg.workdir / p


def _from_capture(cfg: C.LoadedConfig, n_elements: int, filter_name: str | None = None) -> Inputs:
    """One image per pose (= stage height) from a capture: darks subtracted, counts -> photons
    (``filter_name``: this filter's frames; default the first of reconstruct.images.filters, else .filter)."""
    from ..acquisition import read_capture
    from ..scene import poses_from_config

    path = _capture_path(cfg)
    src = cfg.model.reconstruct.images
    if filter_name is None:
        filter_name = src.filters[0] if src.filters else src.filter
    cap = read_capture(path, filter_name, src.exposures_s.get(filter_name, src.exposure_s) if filter_name else src.exposure_s)
    order = cap.pose_order([p.height_mm for p in poses_from_config(cfg.model.subject)])
    photons, valid = cap.photons(emccd_model(cfg.model.system.camera.sensor, cap.exposure_s))
    nx, ny = cfg.model.system.camera.pixels
    if photons.shape[1:] != (ny, nx):
        raise UserError(f"reconstruct.images.capture: {path} holds {photons.shape[2]} x {photons.shape[1]} pixel "
                        f"frames; system.camera.pixels is {nx} x {ny}.")
    truth = cap.truth_power if cap.truth_power is not None and len(cap.truth_power) == n_elements else None
    return Inputs(photons[order], valid[order] & np.isfinite(photons[order]), truth,
                  f"{path} filter {cap.filter}, {cap.repeats} repeat(s) averaged, {cap.n_darks} dark(s) subtracted",
                  files={"capture.h5": path}, noise_kind="emccd", exposure_s=float(cap.exposure_s),
                  frames_averaged=max(int(cap.repeats), 1))


def _image_sources(cfg: C.LoadedConfig) -> list[str]:
    """sha256 of the image files reconstruct reads (what makes its output stale)."""
    rc = cfg.model.reconstruct
    if isinstance(rc.images, C.CaptureSource):
        p = _capture_path(cfg)
        return [A.file_sha256(p)] if p.is_file() else []
    if rc.images is not None:
        out = [A.file_sha256(cfg.resolve(p)) for p in rc.images.files if cfg.resolve(p).is_file()]
        if rc.images.calibration is not None and cfg.resolve(rc.images.calibration).is_file():
            out.append(A.file_sha256(cfg.resolve(rc.images.calibration)))
        return out
    sim = cfg.workdir / "simulation.h5"
    return [A.file_sha256(sim)] if sim.is_file() else []


def load_inputs(cfg: C.LoadedConfig, n_poses: int, n_elements: int, surface_sha256: str | None = None,
                poses: list | None = None) -> Inputs:
    rc = cfg.model.reconstruct
    nx, ny = cfg.model.system.camera.pixels
    if isinstance(rc.images, C.CaptureSource):
        return _from_capture(cfg, n_elements)
    if rc.images is not None:
        return _image_files(cfg, n_poses, poses)
    path = _simulation(cfg)
    with A.open_artefact(path, "simulation") as f:
        # images simulated under another emission model are a model-mismatch experiment, not other
        # geometry: reconstructed, with a warning (_emission_checks); T itself is always this config's
        stored, now = _without_emission(A.read_provenance(f)), _without_emission(geometry_of(cfg, surface_sha256))
        A.check_geometry(path, stored, now,
                         remedy=f"Run 'fluxmap simulate {cfg.path}' again, or reconstruct with the config it was made with")
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
            model = emccd_model(cfg.model.system.camera.sensor, float(f["images"].attrs["exposure_s"]))
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


def _image_files(cfg: C.LoadedConfig, n_poses: int, poses: list | None) -> Inputs:
    """Images from files named per pose, each checked against what it claims to be."""
    rc = cfg.model.reconstruct
    im = rc.images
    nx, ny = cfg.model.system.camera.pixels
    if len(im.files) != n_poses:
        raise UserError(f"reconstruct.images.files: {len(im.files)} file(s) for {n_poses} pose(s) "
                        "(one file per pose, in subject.poses order: heights x rotations).")
    model = None
    if im.units == "counts":
        if "sensor" not in cfg.model.system.camera.model_fields_set:
            raise UserError("reconstruct.images.units is counts, but system.camera.sensor is not given: converting "
                            "counts to photons needs the camera's bias, gain and quantum efficiency (give "
                            "system.camera.sensor, or images in photons).")
        model = emccd_model(cfg.model.system.camera.sensor, im.exposure_s)
    maps = {} if im.calibration is None else read_radiometric_maps(  # per-pixel bias, dark, flat (radiometry)
        cfg.resolve(im.calibration), "reconstruct.images.calibration", (ny, nx))
    imgs, valid = [], []
    for k, p in enumerate(im.files):
        where = f"reconstruct.images.files[{k}] ({cfg.resolve(p)})"
        try:
            img, meta = read_image(cfg.resolve(p))
        except ValueError as e:
            raise UserError(f"reconstruct.images.files[{k}]: {e}") from None
        if img.shape != (ny, nx):
            raise UserError(f"{where} is {img.shape[1]} x {img.shape[0]} pixels; the camera has {nx} x {ny} "
                            "(system.camera.pixels).")
        said = meta.get("fluxmap:units")
        stored = sample_type(cfg.resolve(p))
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
            img = counts_to_photons_with_maps(np.where(finite, img, 0), model, **maps)
            ok &= np.isfinite(img)  # dead pixels of the flat map
            img = np.where(finite, img, np.nan)
        if not np.any(img[ok] > 0):
            raise UserError(f"{where}: no pixel holds a positive signal (all are zero or negative"
                            + (" after the bias is subtracted" if model is not None else "") + "); a reconstruction "
                            "from it would be zero everywhere.")
        imgs.append(img)
        valid.append(ok)
    files = {f"image pose {k}": cfg.resolve(p) for k, p in enumerate(im.files)}
    return Inputs(np.array(imgs), np.array(valid), None, "files", files=files,
                  noise_kind="emccd" if model is not None else "poisson", exposure_s=im.exposure_s)


STRAY_WARN = 0.05  # share of the image's light on pixels no element reaches: warned above this
STRAY_REFUSE = 0.5  # ... and refused above this: the images do not show this geometry
SPIKE_SIGMA = 20.0  # a pixel this many sigma of the noise model above the model ...
SPIKE_SPREAD = 5.0  # ... and this many times the residuals' own spread (where the fit is off by more than noise) ...
SPIKE_ISOLATION = 8.0  # ... and this many times further above it than any of its 8 neighbours
MAX_SPIKE_SHARE = 0.005  # at most this share of the valid pixels is left out as spikes


def isolated_spikes(image: np.ndarray, model: np.ndarray, valid: np.ndarray, noise: N.PhotonNoise) -> np.ndarray:
    """Pixels far above the model that none of their neighbours follows: cosmic rays, hot
    pixels, a stray reflection off a screw head — light no smooth surface behind a lens
    with a point spread of a pixel or more can send to one pixel alone.

    ``z = (a - model) / sqrt(var(max(a, model)))`` (the variance at the larger of the two,
    so a spike cannot shrink its own sigma). Noise alone gives a Gaussian z, whose largest
    value on 10⁷ pixels is about 5.3: SPIKE_SIGMA = 20 is no false alarm on noise. Where the
    model is off by more than noise (a camera a calibration error away, a surface finer than
    the elements: |z| of 25 and more along edges at high signal, as the accuracy battery met,
    or up to 67 on test_plausible_but_wrong's images at 2e4 photons a pixel) the residuals'
    own spread ``s`` (1.4826 x the median |z| where the model has light: a Gaussian's sigma,
    robust to the spikes themselves; 1.6 on issue 25's scene at a 2e4 peak, 3.7 at 2e5, 36-39
    there) sets the bar too: a spike is a 5-sigma outlier of that spread (SPIKE_SPREAD). So a spike has
    ``z > max(SPIKE_SIGMA, SPIKE_SPREAD s)`` and ``z > SPIKE_ISOLATION x`` the largest ``z`` of
    its valid neighbours (at least 1). Images are [ny, nx] (a 1-D array is one row).
    Returns a mask of the image's shape."""
    from scipy.ndimage import maximum_filter

    a = np.asarray(image, dtype=np.float64)
    shape = a.shape
    a2 = a.reshape(1, -1) if a.ndim == 1 else a
    m2 = np.broadcast_to(np.asarray(model, dtype=np.float64).reshape(a2.shape) if np.ndim(model) else model, a2.shape)
    ok = np.asarray(valid, bool).reshape(a2.shape) & np.isfinite(a2) & np.isfinite(m2)
    with np.errstate(invalid="ignore"):
        z = np.where(ok, (a2 - m2) / np.sqrt(noise.variance(np.where(ok, np.maximum(a2, m2), 0.0))), 0.0)
    scale = residual_spread(z, ok & (m2 > 0))
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    neighbours = maximum_filter(z, footprint=ring, mode="constant", cval=0.0)
    return ((z > max(SPIKE_SIGMA, SPIKE_SPREAD * scale))
            & (z > SPIKE_ISOLATION * np.maximum(neighbours, 1.0))).reshape(shape)


def residual_spread(z: np.ndarray, where: np.ndarray) -> float:
    """The spread of the residuals ``z`` (in noise sigma) over ``where``, robust to the spikes
    among them: 1.4826 x the median |z| (a Gaussian's sigma), at least 1 (the noise model's)."""
    return max(1.0, 1.4826 * float(np.median(np.abs(z[where])))) if np.any(where) else 1.0


def describe_pixels(mask: np.ndarray, excess: np.ndarray, limit: int = 3) -> str:
    """'(row r, column c) +X photons' for the brightest few pixels of ``mask``."""
    m2 = mask.reshape(1, -1) if mask.ndim == 1 else mask
    e2 = excess.reshape(m2.shape)
    rows, cols = np.nonzero(m2)
    order = np.argsort(-e2[rows, cols])[:limit]
    text = ", ".join(f"(row {rows[i]}, column {cols[i]}) +{e2[rows[i], cols[i]]:.3g}" for i in order)
    return text + (f" and {rows.size - limit} more" if rows.size > limit else "") + " photons"


def light_outside(T, image: np.ndarray, valid: np.ndarray, noise: N.PhotonNoise, label: str, surface) -> str | None:
    """The image's light that no element of the subject can have sent: on pixels where every
    column of T (all views) is zero.  The solve only looks at the pixels T reaches, so light
    elsewhere would otherwise be ignored without a word — a mesh in metres instead of mm, a
    pose or a camera that does not match the images would give a plausible total.

    Counted when it stands out of the noise (more than 5 σ of the noise model summed over
    those pixels); a warning above :data:`STRAY_WARN` of the light, a :class:`UserError`
    above :data:`STRAY_REFUSE`.  Isolated spikes there (:func:`isolated_spikes` against a
    model of 0: cosmic rays, hot pixels) say nothing of the geometry and are not counted
    (:func:`reject_spikes` names them after the solve).  Returns the warning or None."""
    reach = np.asarray(abs(T).sum(axis=1)).ravel() > 0
    a = np.asarray(image, dtype=np.float64).ravel()
    ok = np.asarray(valid).ravel() & np.isfinite(a)
    out_px = ok & ~reach
    spikes = isolated_spikes(np.asarray(image), 0.0, np.asarray(valid).reshape(np.shape(image)), noise).ravel() & out_px
    if spikes.sum() <= MAX_SPIKE_SHARE * ok.sum():
        out_px &= ~spikes
        ok &= ~spikes
    outside = float(a[out_px].sum())
    total = float(a[ok].sum())
    if total <= 0 or outside <= 0:
        return None
    noise_sd = float(np.sqrt(noise.variance(a[out_px]).sum()))
    share = outside / total
    if outside <= 5 * noise_sd or share <= STRAY_WARN:
        return None
    lo, hi = surface.bounds_mm()
    what = (f"{share:.0%} of the image's light ({outside:.3g} of {total:.3g} photons, {noise_sd:.2g} of it noise) "
            f"falls on pixels that no element of the subject can reach")
    if share > STRAY_REFUSE:
        raise UserError(
            f"reconstruct, pose {label}: {what}: the images do not show this geometry. Check the mesh's units "
            f"(fluxmap reads millimetres; subject.surface spans {np.ptp(np.stack([lo, hi]), axis=0).round(3).tolist()} mm; "
            "a mesh in metres needs subject.surface.scale_to_mm: 1000), "
            "subject.poses (their order is the images' order), system.camera (pose, pixels, binning) and whether "
            "the images still hold a bias or background; set pixels that show something else to NaN to leave "
            "them out.")
    return (f"{what}: it is left out of the fit (light from outside the subject's mesh, a misplaced pose or "
            "camera, an unsubtracted bias or background, or stray light); set such pixels to NaN to silence this")


def reject_spikes(image: np.ndarray, fitted: np.ndarray, valid: np.ndarray,
                  noise: N.PhotonNoise) -> tuple[np.ndarray, str | None]:
    """After a solve: the valid mask without the isolated spikes above the fit, and the
    warning that names them.  More than :data:`MAX_SPIKE_SHARE` of the pixels is not a few
    cosmic rays: nothing is left out, and the warning says so."""
    spikes = isolated_spikes(image, fitted, valid, noise)
    n = int(spikes.sum())
    if n == 0:
        return valid, None
    excess = np.where(spikes, np.asarray(image, float) - np.nan_to_num(fitted), 0.0)
    where = describe_pixels(spikes, excess)
    if n > MAX_SPIKE_SHARE * np.count_nonzero(valid):
        return valid, (f"{n} pixels stand alone more than {SPIKE_SIGMA:g} sigma above the fit "
                       f"({where}); too many to be cosmic rays or hot pixels, so all were kept: check the images")
    return valid & ~spikes, (f"left out {n} isolated pixel(s) more than {SPIKE_SIGMA:g} sigma above "
                             f"the fit that no neighbour follows ({where}): cosmic rays or hot pixels? They "
                             "held light no surface behind the lens can send to one pixel; set them to NaN to "
                             "silence this")


def direct_roi(T_path: Path, image: np.ndarray) -> float:
    """The older quantification: photons summed over the region the direct view covers."""
    direct = load_view(T_path, 0)
    rows = np.diff(direct.indptr) > 0
    return float(np.nansum(image.ravel()[rows]))


def photon_noise(cfg: C.LoadedConfig, kind: str, exposure_s: float, frames_averaged: int = 1) -> N.PhotonNoise:
    """The noise model of the images (``reconstruct.noise``, or ``auto``: what the simulation
    used, EMCCD for count images, Poisson otherwise): every weight, σ and χ² comes from it."""
    rc = cfg.model.reconstruct
    kind = (kind if kind in N.NOISE_KINDS else "poisson") if rc.noise == "auto" else rc.noise
    sensor = emccd_model(cfg.model.system.camera.sensor, exposure_s) if kind == "emccd" else None
    return N.PhotonNoise(kind, read_noise_photons=rc.read_noise_photons, sensor=sensor, frames_averaged=frames_averaged)


REGULARISED = ("paper", "tikhonov", "nnls", "weighted_lsq")  # lambda rules of fluxcli.inverse


@dataclass
class Grid:
    """The unknowns of a solve: the elements, or sub-elements summed back per element, or
    vertices (exitance linear within a face) shared out to the elements."""

    Ts: list  # per pose, (n_pixels, n_unknowns)
    adjacency: sp.csr_matrix  # unknowns touching, as edge weights of the smooth prior (vertices: cotangent)
    parent: np.ndarray | None  # unknown -> element; None when the unknowns are the elements
    n_elements: int
    areas: np.ndarray | None = None  # (n_unknowns,) mm²: priors act on exitance
    surface: object = None  # the elements' surface
    paths: list | None = None  # per pose, the T cache file Ts[k] was read from (vertices: the fine T)
    vmap: "VertexMap | None" = None  # vertices: how the fine T gives T per vertex and per element
    maps: list | None = None  # vertices: per pose the ElementMap (parent is then None)

    def parts(self, k: int | None = None):
        """What run_method takes as ``parent`` for pose k (None: all poses jointly)."""
        if self.maps is None:
            return self.parent
        if k is not None:
            return self.maps[k]
        m = self.maps[0]
        return replace(m, T=sp.vstack([x.T for x in self.maps]).tocsr(),
                       T_fine=None if m.T_fine is None else sp.vstack([x.T_fine for x in self.maps]).tocsr())


@dataclass
class ElementMap:
    """Unknowns that are not parts of one element (vertices): the element power per unit of
    each unknown, and the element-level T, adjacency and areas that classify the elements
    (observed, poorly observed) exactly as a solve per element would."""

    to_elements: sp.csr_array  # (n_elements, n_unknowns)
    T: sp.csr_array  # (n_pixels, n_elements)
    adjacency: sp.csr_matrix
    areas: np.ndarray
    hats: object = None  # linear_elements: the T given is per vertex; run_method makes the element unknowns
    T_fine: object = None  # linear_elements: (n_pixels, n_fine) T per face of the refined surface (what each face is seen)


@dataclass
class VertexMap:
    """Pose-independent maps of the vertex unknowns (no T inside: a sweep task takes this
    and the fine T's cache path): T per vertex = T_fine · to_fine, per element = T_fine ·
    fine_to_elements."""

    to_fine: sp.csr_array  # (n_fine, n_vertices)
    fine_to_elements: sp.csr_array  # (n_fine, n_elements)
    to_elements: sp.csr_array  # (n_elements, n_vertices)
    adjacency: sp.csr_matrix  # elements touching
    areas: np.ndarray  # element areas, mm²
    hats: object = None  # linear_elements: surface.ElementHats (one unknown per element, from the vertices' T)
    # the emission's tangential-flux term (optics.emission.tangent_operator), (2 n_fine, n_vertices); None: none
    tangent: "sp.csr_array | None" = None

    def unknowns_T(self, T_fine, T_tangent=None) -> sp.csr_array:
        """T per vertex (columns of the hat functions; linear_elements: run_method combines them);
        with the fine T's tangential matrix (pixels x 2 n_fine) also the light the exitance
        gradient of each hat function tilts into each pixel.  A hat alone is not an exitance the
        term holds for everywhere: at its rim phi_v -> 0 while its gradient does not, and a pixel
        that sees only that rim at a grazing angle can get a slightly negative entry (on the Monte
        Carlo box at 60 deg: 5e-4 of T's mass).  The solvers need T >= 0: such entries are set to 0."""
        if T_tangent is None or self.tangent is None:
            return sp.csr_array(T_fine @ self.to_fine)
        T = sp.csr_array(T_fine @ self.to_fine + T_tangent @ self.tangent)
        np.maximum(T.data, 0.0, out=T.data)
        T.eliminate_zeros()
        return T

    def element_map(self, T_fine) -> ElementMap:
        return ElementMap(self.to_elements, sp.csr_array(T_fine @ self.fine_to_elements), self.adjacency, self.areas,
                          self.hats, None if self.hats is None else sp.csr_array(T_fine))


def make_grid(cfg: C.LoadedConfig, ctx: RunContext, surface, unknowns: str) -> Grid:
    if unknowns in ("vertices", "linear_elements"):  # T per face of the once-refined surface, per hat function
        _, _, todo, _ = ensure_T(cfg, replace(ctx, force=False), label=f"building T ({unknowns.replace('_', ' ')})",
                                 unknowns="refined:1")
        vb = surface.vertex_basis()
        _, fine_parent = surface.refined(1)
        fine_to_el = sp.csr_array((np.ones(fine_parent.size), (np.arange(fine_parent.size), fine_parent)),
                                  shape=(fine_parent.size, surface.n_elements))
        stiffness, areas, hats = vb.stiffness, vb.areas_mm2, None
        if unknowns == "linear_elements":  # one unknown per element, still linear within faces
            hats = vb.per_element(fine_to_el)
            stiffness, areas = None, None  # per solve: the unknowns depend on the elements the pixels see
        vmap = VertexMap(vb.to_fine, fine_to_el, vb.to_elements, surface.element_adjacency(), surface.element_areas_mm2,
                         hats)
        Tf = [load_T(pt.path).tocsr() for _, pt in todo]
        Tt = [load_T_tangent(pt.path) for _, pt in todo]
        if any(t is not None for t in Tt):  # the emission's tangential flux: acts through the hats' gradients
            from ..optics.emission import tangent_operator

            vmap = replace(vmap, tangent=tangent_operator(surface, 1))
        return Grid([vmap.unknowns_T(T, t) for T, t in zip(Tf, Tt)], stiffness, None, surface.n_elements, areas, surface,
                    [str(pt.path) for _, pt in todo], vmap, [vmap.element_map(T) for T in Tf])
    label = "building T" if unknowns == "elements" else "building T (sub-elements)"
    _, _, todo, _ = ensure_T(cfg, replace(ctx, force=False), label=label, unknowns=unknowns)
    grid_surface, parent = surface.unknowns() if unknowns == "sub_elements" else (surface, None)
    return Grid([load_T(pt.path) for _, pt in todo], grid_surface.element_adjacency(), parent, surface.n_elements,
                grid_surface.element_areas_mm2, surface, [str(pt.path) for _, pt in todo])


def run_method(T: sp.csr_matrix, a: np.ndarray, valid: np.ndarray, m: C.MethodSettings, noise: N.PhotonNoise,
               adjacency=None, parent=None, n_elements: int | None = None, areas=None):
    """Solve on the valid pixels; returns the inverse.Result and the pixel mask used.

    ``noise`` is the images' noise model; ``adjacency`` (unknowns touching) and ``areas``
    (mm²) are what the exitance prior of ``smooth`` needs; with ``parent`` the unknowns are
    sub-elements, summed back into ``n_elements`` elements (an element counts as observed
    when any of its parts is, its class is its best part's; sigma is not propagated: NaN);
    with an :class:`ElementMap` they are vertices shared out to the elements, which are
    classified on their own T."""
    if isinstance(parent, ElementMap) and parent.hats is not None:
        T, parent, adjacency, areas = element_unknowns(T, valid, parent)
    with blas_threads(1):  # dense ~10^3 solves: BLAS threads cost more than they give (workers.blas_threads)
        groups = parent.to_elements if isinstance(parent, ElementMap) else (
            None if parent is None else (parent, n_elements))
        res, keep = _solve(T, a, valid, m, noise, adjacency, areas, groups=groups)
    if parent is None:
        return res, keep
    from ..inverse.covariance import Mapped, parent_map

    if res.covariance is not None:  # variance_of(weights over the elements) (ROI totals)
        res = replace(res, covariance=Mapped(res.covariance, parent.to_elements if isinstance(parent, ElementMap)
                                             else parent_map(parent, n_elements)))
    if isinstance(parent, ElementMap):
        return _on_elements(res, keep, parent), keep
    obs = res.observed
    power = np.bincount(parent, weights=np.where(obs, res.power, 0.0), minlength=n_elements)
    observed = np.bincount(parent, weights=obs.astype(float), minlength=n_elements) > 0
    cls = np.zeros(n_elements, np.int8)
    np.maximum.at(cls, parent, res.observation)
    sigma = res.sigma_groups if res.sigma_groups is not None else np.full(n_elements, np.nan)
    return replace(res, power=np.where(observed, power, np.nan), observed=observed,
                   sigma=np.where(observed, sigma, np.nan), observation=cls), keep


def element_unknowns(T_vertices, valid, emap: ElementMap):
    """``unknowns: linear_elements``: T per vertex -> T per unknown (the elements these pixels
    see, and the vertices on the rim of that set: :class:`~fluxcli.surface.mesh.ElementHats`);
    returns that T, the ElementMap sharing the unknowns out to the elements, the prior's
    edge weights and the unknowns' areas (mm²)."""
    from ..inverse._common import DEFAULT_REL_THRESHOLD, observed

    hats = emap.hats
    keep = np.asarray(valid).ravel()
    included = observed(sp.csr_array(emap.T[keep]), DEFAULT_REL_THRESHOLD)  # the elements' own T
    if emap.T_fine is None:
        b = hats.basis(included)
    else:  # less the elements the camera sees only the edges of (ElementHats.seen_basis)
        b = hats.seen_basis(included, np.asarray(sp.csr_array(emap.T_fine[keep]).sum(axis=0)).ravel())
    return (sp.csr_array(T_vertices @ b.prolong), replace(emap, to_elements=b.to_elements, hats=None, T_fine=None),
            b.stiffness, b.areas_mm2)


def _on_elements(res, keep, emap: ElementMap):
    """A solve on vertex unknowns as element powers; the elements are classified on their
    own T (sensitivity, neighbours, σ of the element sums), as a solve per element would."""
    from ..inverse.methods import POOR_SHARE_TEXT, observation_classes, poor_share_warning
    from ..inverse._common import DEFAULT_REL_THRESHOLD

    T_el = emap.T[keep]
    power = emap.to_elements @ np.where(res.observed, res.power, 0.0)
    sigma = res.sigma_groups if res.sigma_groups is not None else np.full(power.size, np.nan)
    cls = observation_classes(T_el, power, sigma, adjacency=emap.adjacency, areas=emap.areas,
                              rel_threshold=DEFAULT_REL_THRESHOLD)
    observed = cls > 0
    warnings = [w for w in res.warnings if POOR_SHARE_TEXT not in w]
    poor = poor_share_warning(power, observed, cls)
    if poor:
        warnings.append(poor)
    return replace(res, power=np.where(observed, power, np.nan), observed=observed,
                   sigma=np.where(observed, sigma, np.nan), observation=cls, warnings=tuple(warnings))


def _solve(T, a, valid, m, noise, adjacency, areas, groups=None):
    keep = valid.ravel()
    Tm, am = T[keep], a.ravel()[keep]
    if m.method == "mlem":  # Poisson likelihood: bias-subtracted counts can dip below zero
        am = np.maximum(am, 0.0)
    kw: dict = {}
    if m.method in REGULARISED:
        if m.lam == "auto":
            kw["lam_rule"] = m.lambda_rule
        else:
            kw["lam"] = float(m.lam)
    if m.method == "paper":
        kw.update(max_iter=m.max_iter, tol=m.tol)
    if m.method == "mlem":
        kw.update(n_iter=m.n_iter)
    if m.method == "smooth":
        if m.lam != "auto":
            kw["lam"] = float(m.lam)
        else:
            kw["lam_rule"] = m.lambda_rule
        kw.update(n_iter=m.max_iter)
    try:
        return solve(Tm, am, method=m.method, variance=noise.variance, adjacency=adjacency, areas=areas,
                     groups=groups, **kw), keep
    except ValueError as e:  # say it in config keys, not the solver's parameter names
        msg = str(e)
        for internal, key in (("lam_rule", "reconstruct.lambda_rule"), ("lam", "reconstruct.lambda"),
                              ("n_iter", "reconstruct.n_iter"), ("transfer matrix T", "T")):
            msg = re.sub(rf"\b{internal}\b", key, msg)
        raise UserError(f"reconstruct.method {m.method}: {msg}") from None


def _solve_poses(gm, inp, m, noise, stray, todo, shape, joint_too: bool, rois, scale: float = 1.0):
    """Each pose on its own (isolated spikes left out and solved again), then all jointly;
    every region of interest measured on each result while its covariance is alive.
    ``scale`` divides the results (a filter's transmission: the light before the filter).
    Returns [(Result, fitted image)] per pose and the joint Result (or None)."""
    ny, nx = shape
    P = len(todo)
    per_pose = []
    for k in range(P):
        def solve_pose():
            res, keep = run_method(gm.Ts[k], inp.images[k], inp.valid[k], m, noise, gm.adjacency,
                                   gm.parts(k), gm.n_elements, gm.areas)
            fitted = np.full(nx * ny, np.nan)
            fitted[keep] = res.fitted
            return res, fitted.reshape(ny, nx)
        res, fitted = solve_pose()
        # inp.valid[k] is a new view at every indexing: compare with the one reject_spikes was given
        # (`valid_k is not inp.valid[k]` was always true: every pose was solved twice)
        valid_before = inp.valid[k]
        valid_k, spiked = reject_spikes(inp.images[k], fitted, valid_before, noise)
        if valid_k is not valid_before:  # solved again without them; the joint solve leaves them out too
            inp.valid[k] = valid_k
            res, fitted = solve_pose()
        res = _scaled(replace(res, warnings=tuple(w for w in (stray[k], spiked) if w) + tuple(res.warnings)), scale)
        if rois:
            rois.measure(str(k + 1), todo[k][1].pose.height_mm, todo[k][1].pose.rotation_deg, res)
        per_pose.append((replace(res, covariance=None), fitted))  # the covariance is n x n: measured, dropped
    joint = None
    if joint_too and P > 1:
        Tj = sp.vstack(gm.Ts).tocsr()
        joint, _ = run_method(Tj, inp.images, inp.valid, m, noise, gm.adjacency, gm.parts(),
                              gm.n_elements, gm.areas)
        joint = _scaled(joint, scale)
        if rois:
            rois.measure("joint", None, None, joint)
        joint = replace(joint, covariance=None)
    return per_pose, joint


def _scaled(res, scale: float):
    """The result divided by ``scale`` (power, σ; the covariance by scale²)."""
    if scale == 1.0:
        return res
    from ..inverse.covariance import Scaled

    return replace(res, power=res.power / scale, sigma=res.sigma / scale,
                   sigma_groups=None if res.sigma_groups is None else res.sigma_groups / scale,
                   covariance=None if res.covariance is None else Scaled(res.covariance, 1.0 / scale))


def _capture_filters(cfg: C.LoadedConfig) -> tuple[str, ...]:
    """The filters a capture source reconstructs, in order (empty: not a capture, or its one filter)."""
    src = cfg.model.reconstruct.images
    if isinstance(src, C.CaptureSource) and src.filters:
        return tuple(src.filters)
    return ()


def _transmission(cfg: C.LoadedConfig, name: str | None) -> float:
    src = cfg.model.reconstruct.images
    if name is None or not isinstance(src, C.CaptureSource):
        return 1.0
    return float(src.transmissions.get(name, 1.0))


MAX_AUTO_SUB_ELEMENTS = 6000  # dense solves: 6000² doubles is 0.29 GB a matrix (a 5880-vertex pose took 14 s)


def resolve_unknowns(m: C.MethodSettings, surface, camera: C.Camera | None = None) -> C.MethodSettings:
    """``unknowns: auto``: ``smooth`` solves for the exitance at the vertices (linear within
    each face, continuous across edges; :meth:`Surface.vertex_basis`) and shares it out to
    the elements when there are at most EXACT_MAX_UNKNOWNS vertices, beyond on one unknown per
    element with the exitance still linear within faces (``linear_elements``, up to
    MAX_AUTO_SUB_ELEMENTS elements); the other methods, and larger meshes, solve per element. (``camera`` is kept in the signature for its
    callers: how finely the camera resolves an element no longer decides, see below.)

    Light varies within an element, and where it varies steeply a model constant per element
    (or per face) cannot fit the data even without noise: honest simulations of a cylinder
    at 21 pixels per element, noiseless, λ → 0, give χ²/pixel (at SNR 30) 3.7 per element and
    2.8 per face with the source at the limb (2.2 % / 2.8 % error), and 1.7 / 1.2 with the
    source behind (8 % / 13 % error, totals over well-observed elements 0.96 / 0.93), against
    0.06 / 0.04 (0.3 % / 0.6 %, 1.000 / 1.002) for exitance linear in each face, with fewer
    unknowns (312 vertices, 576 faces). At 5–6 pixels per element (paper-3d, heights, the
    demo) it helps as much: 3.13 → 1.40 %, 3.19 → 2.46 %, 5.0 → 2.1 % error.

    Until November 2026 ``auto`` also asked for ≥ 12 pixels per element (≥ 4 where there are
    at most 1.25 vertices per element) and at most 4000 vertices, from one scene at 0.6
    pixels per element whose total went 1.038 → 1.067 on vertices. Measured since, on the
    independent renderer's cylinder (elements of 2 x 2 quads, SNR 30, blob 20° / 45° from
    the top; error over observed elements, per element → vertices): 48 x 24 quads at 4.7
    pixels per element 7.5 → 2.7 % / 10.0 → 4.3 %, at 2 pixels 9.9 → 5.5 % / 16.1 → 9.2 %, at
    0.9 pixels 8.8 → 5.3 % / 11.6 → 6.0 %; 96 x 48 quads (4706 vertices) at 4.7 pixels
    3.2 → 2.0 % / 4.3 → 2.6 %, at 0.2 pixels 6.2 → 5.4 % / 8.8 → 6.5 %; the battery's
    cylinder at 2.2 and 0.55 pixels per element 6.1 → 3.7 % and 7.4 → 5.0 % (top), 9.3 →
    6.3 % and 12.9 → 8.4 % (limb). Vertices won every one; totals moved either way by ≤ 1.5 %.

    Beyond :data:`~fluxcli.inverse.methods.EXACT_MAX_UNKNOWNS` vertices (where the exact
    non-negative steps would cost minutes) ``auto`` solves on ``linear_elements`` instead: one
    unknown per element (and per vertex on the rim of what the camera sees), the exitance
    still linear within faces (:class:`~fluxcli.surface.mesh.ElementHats`), so the reported
    elements, not the mesh, set the cost and the solve stays exact. Issue 25's scene (5666
    vertices, 1168 elements, 2 x 2 quads per element) went from minutes to seconds; at SNR 30
    the element-sized basis tied or won on the battery's grouped-quad cases (renderer-direct
    1.55 → 1.38 %, indep-direct 1.22 → 1.16 %, indep-mirrors 1.11 → 1.03 %). It has a quarter
    of the vertices' freedom, and where the light rises steeply within elements and the data
    are nearly noiseless the vertices win (test_independent_renderer's source behind the
    limb at SNR 300: 0.4 % on vertices, 1.8 % per element), so below the cap vertices stay
    (and the battery's figures with them)."""
    if m.unknowns != "auto":
        return m
    if m.method != "smooth":
        return m.model_copy(update={"unknowns": "elements"})
    from ..inverse.methods import EXACT_MAX_UNKNOWNS

    nv = n_vertices(surface)
    if nv <= EXACT_MAX_UNKNOWNS:
        return m.model_copy(update={"unknowns": "vertices"})
    return m.model_copy(update={"unknowns": "linear_elements" if surface.n_elements <= MAX_AUTO_SUB_ELEMENTS
                                else "elements"})


def n_vertices(surface) -> int:
    """Unknowns of ``reconstruct.unknowns: vertices``: the vertices of the element faces."""
    return int(np.unique(surface.faces[surface.element_of_face >= 0]).size)


DENSE = ("paper", "tikhonov", "nnls", "weighted_lsq", "smooth")  # form T'WT (n x n) densely


def _check_solver_size(cfg: C.LoadedConfig, ctx: RunContext, surface, n_poses: int) -> None:
    """Dense normal matrices are n_unknowns^2: refuse before allocating, naming the keys."""
    rc = cfg.model.reconstruct
    cam = cfg.model.system.camera
    methods = [resolve_unknowns(x, surface, cam) for x in (rc.settings(), *(rc.sweep.methods if rc.sweep else ()))]
    n_sub = {"elements": surface.n_elements}
    if any(s.unknowns == "sub_elements" for s in methods):
        n_sub["sub_elements"] = surface.unknowns()[0].n_elements
    n_sub["vertices"] = n_vertices(surface)
    n_sub["linear_elements"] = surface.n_elements  # and the rim of what each pose sees (a few % more)
    nx, ny = cfg.model.system.camera.pixels
    need = 8.0 * nx * ny * n_poses * 8  # images, masks, fits and residuals
    for s in methods:
        n = n_sub[s.unknowns]
        if s.method == "smooth" and n > DENSE_MAX_UNKNOWNS:  # the matrix-free path (fluxcli.inverse.matfree)
            need = max(need, matfree_bytes(n, n_poses=n_poses, n_pixels=nx * ny * n_poses)
                       * (ctx.jobs if rc.sweep else 1))
        elif s.method in DENSE:
            need = max(need, 8.0 * n ** 2 * 4 * (ctx.jobs if rc.sweep else 1))
    if any(s.method == "smooth" and n_sub[s.unknowns] > DENSE_MAX_UNKNOWNS for s in methods):
        ctx.say(f"reconstruct: more than {DENSE_MAX_UNKNOWNS} unknowns: the matrix-free solve (sparse T'WT and "
                f"Laplacian); about {need / 1e9:.2g} GB of memory at its peak")
    check_memory(need, f"reconstructing {surface.n_elements} elements ({', '.join(sorted({s.method for s in methods}))})",
                 "the elements of subject.surface, use reconstruct.unknowns: elements, or choose "
                 "reconstruct.method: mlem or backprojection (no dense normal matrix)")


def describe(m: C.MethodSettings) -> str:
    base = _describe(m)
    return {"elements": base, "vertices": f"{base} on vertices (exitance linear within faces)",
            "linear_elements": f"{base} per element, exitance linear within faces"}.get(
        m.unknowns, f"{base} on sub-elements")


def _describe(m: C.MethodSettings) -> str:
    if m.method == "smooth":
        lam = ("auto/UPRE" if m.lambda_rule == "gcv" else f"auto/{m.lambda_rule}") if m.lam == "auto" else f"{m.lam:g}"
        return f"smooth(lambda={lam}, {m.max_iter} it)"
    if m.method in REGULARISED:
        lam = f"auto/{m.lambda_rule}" if m.lam == "auto" else f"{m.lam:g}"
        extra = f", {m.max_iter} it" if m.method == "paper" else ""
        return f"{m.method}(lambda={lam}{extra})"
    return f"{m.method}({m.n_iter} it)" if m.method == "mlem" else m.method


# what `unknowns: auto` and the solvers do; a reconstruction made by an older version is redone
SOLVER_VERSION = ("2026-11 vertex basis, cotangent prior, provisional UPRE, isolated spikes left out, exact non-negative "
                  "steps, linear_elements beyond 2500 vertices, discrepancy where UPRE interpolates, no element unknown where "
                  "only the element's edges are seen")


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    rc = cfg.model.reconstruct
    check_folders(cfg)
    out = cfg.workdir / "reconstruction.h5"
    m_ = cfg.model
    sources = _image_sources(cfg)
    digest = A.inputs_digest(system=m_.system.model_dump(mode="json"), subject=geometry_of(cfg)["subject"],
                             transfer=m_.transfer.model_dump(mode="json"),
                             reconstruct=rc.model_dump(mode="json", by_alias=True), images=sources,
                             solver=SOLVER_VERSION,
                             **({"rois": [r.model_dump(mode="json") for r in m_.rois]} if m_.rois else {}))
    if not ctx.force and A.is_up_to_date(out, "reconstruction", digest):
        ctx.say(f"reconstruct: {out} is up to date (--force to redo)")
        with A.open_artefact(out, "reconstruction") as f:
            for line in json.loads(f.attrs.get("totals_summary", "[]")):
                ctx.say(line)
        return out
    _, placer, todo = plan(cfg)
    surface = placer.surface
    _check_solver_size(cfg, ctx, surface, len(todo))
    inp = load_inputs(cfg, len(todo), surface.n_elements, surface.digest(),  # checked before any T is built
                      [pt.pose for _, pt in todo])
    if rc.sweep is not None:
        _check_sweep(cfg, inp)
    views, placer, todo, _ = ensure_T(cfg, replace(ctx, force=False), label="building T")
    P = len(todo)
    nx, ny = cfg.model.system.camera.pixels
    m = resolve_unknowns(rc.settings(), surface, cfg.model.system.camera)
    grids = {u: make_grid(cfg, ctx, surface, u)
             for u in {"elements", m.unknowns,
                       *[resolve_unknowns(s, surface, cfg.model.system.camera).unknowns
                         for s in (rc.sweep.methods if rc.sweep else ())]}}
    Ts = grids["elements"].Ts
    gm = grids[m.unknowns]
    noise = photon_noise(cfg, inp.noise_kind, inp.exposure_s, inp.frames_averaged)
    stray = [light_outside(Ts[k], inp.images[k], inp.valid[k], noise, pt.pose.label, surface)
             for k, (_, pt) in enumerate(todo)]
    ctx.say(f"reconstruct: {inp.source}; {describe(m)}, {P} pose(s); {noise.kind} noise model")
    from ._radiometric import assumed_qe_warning, counts_in
    if qe_warning := assumed_qe_warning(cfg, "reconstruct", real_counts=counts_in(cfg)):  # QE scales every photon
        ctx.say(qe_warning)
    from .outputs import reconstruction_exposure_s
    from .rois import RoiMeter

    def roi_exposure_s(inp_):  # a capture knows its frames' exposure; else as the config states it
        return inp_.exposure_s if isinstance(rc.images, C.CaptureSource) else reconstruction_exposure_s(cfg)

    rois = RoiMeter(cfg, surface, roi_exposure_s(inp))  # regions of interest (issue 24)
    t0 = time.perf_counter()
    filters = _capture_filters(cfg)
    main_filter = filters[0] if filters else getattr(rc.images, "filter", None)
    scale = _transmission(cfg, main_filter)
    if inp.truth is not None and scale != 1.0:
        inp.truth = inp.truth / scale  # the truth through the filter, as the results: before it
    totals = B.TotalMeter(ctx, P + int(rc.joint and P > 1))  # each total's photon-noise sigma; progress
    per_pose, joint = _solve_poses(gm, inp, m, noise, stray, todo, (ny, nx), rc.joint, B.Both(rois, totals), scale)
    others = {}  # filter -> (inputs, per pose, joint, ROI meter): one T per pose for every filter
    for name in filters[1:]:
        inp_f = _from_capture(cfg, surface.n_elements, name)
        t_f = _transmission(cfg, name)
        if inp_f.truth is not None and t_f != 1.0:
            inp_f.truth = inp_f.truth / t_f
        noise_f = photon_noise(cfg, inp_f.noise_kind, inp_f.exposure_s, inp_f.frames_averaged)  # its own exposure
        stray_f = [light_outside(Ts[k], inp_f.images[k], inp_f.valid[k], noise_f, pt.pose.label, surface)
                   for k, (_, pt) in enumerate(todo)]
        meter = RoiMeter(cfg, surface, roi_exposure_s(inp_f))
        pp_f, joint_f = _solve_poses(gm, inp_f, m, noise_f, stray_f, todo, (ny, nx), rc.joint, meter, t_f)
        others[name] = (inp_f, pp_f, joint_f, meter)
    seconds = time.perf_counter() - t0
    budget = B.error_budget(cfg, ctx, surface, m, gm, inp, noise, per_pose, joint, todo, scale, totals, roi_exposure_s(inp),
                            rois)
    per_pose = B.with_shift_warnings(per_pose, budget.shifts, [pt.pose.label for _, pt in todo])
    main = joint if joint is not None else per_pose[0][0]
    areas = surface.element_areas_mm2
    rows = []
    prov = provenance(cfg, surface.digest())
    for name, path in (inp.files or {}).items():
        prov.add_file(name, path, base=out.parent)
    with A.write_artefact(out, "reconstruction", config_sha256=cfg.sha256,
                          inputs={"T": json.dumps([pt.key for _, pt in todo]), "images": inp.source},
                          provenance=prov) as f:
        f.attrs["inputs_digest"] = digest
        A.write_surface(f.create_group("surface"), surface)
        _write_geometry(f.create_group("geometry"), cfg, placer, views, todo)
        g = f.create_group("flux")
        _write_flux(g, main, areas)
        g.attrs["joint_over_poses"] = joint is not None
        pp = f.create_group("per_pose")
        pp.create_dataset("power", data=np.array([r.power for r, _ in per_pose])).attrs["unit"] = "photons"
        pp.create_dataset("sigma", data=np.array([r.sigma for r, _ in per_pose])).attrs["unit"] = "photons"
        pp.create_dataset("observed", data=np.array([r.observed for r, _ in per_pose]))
        pp.create_dataset("total", data=[np.nansum(r.power) for r, _ in per_pose]).attrs["unit"] = "photons"
        pp.create_dataset("lambda", data=[r.lam for r, _ in per_pose])
        pp.create_dataset("vertices_mm", data=np.array([sc.surface.vertices_mm for sc, _ in todo]),
                          compression="gzip").attrs["meaning"] = "the surface placed at each pose (faces as /surface/faces)"
        pp.create_dataset("backprojection_total", data=[np.nansum(backprojection(Ts[k], np.where(
            inp.valid[k], inp.images[k], 0.0).ravel())) for k in range(P)]).attrs["unit"] = \
            "a.u.: sum of T'a (photons weighted by the dimensionless T; not a flux)"
        pp.create_dataset("direct_roi_photons", data=[direct_roi(todo[k][1].path, inp.images[k]) for k in range(P)]
                          ).attrs["meaning"] = "measured photons summed over the pixels the direct view reaches"
        pp.create_dataset("heights_mm", data=[pt.pose.height_mm for _, pt in todo])
        pp.create_dataset("rotations_deg", data=[pt.pose.rotation_deg for _, pt in todo])
        fit = f.create_group("fit")
        fitted = np.array([fi for _, fi in per_pose])
        fit.create_dataset("measured", data=inp.images.astype(np.float32), compression="gzip").attrs["unit"] = "photons"
        fit.create_dataset("fitted", data=fitted.astype(np.float32), compression="gzip").attrs["unit"] = "photons"
        fit.create_dataset("residual", data=(inp.images - fitted).astype(np.float32), compression="gzip")
        fit.create_dataset("valid", data=inp.valid, compression="gzip")
        f.attrs["method"] = m.method
        # the exposure that makes rates (photons/s), fixed here: summary, report and the VTP read it
        # from this file, and refuse a config that later states another (a published rate must not move)
        t_rate = roi_exposure_s(inp)
        f.attrs["rate_exposure_s"] = float(t_rate) if t_rate is not None else np.nan
        f.attrs["rate_exposure_source"] = ("capture.h5 frames" if isinstance(rc.images, C.CaptureSource)
                                           else "config" if t_rate is not None else "none")
        f.attrs["settings"] = json.dumps(m.model_dump(mode="json", by_alias=True))
        f.attrs["lambda_used"] = float(main.lam) if main.lam is not None else np.nan
        f.attrs["seconds"] = A.recorded_seconds(seconds)
        if inp.truth is not None:
            t = f.create_group("truth")
            t.create_dataset("power", data=inp.truth)
            err = [error_l1(r.power, inp.truth) for r, _ in per_pose]
            ratio = [total_ratio(r.power, inp.truth) for r, _ in per_pose]
            t.create_dataset("error_per_pose", data=err)
            t.create_dataset("total_ratio_per_pose", data=ratio)
            t.attrs["error"] = error_l1(main.power, inp.truth)
            t.attrs["total_ratio"] = total_ratio(main.power, inp.truth)
            for name, sel in (("observed", main.observed), ("well_observed", main.well_observed)):
                if sel.any():
                    only = np.where(sel, main.power, np.nan)
                    t.attrs[f"error_{name}"] = error_l1(only, inp.truth, observed_only=True)
                    t.attrs[f"total_ratio_{name}"] = total_ratio(only, inp.truth, observed_only=True)
        for k, (_, pt) in enumerate(todo):
            r = per_pose[k][0]
            row = [pt.pose.height_mm, pt.pose.rotation_deg, _headline_cell(r),
                   f"{r.observed.mean():.0%}", f"{r.lam:.3g}" if r.lam is not None else "-"]
            if inp.truth is not None:
                row += _vs_truth(r.power, r.observed, inp.truth)
            rows.append(row)
        if joint is not None:
            row = ["joint", "", _headline_cell(joint), f"{joint.observed.mean():.0%}",
                   f"{joint.lam:.3g}" if joint.lam is not None else "-"]
            if inp.truth is not None:
                row += _vs_truth(joint.power, joint.observed, inp.truth)
            rows.append(row)
        per_pose, joint, emission_lines = _emission_checks(f, placer, views, todo, per_pose, joint, inp, noise, cfg)
        _warnings(ctx, f, per_pose, joint, todo)
        summary = _total_summary(per_pose, joint, todo, {b.label: b.sigma for b in budget.totals})
        B.write(f.create_group("budget"), budget)
        summary += budget.lines()
        f.attrs["totals_summary"] = json.dumps(summary)
        pp.create_dataset("chi2_per_pixel", data=[r.chi2_per_pixel for r, _ in per_pose])
        heads = [headline_of(r) for r, _ in per_pose]
        pp.create_dataset("headline_total", data=[h.photons for h in heads]).attrs["unit"] = \
            "photons: the total over observed elements, or over well-observed ones where headline_reason says why"
        pp.create_dataset("headline_reason", data=np.array([h.reason or "" for h in heads], dtype=object),
                          dtype=h5py.string_dtype())
        pp.create_dataset("observation", data=np.array([r.observation for r, _ in per_pose]))
        if rc.sweep is not None:
            _sweep(cfg, ctx, f.create_group("sweep"), grids, todo)
        if rois:
            rois.write(f.create_group("rois"))
        if filters:
            _write_filters(f.create_group("filters"), cfg, {filters[0]: (inp, per_pose, joint, rois), **others}, areas,
                           [pt.path for _, pt in todo])
        from ..artefacts.digest import seal

        seal(f, ("flux", "per_pose", "rois", "surface", "truth"))  # fluxmap study refuses a file changed after this
    header = ["height_mm", "rotation_deg", "total photons", "observed", "lambda"]
    if inp.truth is not None:  # the paper's convention (unobserved elements count as 0) beside the observed ones
        header += ["error all / observed", "total ratio all / observed"]
    ctx.table(header, rows)
    ctx.say(f"{seconds:.2f} s of solving")
    if filters and rois:
        from ..quantify.rois import spectrum_csv_text

        A.write_text(cfg.workdir / "rois_spectrum.csv", spectrum_csv_text(
            [(nm, _transmission(cfg, nm), mt) for nm, mt in [(filters[0], rois)] + [(k, v[3]) for k, v in others.items()]]))
        ctx.say(f"ROI spectrum over {len(filters)} filters: {cfg.workdir / 'rois_spectrum.csv'}")
    if rois:
        ctx.table(*rois.table())
        for name, label, _, _, x in rois.rows():
            if x.status:
                ctx.warn(f"ROI {name}, {label}: {x.status}")
        ctx.say(f"ROI numbers for other tools: {rois.write_csv(cfg.workdir / 'rois.csv')}"
                + ("" if rois.exposure_s is not None else " (no exposure time given: per exposure, not per second)"))
    export_3d(cfg, ctx, out)  # <workdir>/*.vtp for ParaView/pyvista, from the artefact
    for line in summary + emission_lines:
        ctx.say(line)
    return out


def _without_emission(x):
    """A provenance (or a geometry dict) without ``subject.emission``."""
    import copy

    geo = copy.deepcopy(x.geometry if isinstance(x, A.Provenance) else x)
    if isinstance(geo.get("subject"), dict):
        geo["subject"].pop("emission", None)
    return replace(x, geometry=geo) if isinstance(x, A.Provenance) else geo


def _simulated_emission(cfg: C.LoadedConfig) -> str | None:
    """How the images were simulated, when they come from simulation.h5 under another emission
    model than this config's: a warning (None when the same, or not simulated)."""
    rc = cfg.model.reconstruct
    if rc.images is not None:
        return None
    path = _simulation(cfg)
    try:
        with A.open_artefact(path, "simulation") as f:
            then = (A.read_provenance(f).geometry.get("subject") or {}).get("emission")
            if f["truth"].attrs.get("kind") == "montecarlo":  # photons: no emission model to mismatch
                return None
    except UserError:
        return None
    now = (geometry_of(cfg).get("subject") or {}).get("emission")
    if then == now:
        return None
    what = lambda e: "lambertian" if e is None else e.get("model", "?") + (  # noqa: E731
        f" (refractive index {e['refractive_index']:g})" if "refractive_index" in e else "")
    return (f"the images were simulated with the emission model {what(then)} and are reconstructed with "
            f"{what(now)} (subject.emission): a model-mismatch experiment, unless the simulation's light does not "
            "depend on it (Monte Carlo photons).")


def _emission_checks(f, placer, views, todo, per_pose, joint, inp, noise, cfg=None) -> tuple[list, object, list[str]]:
    """Issue 21, item 2: per pose (and jointly) the share of the observed light seen beyond 60 and
    75 deg from the normal and the share of the total resting on such views, and whether the
    residual is structured by viewing angle (:mod:`fluxcli.inverse.diagnostics`); stored under
    /emission and /per_pose, warnings added to the poses' (and the joint solve's)."""
    from ..inverse import diagnostics as D
    from ..optics.emission import CHECK_DEG

    prof = placer.emission
    g = f.create_group("emission")
    g.attrs["model"] = prof.model
    g.attrs["description"] = prof.describe()
    g.attrs["refractive_index"] = np.nan if prof.refractive_index is None else prof.refractive_index
    g.attrs["table_file"] = prof.source or ""
    deg = np.linspace(0.0, 90.0, 181)
    g.create_dataset("angle_deg", data=deg)
    g.create_dataset("relative_radiance", data=prof.radiance(np.radians(deg))).attrs["meaning"] = "L(theta) / L(0)"
    mismatch = _simulated_emission(cfg) if cfg is not None else None
    weights = [v.weight for v in views]
    centres = [v.camera.center_mm for v in views]
    light, totals, slopes, out, all_T, all_ang = [], [], [], [], [], []
    for k, ((res, fitted), (scene, pt)) in enumerate(zip(per_pose, todo)):
        Tv = [load_view(pt.path, v) for v in range(len(views))]
        ang = D.element_angles(scene.surface, centres, prof.weight)
        light.append(D.grazing_shares(Tv, weights, res.power, ang))
        totals.append(D.total_shares(Tv, weights, res.power, ang))
        px = D.pixel_angles(Tv, weights, res.power, ang)
        model = np.nan_to_num(fitted.ravel())
        st = D.angle_structure(inp.images[k].ravel(), model, noise.variance(model), px, inp.valid[k].ravel())
        warns = tuple(w for w in (D.grazing_warning(totals[-1]), D.structure_warning(st, prof.describe()),
                                  mismatch if k == 0 else None) if w)
        out.append((replace(res, warnings=tuple(res.warnings) + warns), fitted) if warns else (res, fitted))
        slopes.append([np.nan, np.nan] if st is None else [st.slope_per_10deg, st.t])
        if joint is not None:
            all_T += Tv
            all_ang.append(ang)
    pp = f["per_pose"]
    bands = np.array(D.BANDS_DEG)
    pp.create_dataset("light_beyond_deg", data=np.array(light)).attrs["bands_deg"] = bands
    pp["light_beyond_deg"].attrs["meaning"] = "share of the model image's light that left the surface beyond each angle"
    pp.create_dataset("total_beyond_deg", data=np.array(totals)).attrs["bands_deg"] = bands
    pp["total_beyond_deg"].attrs["meaning"] = ("share of the reconstructed total resting on views beyond each angle "
                                               "(each element weighted by the share of its collected light from there)")
    pp.create_dataset("residual_vs_angle", data=np.array(slopes)).attrs["meaning"] = \
        "relative residual change per 10 deg of emission angle, and its t value (NaN: not testable)"
    lines = [f"emission model: {prof.describe()}"
             + ("" if prof.is_lambertian else " (L/L0 " + ", ".join(
                 f"{r:.2f} at {a:g} deg" for a, r in zip(CHECK_DEG[::2], prof.radiance(np.radians(CHECK_DEG[::2]))))
                + ")")]
    lines += [f"seen at grazing angles, pose {pt.pose.label}: light {D.describe_shares(li)}; "
              f"total {D.describe_shares(to)}" for li, to, (_, pt) in zip(light, totals, todo)]
    if joint is not None:
        ang = D.ElementAngles(np.concatenate([a.mean_deg for a in all_ang]), np.concatenate([a.beyond for a in all_ang]))
        jl = D.grazing_shares(all_T, weights * len(todo), joint.power, ang)
        jt = D.total_shares(all_T, weights * len(todo), joint.power, ang)
        g.create_dataset("joint_light_beyond_deg", data=jl)
        g.create_dataset("joint_total_beyond_deg", data=jt)
        lines.append(f"seen at grazing angles, all poses jointly: light {D.describe_shares(jl)}; "
                     f"total {D.describe_shares(jt)}")
        w = D.grazing_warning(jt)
        if w:
            joint = replace(joint, warnings=tuple(joint.warnings) + (w,))
    return out, joint, lines


def _vs_truth(power, observed, truth) -> list[str]:
    """Error and total ratio against the simulated truth over all elements (unobserved ones
    count as 0, the paper's convention) and over the observed ones."""
    only = np.where(observed, power, np.nan)
    if not observed.any():
        return [f"{error_l1(power, truth):.2%} / -", f"{total_ratio(power, truth):.3f} / -"]
    return [f"{error_l1(power, truth):.2%} / {error_l1(only, truth, observed_only=True):.2%}",
            f"{total_ratio(power, truth):.3f} / {total_ratio(only, truth, observed_only=True):.3f}"]


def _write_geometry(g, cfg: C.LoadedConfig, placer, views, todo) -> None:
    """What the report draws besides the flux, so that it reads artefacts only."""
    cam = cfg.model.system.camera
    g.attrs["axis_point_mm"] = np.asarray(placer.axis_point, float)
    g.attrs["axis_direction"] = np.asarray(placer.axis, float)
    g.attrs["camera_look"] = np.asarray(cam.pose.look, float)
    g.attrs["camera_up"] = np.asarray(cam.pose.up, float)
    g.attrs["view_names"] = json.dumps([v.name for v in views])
    base = cfg.workdir  # paths relative to the artefact's folder: the same bytes in any clone
    g.attrs["T_files"] = json.dumps([A.portable_path(pt.path, base) for _, pt in todo])
    files = getattr(cfg.model.reconstruct.images, "files", None)  # image files (not a capture)
    g.attrs["image_files"] = json.dumps([A.portable_path(cfg.resolve(p), base) for p in files] if files else [])


def _write_flux(g, res, areas) -> None:
    g.create_dataset("power", data=res.power).attrs["unit"] = "photons per element (NaN: unobserved)"
    g.create_dataset("exitance", data=res.power / areas).attrs["unit"] = "photons mm^-2"
    g.create_dataset("observed", data=res.observed)
    g.create_dataset("sigma", data=res.sigma).attrs["unit"] = "photons (1 sd)"
    g.create_dataset("total", data=np.nansum(res.power)).attrs["unit"] = "photons over observed elements"
    # issue 8: what the data pin down, what they barely see, and what went wrong — in the artefact
    well = res.well_observed
    g.create_dataset("observation", data=res.observation).attrs["meaning"] = \
        "0 unobserved, 1 poorly observed (tiny sensitivity next to its neighbours, or sigma >= value), 2 well observed"
    g.create_dataset("well_observed", data=well)
    g.create_dataset("total_well_observed", data=np.nansum(np.where(well, res.power, 0.0))).attrs["unit"] = \
        "photons over well-observed elements"
    g.create_dataset("total_poorly_observed", data=np.nansum(np.where(res.observed & ~well, res.power, 0.0))
                     ).attrs["unit"] = "photons over poorly observed elements"
    # issue 25: the number to read first; the total over observed elements when it is pinned down
    h = headline_of(res)
    d = g.create_dataset("headline_total", data=h.photons)
    d.attrs["unit"] = f"photons over {h.over}"
    d.attrs["over"] = h.over
    d.attrs["reason"] = h.reason or ""
    g.attrs["chi2_per_pixel"] = res.chi2_per_pixel
    g.attrs["converged"] = res.converged
    g.attrs["iterations"] = res.iterations
    g.attrs["lambda"] = res.lam
    g.attrs["warnings"] = json.dumps(list(res.warnings))


def _write_filters(g, cfg: C.LoadedConfig, results: dict, areas, T_paths) -> None:
    """/filters/<name>: each filter's reconstruction (joint, else the first pose) and its
    per-pose powers, transmission and ROI numbers; g.attrs['order'] the filters in order."""
    g.attrs["order"] = json.dumps(list(results))
    g.attrs["meaning"] = "the light leaving the surface within each filter's band, before the filter (divided by its transmission)"
    for name, (inp_f, pp, joint, meter) in results.items():
        h = g.create_group(name)
        h.attrs["transmission"] = _transmission(cfg, name)
        h.attrs["source"] = inp_f.source
        main = joint if joint is not None else pp[0][0]
        _write_flux(h.create_group("flux"), main, areas)
        h.create_dataset("per_pose_power", data=np.array([r.power for r, _ in pp])).attrs["unit"] = "photons"
        h.create_dataset("per_pose_total", data=[np.nansum(r.power) for r, _ in pp]).attrs["unit"] = "photons"
        h.create_dataset("direct_roi_photons", data=[direct_roi(T_paths[k], inp_f.images[k]) for k in range(len(pp))]
                         ).attrs["meaning"] = "measured photons (through the filter) summed over the pixels the direct view reaches"
        if inp_f.truth is not None:
            h.create_dataset("truth_power", data=inp_f.truth).attrs["unit"] = "photons (before the filter)"
        if meter:
            meter.write(h.create_group("rois"))


def headline_of(res):
    """The trustworthy total of one solve (:func:`fluxcli.inverse.methods.headline_total`)."""
    from ..inverse.methods import headline_total

    return headline_total(res.power, res.observed, res.well_observed, res.warnings)


def _headline_cell(res) -> str:
    h = headline_of(res)
    return f"{h.photons:.4g}" if h.reason is None else f"{h.photons:.4g} over well-observed (see below)"


def _warnings(ctx: RunContext, f, per_pose, joint, todo) -> list[str]:
    """Every warning of every solve: to the console and to /warnings (never silent)."""
    out = [f"pose {pt.pose.label}: {w}" for (r, _), (_, pt) in zip(per_pose, todo) for w in r.warnings]
    if joint is not None:
        out += [f"joint: {w}" for w in joint.warnings]
    f.create_dataset("warnings", data=np.array(out, dtype=object), dtype=h5py.string_dtype())
    for w in out:
        ctx.warn(w)
    return out


def _total_summary(per_pose, joint, todo, sigmas: dict | None = None) -> list[str]:
    """The number the mission is about: the total per pose and jointly, with its spread and,
    from the error budget (``sigmas``: its label -> 1 sd in photons), its σ."""
    sigmas = sigmas or {}
    tot = np.array([np.nansum(r.power) for r, _ in per_pose])
    well = np.array([np.nansum(np.where(r.well_observed, r.power, 0.0)) for r, _ in per_pose])

    def pm(label: str) -> str:
        s = sigmas.get(label, np.nan)
        return f" ± {s:.2g}" if np.isfinite(s) else ""

    lines = []
    for (r, _), (_, pt), t, w in zip(per_pose, todo, tot, well):
        h, what = headline_of(r), f"pose {pt.pose.label}"
        lines.append(h.line(f"total flux, {what}") + (f"; observed total {t:.4g}{pm(what)} photons" if pm(what) else "")
                     if h.reason else
                     f"total flux, {what}: {t:.4g}{pm(what)} photons over observed elements ({w:.4g} over well-observed)")
    if len(tot) > 1:
        spread = (tot.max() - tot.min()) / tot.mean() if tot.mean() > 0 else np.nan
        lines.append(f"total flux over {len(tot)} poses: mean {tot.mean():.4g} photons, spread (max-min)/mean "
                     f"{spread:.1%}, sd/mean {tot.std(ddof=1) / tot.mean():.1%}")
    if joint is not None:
        h, what, t = headline_of(joint), "all poses jointly", np.nansum(joint.power)
        lines.append(h.line(f"total flux, {what}") + (f"; observed total {t:.4g}{pm(what)} photons" if pm(what) else "")
                     if h.reason else
                     f"total flux, {what}: {t:.4g}{pm(what)} photons over observed elements "
                     f"({np.nansum(np.where(joint.well_observed, joint.power, 0.0)):.4g} over well-observed)")
    return lines


# ------------------------------------------------------------------ the study sweep
def _sweep_cell(sim_path: str, grids_k: dict, pose: int, level: int, repeats: int,
                methods: list[C.MethodSettings], noise: N.PhotonNoise, sensor: dict | None) -> np.ndarray:
    """Errors (methods x repeats) of one (level, pose) cell; runs in a worker process.
    ``grids_k``: per unknowns (T's cache file, adjacency, parent or VertexMap, n_elements, areas)."""
    import h5py

    Ts, parts = {}, {}
    for u in {m.unknowns for m in methods}:  # T by path: no T inside a task graph
        T, part = load_T(grids_k[u][0]), grids_k[u][2]
        if isinstance(part, VertexMap):  # the fine T: per vertex, and per element for the classes
            T, part = part.unknowns_T(T, load_T_tangent(grids_k[u][0])), part.element_map(T)
        Ts[u], parts[u] = T, part
    out = np.zeros((len(methods), repeats))
    with h5py.File(sim_path, "r") as f:
        truth = f["truth/power"][()] * f["truth/level_scale"][level]
        imgs = f["images/noisy"][level, :repeats, pose].astype(float)
        counts = f["images/counts"][level, :repeats, pose] if "counts" in f["images"] else None
    model = N.EMCCDModel(**sensor) if (sensor is not None and counts is not None) else None
    for r in range(repeats):
        valid = np.isfinite(imgs[r]) & (~N.saturated(counts[r], model) if model is not None else True)
        for i, m in enumerate(methods):
            _, adjacency, _, n_el, areas = grids_k[m.unknowns]
            res, _ = run_method(Ts[m.unknowns], imgs[r], valid, m, noise, adjacency, parts[m.unknowns], n_el, areas)
            out[i, r] = error_l1(res.power, truth)
    return out


def _check_sweep(cfg: C.LoadedConfig, inp: Inputs) -> None:
    """Before any solving: a sweep needs the simulation's truth and levels that exist."""
    sw = cfg.model.reconstruct.sweep
    if inp.truth is None:
        raise UserError("reconstruct.sweep: a sweep needs a simulation (ground truth), not image files "
                        "(reconstruct.images).")
    path = _simulation(cfg)
    with A.open_artefact(path, "simulation") as f:
        L, R = f["images/noisy"].shape[:2]
    if sw.repeats is not None and sw.repeats > R:
        raise UserError(f"reconstruct.sweep.repeats: {path} holds {R} noise repeat(s); asked for {sw.repeats} "
                        "(simulate more with simulate.noise.repeats).")
    bad = [li for li in (sw.levels or ()) if li >= L]
    if bad:
        raise UserError(f"reconstruct.sweep.levels: {path} holds {L} signal level(s) (0 to {L - 1}); asked for {bad}.")


def _sweep(cfg: C.LoadedConfig, ctx: RunContext, g, grids: dict, todo) -> None:
    sw = cfg.model.reconstruct.sweep
    path = _simulation(cfg)
    with A.open_artefact(path, "simulation") as f:
        L, R, P = f["images/noisy"].shape[:3]
        snr = f["images/max_snr"][()]
        levels = f["truth/levels_peak_photons"][()]
        sensor = None
        noise = photon_noise(cfg, str(f["images"].attrs.get("noise_model", "poisson")).replace("none", "poisson"),
                             float(f["images"].attrs.get("exposure_s", 1.0)))
        if "counts" in f["images"]:
            sensor = cfg.model.system.camera.sensor.model_dump() | {"exposure_s": float(f["images"].attrs["exposure_s"])}
    lv = list(sw.levels) if sw.levels is not None else list(range(L))
    reps = min(sw.repeats or R, R)
    methods = [resolve_unknowns(x, grids["elements"].surface, cfg.model.system.camera) for x in sw.methods]
    cells = [(li, k) for li in lv for k in range(P)]
    err = np.full((len(methods), L, P, reps), np.nan)
    t0 = time.perf_counter()
    def per_pose(k):  # only what this pose's cell needs crosses to the worker; its T by path
        return {u: (gr.paths[k], gr.adjacency, gr.vmap if gr.vmap is not None else gr.parent, gr.n_elements, gr.areas)
                for u, gr in grids.items()}

    args = [(str(path), per_pose(k), k, li, reps, methods, noise, sensor)
            for li, k in cells]
    with ctx.progress("sweep", total=len(cells)) as advance:
        if ctx.jobs > 1 or ctx.client is not None:  # local processes, or the cells on a Dask cluster
            with pool_for(ctx.client)(ctx.jobs) as ex:
                for (li, k), e in zip(cells, ex.map(_sweep_cell, *zip(*args))):
                    err[:, li, k] = e
                    advance()
        else:
            for (li, k), a in zip(cells, args):
                err[:, li, k] = _sweep_cell(*a)
                advance()
    names = [describe(m) for m in methods]
    g.create_dataset("error", data=err).attrs["layout"] = "error[method, level, pose, repeat] (paper Eq. 15)"
    g.create_dataset("mean", data=np.nanmean(err, axis=3))
    g.create_dataset("sd", data=np.nanstd(err, axis=3, ddof=1) if reps > 1 else np.zeros(err.shape[:3]))
    g.create_dataset("max_snr", data=snr)
    g.create_dataset("levels_peak_photons", data=levels)
    g.attrs["methods"] = json.dumps(names)
    g.attrs["seconds"] = A.recorded_seconds(time.perf_counter() - t0)
    rows = []
    for k, (_, pt) in enumerate(todo):
        for li in lv:
            rows.append([pt.pose.height_mm, f"{levels[li]:.0e}", f"{snr[li, k]:.1f}",
                         *[f"{100 * np.mean(err[i, li, k]):.2f} ± {100 * np.std(err[i, li, k], ddof=1 if reps > 1 else 0):.2f}"
                           for i in range(len(methods))]])
    ctx.table(["height_mm", "peak", "max SNR", *[f"{n} error %" for n in names]], rows)
    ctx.say(f"sweep: {len(cells)} cells x {reps} repeats x {len(methods)} methods in {time.perf_counter() - t0:.1f} s")
