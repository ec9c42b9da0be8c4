"""The YAML config: schema (validated, unknown keys rejected) and loader.

Every field carries its unit in its name and one line of description.  Paths in a config
are relative to the config file.  See DESIGN.md section 8 for the contract.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, field_validator, model_validator

from .errors import UserError
from .inverse.methods import METHODS

Vec3 = tuple[float, float, float]


MAX_LENGTH_MM = 1e6  # 1 km: no imaging rig is larger, and squares of lengths beyond ~1e150 overflow
MAX_DURATION_S = 86400.0  # a day: no exposure, settle or timeout is longer, and a sleep of 1e300 s overflows the clock


def _longest(v) -> float:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return abs(float(v))
    if isinstance(v, (list, tuple)):
        return max((_longest(x) for x in v), default=0.0)
    return 0.0


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN/inf: never a length

    @field_validator("*", mode="after")
    @classmethod
    def _lengths_in_range(cls, v, info):
        """Every ``*_mm`` value (and each number in a ``*_mm`` list) is at most 1 km, every ``*_s``
        duration at most a day; a ``*_per_mm`` is a density, not a length (the L490MZ's 2155789
        counts per mm), and a ``*_per_s`` or ``*_mm_s`` a rate."""
        name = info.field_name or ""
        if name.endswith("_mm") and not name.endswith("_per_mm") and _longest(v) > MAX_LENGTH_MM:
            raise ValueError(f"lengths are in millimetres here and at most {MAX_LENGTH_MM:g} mm (1 km); "
                             f"got {_longest(v):g}")
        if (name.endswith("_s") and not name.endswith(("_per_s", "_mm_s"))  # a duration, not a rate
                and _longest(v) > MAX_DURATION_S):
            raise ValueError(f"durations are in seconds here and at most {MAX_DURATION_S:g} s (a day); "
                             f"got {_longest(v):g}")
        if _has_nul(v):  # the OS refuses it in any path ("embedded null byte", once exit 1 from a study file)
            raise ValueError("holds a NUL character (\\x00), which no file name or name may contain")
        return v

    @model_validator(mode="before")
    @classmethod
    def _no_empty_paths(cls, data):
        """A path given as empty text (``workdir: ""``) is read by Python as "." (the config's own
        folder), so artefacts or a T cache would land beside the configs without a word: refused,
        naming the key."""
        if isinstance(data, dict):
            for name, field in cls.model_fields.items():
                if name in data and _holds_path(field.annotation) and _has_blank(data[name]):
                    raise ValueError(f"{name}: {EMPTY_PATH}")
        return data


EMPTY_PATH = "is an empty path; give a file or folder name, or leave the key out for its default"


def _holds_path(annotation) -> bool:
    """Whether a field's type is, or holds, a Path (``Path | None``, ``tuple[Path, ...]``)."""
    return annotation is Path or any(_holds_path(a) for a in get_args(annotation))


def _has_blank(v) -> bool:
    """Whether a value (or an item of a list) is text with nothing but spaces in it."""
    if isinstance(v, str):
        return not v.strip()
    return isinstance(v, (tuple, list)) and any(isinstance(x, str) and not x.strip() for x in v)


def _has_nul(v) -> bool:
    """Whether a text or path value (or one inside a list or mapping) holds a NUL character."""
    if isinstance(v, (str, Path)):
        return "\x00" in str(v)
    if isinstance(v, (tuple, list)):
        return any(_has_nul(x) for x in v)
    if isinstance(v, dict):
        return any(_has_nul(k) or _has_nul(x) for k, x in v.items())
    return False


def _unit(v: Vec3, what: str) -> Vec3:
    n = math.hypot(*v)  # scaled: no overflow in the squares
    if n == 0:
        raise ValueError(f"{what} must be a non-zero vector")
    if not 1e-100 < n < 1e100:  # a direction; code downstream normalises it with plain squares
        raise ValueError(f"{what} is a direction: give it components of ordinary size (its length is {n:g})")
    return tuple(c / n for c in v)  # type: ignore[return-value]


# --------------------------------------------------------------------------- system
MIN_F_NUMBER = 0.5  # sin θ ≤ 1 in air: N = 1 / (2 NA) ≥ 0.5 for any lens (Abbe's sine condition)


class Lens(Model):
    focal_length_mm: float = Field(gt=0, description="Thin-lens focal length f (mm).")
    f_number: float | None = Field(None, gt=0, description="f-number N; aperture radius R = f/(2N).")
    aperture_diameter_mm: float | None = Field(None, gt=0, description="Lens aperture diameter 2R (mm), instead of f_number.")
    focus_distance_mm: float = Field(description="Distance from the lens centre to the front focal plane along the optical axis (mm).")

    @model_validator(mode="after")
    def _check(self) -> "Lens":
        if (self.f_number is None) == (self.aperture_diameter_mm is None):
            raise ValueError("give exactly one of f_number and aperture_diameter_mm")
        if self.focus_distance_mm <= self.focal_length_mm:
            raise ValueError(
                f"focus_distance_mm ({self.focus_distance_mm}) must exceed focal_length_mm "
                f"({self.focal_length_mm}): a thin lens cannot focus closer than its focal length"
            )
        n = self.focal_length_mm / (2 * self.aperture_radius_mm)
        if n < MIN_F_NUMBER:  # (a slip: 0.28 for 2.8, an aperture in cm or a radius as a diameter...)
            raise ValueError(
                f"the aperture is f/{n:.3g} (focal_length_mm {self.focal_length_mm:g}, aperture diameter "
                f"{2 * self.aperture_radius_mm:.4g} mm): no lens in air is faster than f/0.5, whose aperture is twice "
                "its focal length; is f_number or aperture_diameter_mm mistyped?"
            )
        return self

    @property
    def aperture_radius_mm(self) -> float:
        if self.aperture_diameter_mm is not None:
            return self.aperture_diameter_mm / 2
        return self.focal_length_mm / (2 * self.f_number)  # type: ignore[operator]


class CameraPose(Model):
    lens_center_mm: Vec3 = Field(description="World position of the lens centre C (mm).")
    look: Vec3 = Field((0.0, 0.0, -1.0), description="Optical axis n, from the lens into the scene.")
    up: Vec3 = Field((0.0, 1.0, 0.0), description="World direction that appears at the top of the image (row 0).")

    @model_validator(mode="after")
    def _check(self) -> "CameraPose":
        look = _unit(self.look, "look")
        up = _unit(self.up, "up")
        if abs(sum(a * b for a, b in zip(look, up))) > 0.999:
            raise ValueError("up must not be parallel to look")
        return self


class Aperture(Model):
    distance_mm: float = Field(gt=0, description="Distance of the aperture plane in front of the lens, along the optical axis (mm).")
    diameter_mm: float = Field(gt=0, description="Diameter of the circular opening, centred on the optical axis (mm).")


class Sensor(Model):
    quantum_efficiency: float = Field(0.9, gt=0, le=1, description="Photons to electrons (QE at the imaging wavelength).")
    em_gain: float = Field(300.0, ge=1, description="EM register gain G.")
    read_noise_e: float = Field(50.0, ge=0, description="Read noise at the output node (rms electrons).")
    bias_counts: float = Field(500.0, ge=0, description="Offset added by the ADC (counts).")
    electrons_per_count: float = Field(10.0, gt=0, description="ADC conversion gain (electrons per count).")
    dark_current_e_per_s: float = Field(0.001, ge=0, description="Dark current per pixel (electrons/s).")
    cic_e_per_pixel: float = Field(0.005, ge=0, description="Clock-induced charge per pixel per frame (electrons).")
    bit_depth: int = Field(16, ge=8, le=16, description="ADC bit depth; counts saturate at 2**bit_depth - 1.")


class CameraUncertainty(Model):
    """1 sd of the calibrated camera (what ``calibrate`` writes as camera.yaml's ``camera.uncertainty``);
    reconstruct carries it into the sigma of every total (reconstruct.calibration_budget)."""

    focal_length_mm: float | None = Field(None, ge=0, description="1 sd of lens.focal_length_mm (mm).")
    focus_distance_mm: float | None = Field(None, ge=0, description="1 sd of lens.focus_distance_mm (mm).")
    aperture_diameter_mm: float | None = Field(None, ge=0, description="1 sd of the lens aperture diameter 2R (mm).")
    lens_center_mm: tuple[float, float, float] | None = Field(
        None, description="1 sd of pose.lens_center_mm along world x, y, z (mm), each >= 0.")
    look_deg: float | None = Field(None, ge=0, description="1 sd of the optical axis direction, per tilt axis (degrees).")
    gain_relative: float | None = Field(None, ge=0, description="Relative 1 sd of the photons per count (radiometric gain, QE included; e.g. 0.02).")

    @field_validator("lens_center_mm")
    @classmethod
    def _nonneg(cls, v):
        if v is not None and min(v) < 0:
            raise ValueError("lens_center_mm: each 1 sd must be >= 0")
        return v


class Camera(Model):
    pixels: tuple[int, int] = Field(description="Sensor size [nx, ny] in (binned) pixels: columns, rows.")
    pixel_pitch_mm: float = Field(gt=0, description="(Binned) pixel pitch on the detector (mm).")
    lens: Lens | None = Field(None, description="The thin lens (required by every stage but calibrate, which derives it).")
    pose: CameraPose | None = Field(None, description="Where the camera is and where it looks (required by every stage but calibrate).")
    measured: dict[str, float | tuple[float, ...]] = Field(default_factory=dict, exclude=True, description="The 1 sigma of each measured value (calibrate writes it: lens.focal_length_mm, pose.lens_center_mm, sensor.em_gain, ...), in the value's unit.")
    assumed: dict[str, str] = Field(default_factory=dict, exclude=True, description="Values that were not measured, each with where the assumption comes from (calibrate writes it, e.g. quantum_efficiency); an assumed quantum_efficiency is warned by every stage that turns counts into photons.")
    apertures: tuple[Aperture, ...] = Field((), description="Extra circular apertures in front of the lens (the beta term).")
    sensor: Sensor = Field(Sensor(), description="Detector model used to turn photons into counts.")
    uncertainty: CameraUncertainty | None = Field(None, description="1 sd of the calibrated values (calibrate writes it); reconstruct propagates it into every total's sigma.")

    @field_validator("pixels")
    @classmethod
    def _pixels(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] < 1 or v[1] < 1:
            raise ValueError("pixels must be two positive integers [nx, ny]")
        return v


class Mirror(Model):
    name: str | None = Field(None, description="Name of the view it adds (default mirror0, mirror1, ...).")
    center_mm: Vec3 = Field(description="Centre of the rectangular mirror (mm).")
    normal: Vec3 = Field(description="Normal of the reflecting side.")
    axis: Vec3 = Field(description="Direction of the first side of the rectangle (in the mirror plane).")
    size_mm: tuple[float, float] = Field(description="[along axis, along normal x axis] (mm).")
    reflectance: float = Field(1.0, gt=0, le=1, description="Mirror reflectance rho.")
    normal_sigma_deg: float | None = Field(None, ge=0, description="1 sd of the normal's direction, per tilt axis (degrees; calibrate's), for reconstruct's calibration budget.")
    offset_sigma_mm: float | None = Field(None, ge=0, description="1 sd of the mirror plane's position along its normal (mm), for reconstruct's calibration budget.")
    scale: float = Field(1.0, gt=0, description="Per-view scale s (filter angular transmission heuristic).")

    @model_validator(mode="after")
    def _check(self) -> "Mirror":
        n = _unit(self.normal, "normal")
        a = _unit(self.axis, "axis")
        if abs(sum(x * y for x, y in zip(n, a))) > 1e-6:
            raise ValueError("axis must lie in the mirror plane (perpendicular to normal)")
        if min(self.size_mm) <= 0:
            raise ValueError("size_mm must be positive")
        return self


class Stage(Model):
    top_z_mm: float = Field(0.0, description="Height of the stage top at stage height 0 (mm).")
    size_mm: tuple[float, float] = Field((150.0, 150.0), description="Plate extent along x and y (mm).")
    thickness_mm: float = Field(5.0, gt=0, description="Plate thickness (mm).")
    center_xy_mm: tuple[float, float] = Field((0.0, 0.0), description="Plate centre in x, y (mm).")


MAX_PANEL_PX = 16384  # a side of a projector panel: 4 x a 4K panel (2^31 filled 24 GB and was killed)


def _panel_pixels(v: tuple[int, int]) -> tuple[int, int]:
    if min(v) < 2 or max(v) > MAX_PANEL_PX:
        raise ValueError(f"pixels must be two integers [width, height], each from 2 to {MAX_PANEL_PX}")
    return v


class ProjectorPose(Model):
    center_mm: Vec3 = Field(description="World position of the projector's centre of projection (mm).")
    look: Vec3 = Field(description="Projection axis, from the projector into the scene.")
    up: Vec3 = Field(description="World direction of the panel's row 0 (top of the projected image).")

    @model_validator(mode="after")
    def _check(self) -> "ProjectorPose":
        look, up = _unit(self.look, "look"), _unit(self.up, "up")
        if abs(sum(a * b for a, b in zip(look, up))) > 0.999:
            raise ValueError("up must not be parallel to look")
        return self


class ProjectorModel(Model):
    """A structured-light projector's optics: pinhole with radial distortion (fluxcli.structured.projector);
    what ``calibrate`` writes into camera.yaml's ``projectors:`` mapping."""

    pixels: tuple[int, int] = Field(description="Panel resolution [width, height] (projector pixels).")
    focal_px: tuple[float, float] = Field(description="Focal lengths [fx, fy] (projector pixels).")
    principal_px: tuple[float, float] | None = Field(None, description="Principal point [cx, cy] (projector pixels; default the panel centre).")
    distortion: tuple[float, float] = Field((0.0, 0.0), description="Radial distortion [k1, k2] (Brown's model, dimensionless).")
    gamma: float = Field(1.0, gt=0, description="Panel response: emitted radiance = value ** gamma.")
    pose: ProjectorPose = Field(description="Where the projector is and where it points.")

    @field_validator("pixels")
    @classmethod
    def _pixels(cls, v: tuple[int, int]) -> tuple[int, int]:
        return _panel_pixels(v)

    @field_validator("focal_px")
    @classmethod
    def _focal(cls, v: tuple[float, float]) -> tuple[float, float]:
        if min(v) <= 0:
            raise ValueError("focal_px must be two positive numbers [fx, fy]")
        return v


class System(Model):
    camera: Camera = Field(description="The camera: sensor, lens, pose, apertures (or a camera.yaml path from calibrate).")
    mirrors: tuple[Mirror, ...] = Field((), description="Plane mirrors; each adds a view.")
    stage: Stage | None = Field(None, description="The stage plate (an occluder); phantoms rest on its top.")


# --------------------------------------------------------------------------- subject
MAX_PHANTOM_PIECES = 1_000_000  # elements x strips: 10^6 faces are minutes of ray tracing; 10^7 filled 6 GB


def _not_too_fine(v: int, info, other: str) -> int:
    """A field validator on a phantom's last count: its product with ``other`` is bounded."""
    n = v * info.data.get(other, 1) if isinstance(info.data.get(other), int) else v
    if n > MAX_PHANTOM_PIECES:
        raise ValueError(f"{other} x {info.field_name} = {n:.3g} pieces; at most {MAX_PHANTOM_PIECES:.0e} (no camera "
                         "resolves more, and building them would exhaust the memory)")
    return v


class CylinderPhantom(Model):
    """A closed cylinder along x resting on the stage; its side is split into elements."""

    phantom: Literal["cylinder"]
    radius_mm: float = Field(12.5, gt=0, description="Cylinder radius (mm).")
    length_mm: float = Field(50.0, gt=0, description="Cylinder length along its axis (x) (mm).")
    n_angular: int = Field(50, ge=3, description="Elements around the circumference.")
    n_axial: int = Field(32, ge=1, description="Elements along the axis.")
    cap_elements: bool = Field(False, description="Make the end caps elements too (else they only occlude).")

    @field_validator("n_axial")
    @classmethod
    def _fine(cls, v, info):
        return _not_too_fine(v, info, "n_angular")


class BoxPhantom(Model):
    """A closed box centred at the origin (its own frame), resting on the stage; each face is split
    into elements of about ``element_mm`` a side. It turns about the x axis through its centre."""

    phantom: Literal["box"]
    size_mm: tuple[PositiveFloat, PositiveFloat, PositiveFloat] = Field((30.0, 40.0, 20.0), description="Side lengths along x, y, z (mm).")
    element_mm: float = Field(2.0, gt=0, description="Target element side (mm): each face gets round(side / element_mm) elements along each side.")

    @field_validator("element_mm")
    @classmethod
    def _fine(cls, v, info):
        size = info.data.get("size_mm")
        if size is not None:
            n = 2 * sum(max(1, round(a / v)) * max(1, round(b / v)) for a, b in ((size[0], size[1]), (size[1], size[2]), (size[0], size[2])))
            if n > MAX_PHANTOM_PIECES:
                raise ValueError(f"{n:.3g} elements; at most {MAX_PHANTOM_PIECES:.0e} (no camera resolves more, and "
                                 "building them would exhaust the memory)")
        return v


class RingPhantom(Model):
    """A thin ring (the paper's 2-D study) seen by a line detector."""

    phantom: Literal["ring"]
    radius_mm: float = Field(25.0, gt=0, description="Ring radius (mm).")
    thickness_mm: float = Field(1.0, gt=0, description="Extent along the ring axis (mm).")
    n_elements: int = Field(200, ge=3, description="Elements around the ring.")
    strips_per_element: int = Field(1, ge=1, description="Sub-elements along the arc (what reconstruct.unknowns: sub_elements solves for).")

    @field_validator("strips_per_element")
    @classmethod
    def _fine(cls, v, info):
        return _not_too_fine(v, info, "n_elements")


class SpherePhantom(Model):
    """A sphere split into latitude x longitude elements."""

    phantom: Literal["sphere"]
    radius_mm: float = Field(10.0, gt=0, description="Sphere radius (mm).")
    n_latitude: int = Field(16, ge=2, description="Element rows from pole to pole.")
    n_longitude: int = Field(32, ge=3, description="Elements around each row.")

    @field_validator("n_longitude")
    @classmethod
    def _fine(cls, v, info):
        return _not_too_fine(v, info, "n_latitude")


class PatchPhantom(Model):
    """A flat rectangle of elements (one emitting side)."""

    phantom: Literal["patch"]
    size_mm: tuple[float, float] = Field((10.0, 10.0), description="Side lengths of the flat patch (mm).")
    n: tuple[int, int] = Field((1, 1), description="Elements along each side.")
    center_mm: Vec3 = Field((0.0, 0.0, 0.0), description="Patch centre (before any pose).")
    normal: Vec3 = Field((0.0, 0.0, 1.0), description="Emitting side.")

    @field_validator("n")
    @classmethod
    def _fine(cls, v, info):
        if v[0] * v[1] > MAX_PHANTOM_PIECES:
            raise ValueError(f"n = {list(v)}: {v[0] * v[1]:.3g} pieces; at most {MAX_PHANTOM_PIECES:.0e} (no camera "
                             "resolves more, and building them would exhaust the memory)")
        return v


class MeshSurface(Model):
    """A triangle mesh file; each triangle an element unless the file has a cell array (VTK) or face property (PLY) 'element' of whole-number ids (also read under the names elements, element_id, any case)."""

    mesh: Path = Field(description="Mesh file pyvista reads (PLY, STL, VTK, OBJ); relative to the config file.")
    scale_to_mm: float = Field(1.0, gt=0, description="Multiply file coordinates by this to get mm.")


class ArtefactSurface(Model):
    """A surface captured by capture-surface."""

    artefact: Path = Field(description="A surface artefact (HDF5 with /surface) from capture-surface.")


Phantom = Annotated[Union[CylinderPhantom, BoxPhantom, RingPhantom, SpherePhantom, PatchPhantom], Field(discriminator="phantom")]


class RotationAxis(Model):
    point_mm: Vec3 | None = Field(None, description="A point on the axis (default: the subject's centre).")
    direction: Vec3 = Field((1.0, 0.0, 0.0), description="Axis direction.")

    @field_validator("direction")
    @classmethod
    def _direction(cls, v: Vec3) -> Vec3:
        _unit(v, "direction")
        return v


class Poses(Model):
    heights_mm: tuple[float, ...] = Field((0.0,), min_length=1, description="Stage heights h (mm).")
    rotations_deg: tuple[float, ...] = Field((0.0,), min_length=1, description="Rotations about the subject axis (deg).")


class LambertianEmission(Model):
    """Radiance the same in every direction (p = 1/pi): the paper's model, right for a matt painted or paper surface."""

    model: Literal["lambertian"]


class DiffuseEmission(Model):
    """Light diffused through a turbid medium (tissue, a phantom) leaving through its smooth, refracting surface into air: diffusion theory with a Fresnel boundary (docs/design.md, Emission)."""

    model: Literal["diffuse"]
    refractive_index: float = Field(1.40, ge=1.0, le=3.0, description="Refractive index of the medium (tissue ~1.37-1.40; 1 = no Fresnel).")
    tangential_flux: bool = Field(True, description="Also model the tangential flux of diffusion theory: where the exitance varies along the surface the light leaves tilted away from the brighter side (acts on reconstruct.unknowns: vertices, whose exitance has a gradient; docs/design.md, Emission).")
    depth_term: bool = Field(True, description="Also model the fluence's curvature with depth (mu_eff^2 = 3 mu_a mu_s'): in an absorbing medium the light leaves more along the normal, by the factor 1 + c cos^2(theta inside), c = 3 mu_a / (mu_a + mu_s') (3 % for mu_a 0.01 /mm, 30 % for 0.1 /mm; docs/design.md, Emission: the depth term). Derived for isotropic scattering; with scattering_anisotropy g it is shortened as the delta-Eddington ray integral says (about half at g 0.9, as the photons of tissue-like scattering want at mu_a 0.3 /mm; at mu_a 0.01-0.1 /mm they want less: docs/design.md).")
    curvature_term: bool = Field(False, description="Also model how the exitance's curvature along the surface (lap_t M) bends the light it sends: over a buried source (M peaked, lap_t M < 0) more leaves along the normal and less at grazing angles, far from it the reverse; L = M p(theta) + l^2 lap_t M h(theta), l = 1 / (mu_s' + mu_a), h carrying no flux of its own, and lap_t M / M with no power-weighted mean over each region that faces one way, so a face's light as a whole keeps the profile (acts on reconstruct.unknowns: vertices and on simulate's truth; docs/design.md, Emission: the curvature term).")
    body_curvature: bool = Field(True, description="Also model how the body's own curvature bends the light: under a convex surface (a mouse's back, a cylinder) the fluence grows faster with depth and an oblique ray runs under a surface that falls away, so more light leaves along the normal and less at grazing angles (a body of radius 12 mm: +4 % head-on, -3 % at 70-80 deg), under a concave one the reverse. Each element's mean curvature comes from the turn of the mesh's normals over a few transport lengths (0 on flat faces: a box is unchanged); its light as a whole is kept; the tangential flux reaches further along a convex surface and drifts more (docs/design.md, Emission: the body's curvature).")
    reduced_scattering_per_mm: float = Field(1.0, gt=0, le=1000, description="The medium's reduced scattering coefficient mu_s' (1/mm) for the depth term and the tangential flux; default 1 /mm, the order of soft tissue and phantoms in the red / near infrared (Jacques 2013).")
    absorption_per_mm: float = Field(0.01, ge=0, le=1000, description="The medium's absorption coefficient mu_a (1/mm) for the depth term and the tangential flux; default 0.01 /mm, a phantom's or tissue's in the near infrared. Set it to the tissue's at the emission wavelength: 0.1-1 /mm for a mouse in the visible (Jacques 2013), where the profile is 30 % steeper or more.")
    scattering_anisotropy: float = Field(0.0, ge=0, lt=1, description="The medium's scattering anisotropy g (the phase function's mean cosine) for the depth term and the tangential flux: 0 for isotropic scattering (the default; most phantoms' models, and the issue's), ~0.9 for soft tissue (Jacques 2013). With mu_s' kept, forward-peaked light scatters last nearer the surface, so the tangential flux drifts less (0.92 -> 0.67 mm at g 0.9, n 1.40) and the depth term is shorter (the delta-Eddington ray integral; docs/design.md, Emission: tissue's scattering).")


class TableEmission(Model):
    """A measured or computed curve: a CSV of the angle from the normal (degrees, 0-90; or cos theta) and the relative radiance, one row per angle, e.g. with a header row 'angle_deg,radiance' or 'cos_theta,radiance' (theta_deg, theta_rad and mu are read too; without a header, a first column within 0..1 is cos theta, else degrees); commas, semicolons, tabs or spaces between columns."""

    model: Literal["table"]
    file: Path = Field(description="The CSV (relative to the config file); radiance relative, any scale.")


Emission = Annotated[Union[LambertianEmission, DiffuseEmission, TableEmission], Field(discriminator="model")]


class Subject(Model):
    surface: Union[Phantom, MeshSurface, ArtefactSurface] = Field(
        description="The subject's surface: a phantom, a mesh file, or a surface artefact (one of the variants below).")
    poses: Poses | None = Field(None, description="Heights x rotations; without it the subject stays put (height 0).")
    rotation_axis: RotationAxis | None = Field(None, description="Axis for rotations (default: the phantom's own axis).")
    emission: Emission | None = Field(None, description="How light leaves the surface (its angular profile), in every stage that models light. Absent: lambertian, with a notice; tissue and turbid phantoms are better described by {model: diffuse, refractive_index: 1.40}.")
    refine_faces: int = Field(0, ge=0, le=3, description="Split every face of the surface into four (at its edge midpoints) this many times; the elements, what is reported, stay as they are. The light within an element is modelled per face, so a spot about an element wide (a source 2-4 mm deep under elements of 2-4 mm) needs faces finer than the elements (docs/accuracy.md, Monte Carlo battery). On a round phantom (cylinder, ring, sphere) the split faces follow its round body, not its flat facets. Each level gives about 4x the vertex unknowns and build-T work.")


# --------------------------------------------------------------------------- transfer
class LensSampling(Model):
    surface_samples_per_pixel: float = Field(2.0, gt=0, description="Surface sub-samples per focal-plane pixel length.")
    max_surface_subdivisions: int = Field(48, ge=1, description="Cap on sub-triangles per face edge.")
    min_surface_subdivisions: int = Field(1, ge=1, description="Floor on sub-triangles per face edge.")
    lens_samples_min: int = Field(32, ge=1, description="Lens samples per surface point, at least.")
    lens_samples_max: int = Field(2048, ge=1, description="Lens samples per surface point, at most.")
    lens_samples_per_blur_pixel: float = Field(4.0, gt=0, description="Lens samples per pixel of blur-disk area.")
    # fewer rays for the same accuracy (issue 14): see docs/design.md, "The T kernel"
    target_column_error: float = Field(0.0, ge=0, description="Adaptive sampling: cast an element's lens samples in doubling rounds until its column's error estimate is at most this fraction of its sum (0: one round).")

    @model_validator(mode="after")
    def _ranges(self) -> "LensSampling":
        if self.lens_samples_max < self.lens_samples_min:
            raise ValueError(f"lens_samples_max ({self.lens_samples_max}) must be at least lens_samples_min "
                             f"({self.lens_samples_min})")
        if self.max_surface_subdivisions < self.min_surface_subdivisions:
            raise ValueError(f"max_surface_subdivisions ({self.max_surface_subdivisions}) must be at least "
                             f"min_surface_subdivisions ({self.min_surface_subdivisions})")
        return self


class PairwiseSampling(Model):
    surface_subdivisions: int = Field(6, ge=1, description="Sub-triangles per face edge (n^2 per face).")
    pixel_subdivisions: int = Field(3, ge=1, description="Sub-pixels per pixel side (n^2 per pixel).")


class Transfer(Model):
    estimator: Literal["lens", "pairwise"] = Field("lens", description="lens (default) or pairwise (the paper's).")
    lens: LensSampling = Field(LensSampling(), description="Sampling of the lens estimator.")
    pairwise: PairwiseSampling = Field(PairwiseSampling(), description="Sampling of the pairwise estimator.")
    ray_offset_mm: float = Field(1e-3, gt=0, description="Rays start this far along the normal (self-hit guard).")
    rays_per_batch: int = Field(100_000, ge=1000, description="Rays per chunk of whole elements, the unit of work of one thread (memory vs overhead); T does not depend on it.")
    cache_dir: Path | None = Field(None, description="Where cached T files live (default <workdir>/cache/T).")


# --------------------------------------------------------------------------- simulate
class GaussianFlux(Model):
    """A Gaussian patch of power over the element centroids."""

    kind: Literal["gaussian"]
    center_mm: Vec3 | None = Field(None, description="Centre of the patch, subject at rest (height 0, no rotation); default the top element.")
    width_mm: float = Field(5.0, gt=0, description="Standard deviation of the Gaussian over element centroids (mm).")
    peak_photons: float = Field(5e7, gt=0, description="Power of the brightest element (photons per exposure).")


class UniformFlux(Model):
    """The same exitance on every element."""

    kind: Literal["uniform"]
    exitance_photons_per_mm2: float = Field(1e5, gt=0, description="Exitance of every element (photons mm^-2 per exposure).")


class FileFlux(Model):
    """Per-element values from a file."""

    kind: Literal["file"]
    path: Path = Field(description="Per-element values in element order: .npy, or text with one value per line (a header line, # comments and blank lines are skipped).")
    quantity: Literal["power", "exitance"] = Field("power", description="power (photons) or exitance (photons/mm^2).")


class Optical(Model):
    mua_per_mm: float = Field(ge=0, le=1e3, description="Absorption coefficient mu_a (1/mm).")
    musp_per_mm: float = Field(gt=0, le=1e3, description="Reduced scattering coefficient mu_s' (1/mm).")
    refractive_index: float = Field(1.4, ge=1, description="Refractive index n (outside is air).")


class Source(Model):
    """A point or ball source of light."""

    power_photons: float = Field(gt=0, description="Source power (photons per exposure).")
    position_mm: Vec3 | None = Field(None, description="Position, subject at rest (height 0, no rotation).")
    depth_mm: float | None = Field(None, gt=0, description="Instead of position: this deep below the surface ...")
    direction: Vec3 = Field((0.0, 0.0, 1.0), description="... under the surface point hit from the subject centre along this direction.")
    radius_mm: float = Field(0.0, ge=0, description="0 for a point source, else a uniform ball.")

    @model_validator(mode="after")
    def _check(self) -> "Source":
        if (self.position_mm is None) == (self.depth_mm is None):
            raise ValueError("give exactly one of position_mm and depth_mm")
        return self


class DiffusionFlux(Model):
    """Sources inside the subject, light diffused to its surface (finite elements)."""

    kind: Literal["diffusion"]
    optical: dict[int, Optical] = Field(description="Optical properties per wavelength (nm).")
    wavelength_nm: int = Field(description="Which wavelength of 'optical' to simulate.")
    sources: tuple[Source, ...] = Field(min_length=1, description="Light sources inside the subject.")
    mesh_edge_mm: float = Field(1.5, gt=0, description="Target tetrahedron edge length (mm).")
    mesh_dir: Path | None = Field(None, description="Folder of tetrahedral meshes shipped with the config "
                                  "(fTetWild is not deterministic; a shipped mesh makes a fresh clone byte-reproducible).")
    solver: Literal["auto", "direct", "amg"] = Field("auto", description="FEM solver: direct (sparse LU), amg "
                                                     "(multigrid-preconditioned CG to a 1e-10 relative residual), or auto "
                                                     "(amg above 100 000 nodes).")

    @model_validator(mode="after")
    def _check(self) -> "DiffusionFlux":
        if self.wavelength_nm not in self.optical:
            raise ValueError(f"wavelength_nm {self.wavelength_nm} has no entry in optical ({sorted(self.optical)})")
        return self


class MonteCarloFlux(Model):
    """Photons transported by Monte Carlo (MCML-style, Fresnel at every face) through the subject: an
    analytic box or cylinder phantom, or the subject's own closed triangle mesh (a mesh file, a
    captured surface, a sphere phantom); the truth is the photons that left through each element, and
    the images are those photons traced through the lens and mirrors (no emission model is assumed)."""

    kind: Literal["montecarlo"]
    mua_per_mm: float = Field(ge=0, le=1e3, description="Absorption coefficient mu_a (1/mm).")
    mus_per_mm: float = Field(gt=0, le=1e3, description="Scattering coefficient mu_s (1/mm); mu_s' = mu_s (1 - g).")
    g: float = Field(0.0, ge=-0.99, le=0.99, description="Henyey-Greenstein anisotropy.")
    refractive_index: float = Field(1.4, ge=1, le=3, description="Refractive index n of the phantom (outside is air).")
    position_mm: Vec3 = Field(description="Isotropic point source, in the subject's own frame before it is placed on the "
                              "stage and posed: a phantom's is centred at the origin, a mesh's is its file's coordinates (in mm, after scale_to_mm).")
    radius_mm: float = Field(0.0, ge=0, description="0 for a point source, else a uniform ball of this radius.")
    n_photons: int = Field(gt=0, le=10**11, description="Photons launched (the source power, photons per exposure).")
    seed: int = Field(0, ge=0, le=2**63 - 1, description="Seed of the photon streams; the same seed gives the same photons.")
    batch_photons: int = Field(2_000_000, ge=1000, le=10**8, description="Photons transported at a time (memory); fewer in a medium where a batch would take more than 30 s, so that progress moves and Ctrl-C is heard.")
    keep_photons: bool = Field(False, description="Also store every escaping photon (exit point, direction) in the artefact; for small runs.")


Flux = Annotated[Union[GaussianFlux, UniformFlux, FileFlux, DiffusionFlux, MonteCarloFlux], Field(discriminator="kind")]


class Noise(Model):
    model: Literal["none", "gaussian", "poisson", "emccd"] = Field("poisson", description="gaussian: the paper's a + N(0, sqrt a).")
    peaks_photons: tuple[float, ...] | None = Field(None, description="Signal levels: truth scaled so its brightest element has this power.")
    repeats: int = Field(1, ge=1, description="Noisy images per level and pose.")
    seed: int = Field(0, ge=0, description="Seed; the same config gives the same bytes.")
    exposure_s: float = Field(1.0, gt=0, description="Exposure (for dark current in the EMCCD model).")

    @field_validator("peaks_photons")
    @classmethod
    def _peaks(cls, v):
        if v is not None and (len(v) == 0 or min(v) <= 0):
            raise ValueError("every signal level must be a positive number of photons")
        return v


class Export(Model):
    format: Literal["none", "tiff", "fits"] = Field("none", description="Also write images as 16-bit TIFF/float FITS files.")
    repeats: int = Field(1, ge=1, description="How many repeats per level to export.")


class Simulate(Model):
    flux: Flux = Field(description="The ground truth on the surface: kind gaussian, uniform, file, diffusion or montecarlo.")
    transfer: "Transfer | None" = Field(None, description="Sampling of the forward T (default: twice as fine as 'transfer').")
    allow_inverse_crime: bool = Field(False, description="Allow the forward T to equal reconstruction's T.")
    truth_refinement: int | None = Field(None, ge=0, le=3, description="The truth lives on the surface with each "
                                         "triangle split into 4 this many times (default 1, or 0 with "
                                         "allow_inverse_crime; 0: constant per element, half an inverse crime).")
    noise: Noise = Field(Noise(), description="Noise model, signal levels, repeats, seed and exposure of the images.")
    export: Export = Field(Export(), description="Also write the images as files.")


# --------------------------------------------------------------------------- reconstruct
Method = Literal[METHODS]  # the method registry's names (fluxcli.inverse.methods.REGISTRY)


class MethodSettings(Model):
    method: Method = Field("smooth", description=" | ".join(["smooth (default)", *(n for n in METHODS if n != "smooth")]) + ".")
    lam: float | Literal["auto"] = Field("auto", alias="lambda",
                                          description="Regularisation in the paper's relative units, or auto: lambda~ = lambda max diag(T'WT), "
                                                      "W = I for paper, W = 1/sigma^2 of the noise model for smooth (so a "
                                                      "fixed value regularises differently as the signal level changes; auto "
                                                      "picks it per image).")
    lambda_rule: Literal["gcv", "lcurve", "discrepancy"] = Field("gcv", description="How 'auto' picks lambda.")
    max_iter: int = Field(10, ge=1, description="paper: at most this many solves; smooth: this many.")
    tol: float = Field(0.01, gt=0, description="paper: stop when the fit improves by less than this fraction.")
    n_iter: int = Field(500, ge=1, description="mlem: EM iterations.")
    unknowns: Literal["auto", "elements", "sub_elements", "vertices", "linear_elements"] = Field(
        "elements", description="Solve per element; per sub-element (phantom strips, else faces) summed per element; or "
                                "per vertex (exitance linear within faces) shared out to the elements; linear_elements: one unknown "
                                "per element, exitance linear within faces (a vertex takes the mean of the elements "
                                "around it); auto: as reconstruct.unknowns.")

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False)

    @field_validator("lam")
    @classmethod
    def _lam(cls, v):
        return _check_lambda(v)


def _check_lambda(v):
    if v != "auto" and not (math.isfinite(v) and v >= 0):
        raise ValueError("lambda must be 'auto' or a finite number >= 0")
    return v


class ImageFiles(Model):
    """Image files, one per pose."""

    files: tuple[Path, ...] = Field(description="One image file per pose (TIFF/FITS/EXR), in subject.poses order.")
    units: Literal["photons", "counts"] = Field("photons", description="counts are converted with system.camera.sensor.")
    exposure_s: float = Field(1.0, gt=0, description="Exposure of the images (s); when given, results are also reported as rates "
                              "(photons/s) and radiance (photons/s/cm^2/sr).")
    calibration: Path | None = Field(None, description="calibration.h5 whose /radiometric bias, dark and flat maps are applied to counts (units: counts).")

    @model_validator(mode="after")
    def _check(self) -> "ImageFiles":
        if self.calibration is not None and self.units != "counts":
            raise ValueError("calibration (bias, dark and flat maps) applies to images in counts; set units: counts")
        return self


def _group_names(names, key: str, where: str) -> None:
    """Filter names are HDF5 group names (/filters/<name>, /truth/<name>), where '/' nests: a name
    that is no group's ('/x', 'a//b', 'x/', './x'), or one nesting another ('580' and '580/20'), is
    refused (``key``: what the message starts with, e.g. ``"filters: "``)."""
    for a in names:
        if any(part in ("", ".") for part in a.split("/")):
            raise ValueError(f"{key}{a!r} cannot name a group of {where} (a '/' at its start or end, two in a row, "
                             "or a '.' between two); rename it")
        nested = [b for b in names if b != a and b.startswith(a + "/")]
        if nested:
            raise ValueError(f"{key}{a!r} and {nested[0]!r} would nest in {where} ({nested[0]} inside {a}); "
                             "rename one")


class CaptureSource(Model):
    """The frames of a capture (capture.h5 of capture-surface)."""

    capture: Path = Field(description="A capture artefact (capture.h5 of capture-surface): relative to the config file, else to the workdir.")
    filter: str | None = Field(None, description="Whose frames to use, by filter name (default: the capture's only filter).")
    exposure_s: float | None = Field(None, gt=0, description="Which exposure time's frames (s) (default: the capture's only one).")
    filters: tuple[str, ...] | None = Field(None, min_length=1, description="Several filters, reconstructed one by one with the same T "
                                             "(the first fills /flux; each its own /filters/<name>; rois_spectrum.csv).")
    transmissions: dict[str, float] = Field(default_factory=dict, description="Filter name -> the share of the light it passes (0..1]: "
                                            "its results are divided by it (the light before the filter); default 1.")
    exposures_s: dict[str, float] = Field(default_factory=dict, description="Filter name -> which exposure time's frames (s) to use "
                                          "for that filter (default exposure_s): a dim band may need a longer exposure.")

    @model_validator(mode="after")
    def _filters(self) -> "CaptureSource":
        if self.filters is not None and self.filter is not None:
            raise ValueError("give filter (one) or filters (several), not both")
        if self.filters is not None and len(set(self.filters)) != len(self.filters):
            raise ValueError("filters: list each filter once")
        _group_names(self.filters or (), "filters: ", "reconstruction.h5")
        named = set(self.filters or ()) | ({self.filter} if self.filter else set())
        for key in ("transmissions", "exposures_s"):
            extra = sorted(set(getattr(self, key)) - named) if named else []
            if extra:
                raise ValueError(f"{key} names {', '.join(extra)}, which is not among the filters reconstructed")
        if any(not v > 0 for v in self.exposures_s.values()):
            raise ValueError("exposures_s must be positive")
        bad = {k: v for k, v in self.transmissions.items() if not 0 < v <= 1}
        if bad:
            raise ValueError(f"transmissions must lie in (0, 1]; got {bad}")
        return self


class Sweep(Model):
    methods: tuple[MethodSettings, ...] = Field(min_length=1, description="Methods compared in the study.")
    levels: tuple[int, ...] | None = Field(None, description="Signal-level indices (default all).")
    repeats: int | None = Field(None, ge=1, description="Repeats per cell (default all).")


class Reconstruct(Model):
    method: Method = Field("smooth", description="The method of /flux (see MethodSettings).")
    lam: float | Literal["auto"] = Field("auto", alias="lambda", description="Regularisation (see MethodSettings), or auto.")
    lambda_rule: Literal["gcv", "lcurve", "discrepancy"] = Field(
        "gcv", description="gcv (default): robust to model error; discrepancy over-regularises when T_fwd != T.")
    max_iter: int = Field(10, ge=1, description="paper: at most this many solves; smooth: this many.")
    tol: float = Field(0.01, gt=0, description="paper: stop when the fit improves by less than this fraction.")
    n_iter: int = Field(500, ge=1, description="mlem: EM iterations.")
    unknowns: Literal["auto", "elements", "sub_elements", "vertices", "linear_elements"] = Field(
        "auto", description="auto (default): smooth solves for the exitance at the vertices (linear within each face, "
                            "continuous; T from the once-refined surface), shared out to the elements, when there are at "
                            "most 2500 vertices; beyond, one unknown per element with the exitance still linear within "
                            "faces (linear_elements) when there are at most 6000 elements; else (and for the other "
                            "methods) per element. elements, sub_elements "
                            "(phantom strips, else faces), vertices or linear_elements (one unknown per element, exitance "
                            "linear within faces: a vertex takes the mean of the elements around it) to choose.")
    images: ImageFiles | CaptureSource | None = Field(None, description="Images from files, or from a capture, instead of simulation.h5.")
    level: int = Field(0, ge=0, description="Which signal level of the simulation to reconstruct.")
    repeat: int = Field(0, ge=0, description="Which noise repeat of the simulation to reconstruct.")
    noiseless: bool = Field(False, description="Reconstruct the simulation's noiseless images.")
    joint: bool = Field(True, description="Also reconstruct all poses jointly onto one surface.")
    calibration_budget: bool = Field(True, description="With system.camera.uncertainty (or mirrors' sigma): rebuild T once per calibrated parameter moved by +1 sd and re-solve at the same lambda, to give every total its calibration sigma (one T build per parameter and pose; false skips it).")
    read_noise_photons: float = Field(0.0, ge=0, description="Added to the shot-noise variance in weights (photons rms).")
    noise: Literal["auto", "gaussian", "poisson", "emccd"] = Field(
        "auto", description="Noise model of the images for weights, sigma and chi^2 (auto: the simulation's; emccd for "
                            "count images, with system.camera.sensor; poisson otherwise).")
    sweep: Sweep | None = Field(None, description="A study: every level x repeat x pose for each method.")

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False)

    @field_validator("lam")
    @classmethod
    def _lam(cls, v):
        return _check_lambda(v)

    def settings(self) -> MethodSettings:
        return MethodSettings(method=self.method, lam=self.lam, lambda_rule=self.lambda_rule,
                              max_iter=self.max_iter, tol=self.tol, n_iter=self.n_iter, unknowns=self.unknowns)


# --------------------------------------------------------------------------- report
class ReportSettings(Model):
    title: str | None = Field(None, description="Page title (default: the config's name).")
    slice_axial_mm: float = Field(0.0, description="Where along the subject's axis (from its centre) to cut the circumference slice (mm).")
    surface_views: bool = Field(True, description="Render the flux on the 3-D surface (pyvista, off-screen).")


# --------------------------------------------------------------------------- calibrate: radiometric
def _distinct(files: tuple[Path, ...]) -> tuple[Path, ...]:
    if len(set(files)) != len(files):
        raise ValueError("a file is listed twice: paired frames must be two different exposures")
    return files


class RadiometricPTCLevel(Model):
    files: tuple[Path, ...] = Field(min_length=2, description="Two or more frames at one illumination and exposure (counts); consecutive frames are paired (1st-2nd, 3rd-4th, ...).")
    exposure_s: float = Field(gt=0, description="Exposure of these frames (s).")
    em_gain_on: bool = Field(False, description="EM gain on (the working gain) or off (gain set to 1 in EM mode: same output amplifier, no multiplication).")
    illumination: str = Field("", description="Label of the light-source setting: gain-on and gain-off levels with the same label are compared per second of exposure to measure the EM gain.")

    @field_validator("files")
    @classmethod
    def _files(cls, v: tuple[Path, ...]) -> tuple[Path, ...]:
        return _distinct(v)


class RadiometricDarks(Model):
    files: tuple[Path, ...] = Field(min_length=1, description="Dark frames (no light) at one exposure (counts).")
    exposure_s: float = Field(gt=0, description="Exposure of these frames (s).")
    em_gain_on: bool = Field(True, description="Whether the EM gain was on (then converted with the measured gain).")


class Radiometric(Model):
    directory: Path | None = Field(None, description="Folder the frame file names below are relative to (itself relative to the config file); default the config's folder.")
    bias: tuple[Path, ...] = Field(min_length=2, description="Bias frames: no light, shortest exposure, EM gain off (counts); consecutive pairs give the read noise.")
    ptc: tuple[RadiometricPTCLevel, ...] = Field(min_length=2, description="Photon-transfer series: at least two gain-off levels (electrons per count); gain-on levels give the EM gain.")
    darks: tuple[RadiometricDarks, ...] = Field((), description="Dark frames per exposure; two or more exposures separate dark current from clock-induced charge.")
    flats: tuple[Path, ...] = Field((), description="Flat frames of the evenly lit bare sensor, EM gain off (counts): the pixel-response map.")
    saturation_counts: float = Field(65535.0, gt=0, description="Saturation level (counts): such pixels are left out of the PTC, and a pair with over 1 % of them is dropped.")
    excess_noise_factor_squared: float | None = Field(None, ge=1, le=2, description="F^2 of the EM register assumed for the gain-on PTC slope; left out: an ideal register's 2 - 1/G, solved with the gain G.")
    gain_tolerance: float = Field(0.1, gt=0, description="Warn when the ratio and PTC EM gains differ by more than this fraction.")

    @field_validator("bias")
    @classmethod
    def _bias(cls, v: tuple[Path, ...]) -> tuple[Path, ...]:
        return _distinct(v)

    @model_validator(mode="after")
    def _check(self) -> "Radiometric":
        if len([lv for lv in self.ptc if not lv.em_gain_on]) < 2:
            raise ValueError("ptc needs at least two levels with em_gain_on: false (the gain-off curve gives electrons per count)")
        if any(d.em_gain_on for d in self.darks) and not any(lv.em_gain_on for lv in self.ptc):
            raise ValueError("darks taken with em_gain_on need ptc levels with em_gain_on: true to measure the EM gain")
        return self


# --------------------------------------------------------------------------- calibrate: geometric
class CalibrationGrid(Model):
    kind: Literal["dots", "checkerboard"] = Field("dots", description="dots (a regular dot grid) or checkerboard (its inner corners are the points).")
    pitch_mm: float = Field(gt=0, description="Distance between neighbouring grid points (mm).")
    shape: tuple[int, int] = Field(description="Points along x and along y [nx, ny] (checkerboard: inner corners).")

    @field_validator("shape")
    @classmethod
    def _shape(cls, v: tuple[int, int]) -> tuple[int, int]:
        if min(v) < 2:
            raise ValueError("shape must be two integers [nx, ny], each 2 or more")
        return v


class CalibrationImage(Model):
    file: Path = Field(description="Image of the grid lying flat (TIFF/FITS/EXR; counts or photons), relative to the config.")
    plane_z_mm: float = Field(description="World z of the grid plane in this image (mm); the world frame is the grid's. On a stage: system.stage.top_z_mm + the stage height + the grid's thickness (calibrate.capture computes it so).")


# --------------------------------------------------------------------------- calibrate: projectors
class ProjectorPatternSettings(Model):
    period_px: int = Field(16, ge=4, le=MAX_PANEL_PX, multiple_of=4, description="Fringe period of the phase-shift frames (projector pixels; a multiple of 4).")
    n_steps: int = Field(8, ge=3, le=64, description="Phase steps per code.")


class ProjectorFrames(Model):
    plane_z_mm: float = Field(description="World z of the flat board (the grid's plane) in these frames (mm).")
    columns: tuple[Path, ...] | str = Field(description="Camera frames while the column code was shown, in the pattern order (white, black, Gray bits and inverses, phase steps): a list of files or one glob pattern (sorted).")
    rows: tuple[Path, ...] | str = Field(description="The same for the row code (the column code turned by 90 degrees).")


class SimulatedProjectorFrames(Model):
    """Frames made by the simulated rig (the demo and tests): a flat matte board at each height."""

    camera: Camera = Field(description="The true camera that renders the frames (or the path of a YAML file with a camera: block).")
    projector: ProjectorModel = Field(description="The true projector (the fit never sees it; its error is reported).")
    heights_mm: tuple[float, ...] = Field(min_length=2, description="Board heights (mm).")
    board_size_mm: tuple[float, float] = Field((160.0, 160.0), description="Board extent along x and y, centred on the axis (mm).")
    albedo: float = Field(0.8, gt=0, le=1, description="Board reflectance.")
    photons_white: float = Field(3000.0, gt=0, description="Photons per pixel (99th percentile) under the white frame.")
    ambient_photons: float = Field(20.0, ge=0, description="Stray light per pixel per frame (photons).")
    em_gain: float = Field(10.0, ge=1, description="EM gain of the frames (camera.sensor gives the rest of the EMCCD).")
    exposure_s: float = Field(0.1, gt=0, description="Exposure of each frame (s; dark current).")
    lens_samples: int = Field(4, ge=1, description="Lens samples per sub-pixel (camera blur).")
    seed: int = Field(0, ge=0, description="Noise seed.")


class ProjectorCalibration(Model):
    name: str | None = Field(None, description="Name (default projector0, ...): its key in camera.yaml's projectors mapping (rig.projectors).")
    pixels: tuple[int, int] = Field(description="Panel resolution [width, height] (pixels).")
    patterns: ProjectorPatternSettings = Field(ProjectorPatternSettings(), description="The Gray code + phase-shift sequence that was shown.")
    images: tuple[ProjectorFrames, ...] = Field((), description="Frames of the board at two or more known heights.")
    simulated: SimulatedProjectorFrames | None = Field(None, description="Instead of images: frames made by the simulated rig (written to <workdir>/projector_frames/).")
    min_contrast_fraction: float = Field(0.1, gt=0, lt=1, description="Shadow mask: white - black above this fraction of its 99th percentile.")
    half_window_px: int = Field(6, ge=2, description="Local homography window: (2 h + 1)^2 camera pixels around each grid point.")
    gamma: float | None = Field(None, gt=0, description="The panel's gamma if known; none: measured from the phase frames' mean.")

    @field_validator("pixels")
    @classmethod
    def _pixels(cls, v: tuple[int, int]) -> tuple[int, int]:
        return _panel_pixels(v)

    @model_validator(mode="after")
    def _check(self) -> "ProjectorCalibration":
        if (len(self.images) == 0) == (self.simulated is None):
            raise ValueError("give either images (frames of the board at two or more heights) or simulated")
        if self.simulated is None and len({im.plane_z_mm for im in self.images}) < 2:
            raise ValueError("give frames at two or more distinct heights (one plane cannot fix a projector)")
        if self.simulated is not None and tuple(self.simulated.projector.pixels) != tuple(self.pixels):
            raise ValueError("simulated.projector.pixels must equal pixels")
        return self


class Calibrate(Model):
    grid: CalibrationGrid | None = Field(None, description="The target: world point (i, j) at ((i-(nx-1)/2) pitch, (j-(ny-1)/2) pitch, plane_z_mm).")
    images: tuple[CalibrationImage, ...] = Field((), description="The grid at five or more known heights through and around focus.")
    refine_mirrors: bool = Field(True, description="Refine the planes of system.mirrors from the grid seen in each mirror.")
    radiometric: Radiometric | None = Field(None, description="Bias, dark, flat and photon-transfer frames: the sensor block.")
    projectors: tuple[ProjectorCalibration, ...] = Field((), description="Structured-light projectors to calibrate against the calibrated camera (needs grid and images); written to camera.yaml's projectors mapping.")
    capture: Path | None = Field(None, description="A capture.h5 holding calibration frames (capture.calibration): the grid frames with their stage heights and the bias, dark, flat and photon-transfer frames, used instead of images and radiometric.")

    @model_validator(mode="after")
    def _check(self) -> "Calibrate":
        if self.capture is not None:
            if self.images or self.radiometric is not None:
                raise ValueError("capture: the frames come from the capture file; leave images and radiometric out")
            if self.projectors:
                raise ValueError("capture: projectors are calibrated from frame files (images); not with capture")
            return self
        if (self.grid is None) != (len(self.images) == 0):
            raise ValueError("give both grid and images (geometric calibration), or neither")
        if self.grid is None and self.radiometric is None:
            raise ValueError("give grid and images (geometric), radiometric, capture, or more than one")
        if self.projectors and self.grid is None:
            raise ValueError("projectors are calibrated against the camera the grid images give: add grid and images")
        return self


# --------------------------------------------------------------------------- rig (issue 11)
class RigFault(Model):
    kind: Literal["no_reply", "late_reply", "garbage", "drop", "error_reply", "stall", "wrong_position"] = Field(
        description="What the simulated device does wrong.")
    on: str = Field("*", description="Which command: '*', an FW102C command prefix ('pos=') or an APT message ('MOT_MOVE_ABSOLUTE', '0x0453').")
    count: int = Field(1, ge=0, description="How many times it happens (0: every time).")
    after: int = Field(0, ge=0, description="Let this many matching commands through first.")
    delay_s: float = Field(0.0, ge=0, description="late_reply: how late (s); stall: how long it hangs (0: for ever).")
    offset: float = Field(1.0, description="wrong_position: how far off (wheel positions, or mm for the stage).")


class RigFilterWheel(Model):
    port: str = Field(description="Serial port or pyserial URL (/dev/ttyUSB0, socket://HOST:PORT); 'pty' or 'socket://127.0.0.1:0' for a simulator.")
    positions: Literal[6, 12] = Field(6, description="Number of wheel positions (the wheel's pcount).")
    filters: dict[str, int] = Field(default_factory=dict, description="Filter name -> wheel position (1..positions).")
    timeout_s: float = Field(2.0, gt=0, description="Bound on a reply that is not a move (s).")
    faults: tuple[RigFault, ...] = Field((), description="Faults the simulator injects (tests, rehearsals).")

    @model_validator(mode="after")
    def _check(self) -> "RigFilterWheel":
        for name, pos in self.filters.items():
            if not 1 <= pos <= self.positions:
                raise ValueError(f"filter {name!r} is at position {pos}, outside 1..{self.positions}")
        return self


class RigStage(Model):
    port: str = Field(description="Serial port or pyserial URL; 'pty' or 'socket://127.0.0.1:0' for a simulator.")
    counts_per_mm: float = Field(gt=0, description="Controller microsteps per mm (unverified for the L490MZ: 134737 or 2155789).")
    travel_mm: tuple[float, float] = Field((0.0, 50.0), description="Allowed heights [low, high] (mm); moves outside are refused.")
    velocity_mm_s: float = Field(0.5, gt=0, le=1.1, description="Move velocity set at connect (mm/s).")
    acceleration_mm_s2: float = Field(0.5, gt=0, description="Move acceleration set at connect (mm/s^2).")
    velocity_scale: float = Field(53.68, gt=0, description="Device velocity units per microstep/s (unverified; Trinamic 53.68).")
    acceleration_scale: float = Field(1 / 90.9, gt=0, description="Device acceleration units per microstep/s^2 (unverified; Trinamic 1/90.9).")
    channel: int = Field(1, ge=1, description="Motor channel.")
    timeout_s: float = Field(2.0, gt=0, description="Bound on a reply that is not a move (s).")
    faults: tuple[RigFault, ...] = Field((), description="Faults the simulator injects (tests, rehearsals).")

    @field_validator("travel_mm")
    @classmethod
    def _travel(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] >= v[1]:
            raise ValueError("travel_mm must be [low, high] with low < high")
        return v

    @model_validator(mode="after")
    def _fits_the_wire(self) -> "RigStage":
        """APT carries positions, velocities and accelerations as signed 32-bit device units."""
        top = 2**31 - 1
        for what, units, keys in (
                ("travel_mm's far end", max(abs(t) for t in self.travel_mm) * self.counts_per_mm,
                 "travel_mm x counts_per_mm"),
                ("velocity_mm_s", self.velocity_mm_s * self.counts_per_mm * self.velocity_scale,
                 "velocity_mm_s x counts_per_mm x velocity_scale"),
                ("acceleration_mm_s2", self.acceleration_mm_s2 * self.counts_per_mm * self.acceleration_scale,
                 "acceleration_mm_s2 x counts_per_mm x acceleration_scale")):
            if units > top:
                raise ValueError(f"{what} is {units:.4g} device units ({keys}), beyond the 2^31 - 1 the APT "
                                 "protocol carries (a signed 32-bit count); check counts_per_mm and the key's unit")
        return self


class FilterLight(Model):
    wavelength_nm: int | None = Field(None, description="Simulated camera: the wavelength whose simulate.flux.optical properties apply behind this filter (diffusion truths; default simulate's own).")
    transmission: float = Field(1.0, ge=0, le=1, description="Simulated camera: fraction of the emission the filter passes.")


class RigCamera(Model):
    backend: Literal["simulated", "dcam", "andor_sdk2", "andor_sdk3", "pvcam"] = Field("simulated", description="simulated (default); a real camera: dcam (Hamamatsu, vendor's DCAM-SDK4 wrapper), andor_sdk2 (iXon EMCCDs), andor_sdk3 (Andor sCMOS) or pvcam (Teledyne Photometrics), the last three through pylablib (pip install 'fluxmap[cameras]').")
    binning: int = Field(1, ge=1, description="Binning set on the camera; system.camera.pixels/pixel_pitch_mm describe the binned image (the ImagEM: 4).")
    filters: dict[str, FilterLight] = Field(default_factory=dict, description="Simulated camera: what reaches the sensor behind each filter (by name); unlisted filters pass simulate's truth unchanged.")
    setpoint_c: float = Field(-65.0, description="Sensor temperature with the cooler on (deg C); dark_current_e_per_s holds there.")
    ambient_c: float = Field(20.0, description="Simulated camera: sensor temperature with the cooler off (deg C).")
    dark_doubling_c: float = Field(6.3, gt=0, description="Simulated camera: dark current doubles per this many deg C.")
    em_gain_range: tuple[float, float] = Field((1.0, 1200.0), description="EM gains the camera accepts [low, high] (unverified: x4-x1200 for the ImagEM).")
    device_index: int = Field(0, ge=0, description="A real camera: which one of its vendor library's list (0 = first).")
    serial: str | None = Field(None, min_length=1, description="andor_sdk2, andor_sdk3, pvcam: the serial number the camera must report (with several cameras, the one chosen); another camera is refused.")
    em_gain_advanced: bool = Field(False, description="andor_sdk2: allow EM gains above 300 (Andor's advanced mode; strong light can then damage the sensor).")
    fan: Literal["full", "low", "off"] = Field("full", description="andor_sdk2: the head's fan (off only with liquid cooling).")
    linux_sdk: bool = Field(False, description="andor_sdk2, andor_sdk3, pvcam on Linux: let pylablib load the vendor's Linux library (it refuses non-Windows libraries unless told).")
    shutter_property: str | None = Field(None, description="dcam: name of the DCAM property that closes a shutter for dark frames (unverified; none: darks refused).")
    true_surface: Union[Phantom, MeshSurface] | None = Field(None, description="Simulated camera: the subject's true surface it renders (emission and projected patterns), when subject.surface is the one capture-surface measures (default subject.surface).")
    subject_albedo: float = Field(0.8, gt=0, le=1, description="Simulated camera: Lambertian reflectance of the subject under the projectors.")
    stage_albedo: float = Field(0.5, ge=0, le=1, description="Simulated camera: Lambertian reflectance of the stage top under the projectors.")


class RigProjector(ProjectorModel):
    """A projector showing structured-light patterns: its pinhole-plus-radial-distortion model
    (ProjectorModel's keys, e.g. from calibrate's camera.yaml) and its display."""

    display: Literal["simulated", "window"] = Field("simulated", description="simulated (an image sink the simulated camera renders) or window (a full-screen window on a monitor: the lab; needs pyglet: pip install 'fluxmap[projector]').")
    screen: int = Field(1, ge=0, description="window: which monitor the projector is (0 = primary).")
    settle_s: float = Field(0.1, ge=0, description="window: wait after a pattern is shown before the camera exposes (s).")
    intensity_photons_per_s_per_sr: float = Field(1e12, gt=0, description="Simulated projector: photons per second per steradian on its axis at full white, as the camera sees them through the pattern frames' filter.")


class Rig(Model):
    time_scale: float = Field(1.0, gt=0, le=100, description="Simulated device timing x this (tests use less; at most 100, when a move already takes minutes); drivers scale their move timeouts by it.")
    filter_wheel: RigFilterWheel | None = Field(None, description="The FW102C filter wheel.")
    stage: RigStage | None = Field(None, description="The L490MZ lab jack (APT).")
    camera: RigCamera | None = Field(None, description="The EMCCD.")
    projectors: dict[str, RigProjector] = Field(default_factory=dict, description="Structured-light projectors by name (capture.surface); or a camera.yaml path (its projectors mapping, from calibrate), or {file: PATH, <name>: {overrides}}.")


# --------------------------------------------------------------------------- capture (acquisition)
class SurfacePatterns(Model):
    period_px: int = Field(16, ge=4, le=MAX_PANEL_PX, multiple_of=4, description="Fringe period of the phase-shift patterns (projector pixels, a multiple of 4).")
    n_steps: int = Field(8, ge=3, le=64, description="Phase steps (8 leaves a gamma-2.2 phase error below 1e-3 period).")


class SurfaceMesh(Model):
    element_size_mm: float = Field(4.0, gt=0, description="Target size of an element of the captured surface (mm).")
    face_size_mm: float = Field(1.0, gt=0, description="Target edge length of its triangles (mm).")
    voxel_mm: float = Field(0.8, gt=0, description="Grid step the implicit surface is contoured on (mm).")
    centre_spacing_mm: float = Field(2.5, gt=0, description="Points are thinned to one per cube of this side as RBF centres (mm).")


class CaptureSurface(Model):
    """Structured light: each projector shows the Gray-code + phase-shift sequence, one camera frame per pattern."""

    projectors: tuple[str, ...] | None = Field(None, description="Projectors (keys of rig.projectors), in this order (default: all).")
    height_mm: float = Field(0.0, description="Stage height of the pattern frames (mm); the surface is stored at rest (as at height 0).")
    filter: str = Field("open", description="Filter in the beam for the pattern frames (a key of rig.filter_wheel.filters).")
    exposure_s: float = Field(0.01, gt=0, description="Exposure of a pattern frame (s).")
    em_gain: float = Field(10.0, ge=1, description="EM gain of the pattern frames.")
    binning: int | None = Field(None, ge=1, description="Camera binning of the pattern frames (default rig.camera.binning); must divide rig.camera.binning (finer frames: more points).")
    patterns: SurfacePatterns = Field(SurfacePatterns(), description="The pattern sequence.")
    min_contrast_photons: float = Field(200.0, gt=0, description="A pixel is lit when white - black exceeds this (photons): the shadow mask.")
    min_modulation_fraction: float = Field(0.25, gt=0, lt=1, description="The fringes' amplitude must reach this fraction of (white - black)/2: the low-modulation mask.")
    mesh: SurfaceMesh = Field(SurfaceMesh(), description="From points to the closed surface.")


class CalibrationGridCapture(CalibrationGrid):
    """The calibration grid lying flat on the stage, one series of frames per stage height (the
    grid's kind, pitch_mm and shape as calibrate.grid's, checked alike)."""

    thickness_mm: float = Field(0.0, ge=0, description="Height of the printed grid surface above the stage top (mm): the grid plane is at z = system.stage.top_z_mm + stage height + thickness_mm.")
    heights_mm: tuple[float, ...] = Field(min_length=3, description="Stage heights (mm), five or more through and around focus; each frame records the height read back from the stage.")
    exposure_s: float = Field(0.1, gt=0, description="Exposure of a grid frame (s).")
    em_gain: float = Field(10.0, ge=1, description="EM gain of the grid frames.")
    repeats: int = Field(1, ge=1, description="Frames per height (averaged by calibrate).")
    filter: str = Field("open", description="Filter in the beam (a key of rig.filter_wheel.filters).")
    dot_diameter_mm: float | None = Field(None, gt=0, description="Simulated camera: diameter of a printed dot (mm; default pitch_mm / 2).")

    @field_validator("heights_mm")
    @classmethod
    def _heights(cls, v):
        if len(set(v)) != len(v):
            raise ValueError("list each stage height once (use repeats for more frames)")
        return v


class CalibrationSeries(Model):
    frames: int = Field(4, ge=2, description="Frames in the series (consecutive frames are paired for temporal variances).")
    exposure_s: float = Field(0.001, gt=0, description="Exposure of each frame (s).")


class CalibrationDarkSeries(Model):
    frames: int = Field(2, ge=1, description="Dark frames at each exposure.")
    exposures_s: tuple[float, ...] = Field((30.0, 120.0), min_length=1, description="Exposures (s); two or more separate dark current from clock-induced charge.")
    em_gain: float = Field(300.0, ge=1, description="EM gain of the dark frames (the working gain; the PTC's gain-on levels measure it).")


class CalibrationPTC(Model):
    """Photon-transfer pairs of one steady, even light at several exposures, EM gain off (gain 1) and on."""

    exposures_off_s: tuple[float, ...] = Field(min_length=2, description="Exposures of the gain-off pairs (s): signals from a few hundred counts to about half of full scale.")
    exposures_on_s: tuple[float, ...] = Field((), description="Exposures of the gain-on pairs (s): the same light, short enough not to saturate at em_gain.")
    em_gain: float = Field(300.0, ge=1, description="EM gain of the gain-on pairs.")
    pairs: int = Field(1, ge=1, description="Pairs of frames per exposure.")


class CalibrationSimulated(Model):
    """What the simulated rig shows for the calibration frames (ignored by a real camera)."""

    grid_photons_per_s: float = Field(2000.0, gt=0, description="Photons per pixel per second inside an in-focus dot on the axis (a dot grid: the dots bright).")
    background_fraction: float = Field(0.05, ge=0, lt=1, description="Brightness of the grid's background relative to a dot.")
    light_photons_per_s: float = Field(1.0e5, gt=0, description="Photons per pixel per second of the even light (flats and PTC).")
    sub: int = Field(2, ge=1, le=6, description="Sub-pixels per pixel side when rendering the grid.")
    lens_samples: int = Field(32, ge=4, description="Lens points per sub-pixel when rendering the grid (defocus blur).")


class CaptureCalibration(Model):
    """Calibration frames for ``fluxmap calibrate`` (``calibrate.capture``), taken before anything else."""

    grid: CalibrationGridCapture | None = Field(None, description="The grid at listed stage heights (geometric calibration).")
    bias: CalibrationSeries | None = Field(None, description="Bias frames: shutter closed, EM gain off, shortest exposure.")
    darks: CalibrationDarkSeries | None = Field(None, description="Dark frames: shutter closed, EM gain on, at each exposure.")
    flats: CalibrationSeries | None = Field(None, description="Flat frames: the even light, EM gain off.")
    ptc: CalibrationPTC | None = Field(None, description="Photon-transfer pairs (the even light).")
    filter: str = Field("open", description="Filter in the beam for the flat and PTC frames (a key of rig.filter_wheel.filters).")
    confirm: bool = Field(True, description="Real camera: wait for Enter before each set-up the operator makes (grid on the stage, even light on); false: no wait (tests, motorised set-ups).")
    simulated: CalibrationSimulated = Field(CalibrationSimulated(), description="Simulated camera: the brightness of the grid and of the even light.")

    @model_validator(mode="after")
    def _check(self) -> "CaptureCalibration":
        if not any((self.grid, self.bias, self.darks, self.flats, self.ptc)):
            raise ValueError("give one or more of grid, bias, darks, flats, ptc")
        if (self.bias is None) != (self.ptc is None):
            raise ValueError("the radiometric calibration needs both bias and ptc (give both, or neither)")
        if self.darks is not None and self.ptc is not None and not self.ptc.exposures_on_s:
            raise ValueError("darks taken with the EM gain on need ptc.exposures_on_s to measure that gain")
        return self


class Capture(Model):
    """The acquisition plan of ``fluxmap capture-surface``: calibration frames (``calibration``) first, then pattern frames (``surface``), then darks, then per height, per filter, repeats."""

    heights_mm: tuple[float, ...] = Field((), description="Stage heights to image the subject at (mm), in this order (none: a calibration-only capture).")
    filters: tuple[str, ...] = Field(("open",), min_length=1, description="Filter names (keys of rig.filter_wheel.filters), in this order.")
    exposure_s: float | tuple[float, ...] = Field(1.0, description="Exposure time (s), or several: each height and filter is taken at each.")
    em_gain: float = Field(300.0, ge=1, description="EM gain of every frame.")
    repeats: int = Field(1, ge=1, description="Frames per height and filter.")
    darks: int = Field(4, ge=0, description="Dark frames (shutter closed, same exposure and gain), taken first.")
    seed: int = Field(0, ge=0, description="Simulated camera: frame k's noise comes from the seed (seed, k).")
    surface: CaptureSurface | None = Field(None, description="Structured-light pattern frames, decoded into <workdir>/surface.h5.")
    calibration: CaptureCalibration | None = Field(None, description="Calibration frames (grid at stage heights, bias, darks, flats, photon transfer) for calibrate.capture.")

    @model_validator(mode="after")
    def _something(self) -> "Capture":
        if not self.heights_mm and self.calibration is None:
            raise ValueError("heights_mm: give one or more stage heights (or a calibration-only capture: calibration)")
        if not self.heights_mm and self.surface is not None:
            raise ValueError("capture.surface images the subject: give heights_mm too")
        return self

    @field_validator("heights_mm", "filters")
    @classmethod
    def _distinct(cls, v, info):
        if len(set(v)) != len(v):
            raise ValueError("list the same value only once (use repeats for more frames)")
        if info.field_name == "filters":
            _group_names(v, "", "capture.h5")
        return v

    @field_validator("exposure_s")
    @classmethod
    def _exposures(cls, v):
        many = v if isinstance(v, tuple) else (v,)
        if not many or min(many) <= 0 or len(set(many)) != len(many):
            raise ValueError("give one or more distinct positive exposure times (s)")
        return v

    @property
    def exposures_s(self) -> tuple[float, ...]:
        return tuple(self.exposure_s) if isinstance(self.exposure_s, tuple) else (float(self.exposure_s),)


# --------------------------------------------------------------------------- regions of interest
_ROI_KEYS = {"sphere": ("center_mm", "radius_mm"), "disc": ("center_mm", "radius_mm"), "box": ("min_mm", "max_mm"),
             "threshold": ("fraction",), "cell_array": ("array", "value"), "elements": ("ids",)}


class Roi(Model):
    """A region of interest on the surface, in the subject's own frame (at rest, before any pose)."""

    name: str = Field(min_length=1, description="What the region is called in tables, files and plots.")
    kind: Literal["sphere", "disc", "box", "threshold", "cell_array", "elements"] = Field(
        description="sphere | disc (geodesic, around the surface point nearest center_mm) | box | threshold "
                    "(a fraction of the peak, connected to it) | cell_array (an integer cell array of the mesh) | "
                    "elements (a list).")
    center_mm: Vec3 | None = Field(None, description="sphere, disc: the centre (mm, subject at rest).")
    radius_mm: float | None = Field(None, gt=0, description="sphere: the radius; disc: the geodesic radius over the surface (mm).")
    min_mm: Vec3 | None = Field(None, description="box: the lower corner (mm, subject at rest).")
    max_mm: Vec3 | None = Field(None, description="box: the upper corner (mm).")
    fraction: float | None = Field(None, gt=0, le=1, description="threshold: elements at or above this fraction of the peak exitance.")
    array: str | None = Field(None, min_length=1, description="cell_array: a cell array of the mesh file holding a whole number per face, integer or floating point (e.g. region).")
    value: int | None = Field(None, description="cell_array: the value whose elements form the region.")
    ids: tuple[int, ...] | None = Field(None, min_length=1, description="elements: element ids (the mesh file's, else indices from 0).")

    @model_validator(mode="after")
    def _keys_of_kind(self) -> "Roi":
        need = _ROI_KEYS[self.kind]
        missing = [k for k in need if getattr(self, k) is None]
        extra = [k for ks in _ROI_KEYS.values() for k in ks
                 if k not in need and k in self.model_fields_set and getattr(self, k) is not None]
        if missing:
            raise ValueError(f"a {self.kind} ROI needs {', '.join(need)}; missing {', '.join(missing)}")
        if extra:
            raise ValueError(f"a {self.kind} ROI takes {', '.join(need)}, not {', '.join(sorted(set(extra)))}")
        if self.kind == "box" and any(lo >= hi for lo, hi in zip(self.min_mm, self.max_mm)):
            raise ValueError("box: min_mm must be below max_mm on every axis")
        return self


def _distinct_rois(v: tuple[Roi, ...]) -> tuple[Roi, ...]:
    names = [r.name for r in v]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"ROI names must be distinct; {', '.join(dup)} is given more than once")
    if any(n == "joint" or "," in n or "\n" in n for n in names):
        raise ValueError("an ROI name may not be 'joint' nor hold commas or line breaks (rois.csv)")
    return v


# --------------------------------------------------------------------------- top level
class Config(Model):
    workdir: Path | None = Field(None, description="Output folder (default runs/<config name>), relative to the config file.")
    # Optional at schema level: each stage states what it needs (fluxcli.cli.STAGE_REQUIRES), so
    # `calibrate` runs without a lens or subject and `rig serve` with only `rig`.
    system: System | None = Field(None, description="The imaging system: camera, mirrors, stage.")
    subject: Subject | None = Field(None, description="What is imaged: its surface, poses and rotation axis.")
    transfer: Transfer = Field(Transfer(), description="How the transfer matrix T is estimated and where it is cached.")
    # Sections of stages that validate their own keys when they are built.
    simulate: Simulate | None = Field(None, description="Ground truth and images for 'fluxmap simulate'.")
    reconstruct: Reconstruct = Field(Reconstruct(), description="Settings of 'fluxmap reconstruct'.")
    report: ReportSettings = Field(ReportSettings(), description="Settings of 'fluxmap report'.")
    calibrate: Calibrate | None = Field(None, description="Settings of 'fluxmap calibrate': grid images, radiometric frames.")
    capture: Capture | None = Field(None, description="The acquisition plan of capture-surface.")
    rig: Rig | None = Field(None, description="The devices of the rig (issue 11).")
    rois: tuple[Roi, ...] = Field((), description="Regions of interest on the surface (issue 24): their totals per pose and "
                                                  "jointly, in reconstruction.h5, rois.csv, summary.json and the report.")

    @field_validator("rois")
    @classmethod
    def _rois(cls, v):
        return _distinct_rois(v)


@dataclass(frozen=True)
class PathResolver:
    """Turns a path the config gives into the file it means: as given when absolute, else beside
    the config file. What a plan hands on instead of the config itself."""

    base_dir: Path  # the config file's folder

    def __call__(self, p: Path | str) -> Path:
        p = Path(p)
        return p if p.is_absolute() else (self.base_dir / p).resolve()


class LoadedConfig:
    """A validated config with where it came from."""

    def __init__(self, model: Config, path: Path, raw: dict[str, Any]):
        self.model = model
        self.path = path
        self.raw = raw

    @property
    def base_dir(self) -> Path:
        return self.path.parent

    @property
    def resolver(self) -> PathResolver:
        """:meth:`resolve` without the config: what plans hand on."""
        return PathResolver(self.base_dir)

    def resolve(self, p: Path | str) -> Path:
        return self.resolver(p)

    @property
    def workdir(self) -> Path:
        w = self.model.workdir or Path("runs") / self.path.stem
        return self.resolve(w)

    @property
    def captured_surface_path(self) -> Path | None:
        """``<workdir>/surface.h5`` when ``capture.surface`` makes it, else None."""
        cap = self.model.capture
        return self.workdir / "surface.h5" if cap is not None and cap.surface is not None else None

    def images_capture_path(self) -> Path:
        """``reconstruct.images.capture``, resolved: beside the config, else in the workdir."""
        p = self.model.reconstruct.images.capture
        first = self.resolve(p)
        return first if first.is_file() or p.is_absolute() else self.workdir / p

    @property
    def sha256(self) -> str:
        return hashlib.sha256(yaml.safe_dump(self.raw, sort_keys=True).encode()).hexdigest()


def _yaml_problem(e: yaml.YAMLError) -> str:
    """One line: what is wrong and where (line, column), without YAML's source excerpt."""
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    mark = getattr(e, "problem_mark", None)
    return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else problem


def _override_value(item: str, value: str) -> Any:
    try:
        return yaml.load(value, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        why = _yaml_problem(e)
        raise UserError(f"--set {item!r}: the value {value!r} is not valid YAML ({why}); quote lists and "
                        "mappings for the shell, e.g. --set 'subject.poses.heights_mm=[0, 10]'.") from None


class _UniqueKeyLoader(yaml.SafeLoader):
    """safe_load, but a key given twice in one mapping is an error (YAML keeps the last silently)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:
                continue
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key: {key!r} is given twice (lines {seen[key] + 1} and {key_node.start_mark.line + 1})",
                    key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_timestamp(self, node):
        """A date YAML's pattern takes but the calendar does not (2026-13-01, 2026-02-30) is a
        YAML error at its line, not a ValueError from inside the parser."""
        try:
            return super().construct_yaml_timestamp(node)
        except ValueError as e:
            raise yaml.constructor.ConstructorError(None, None, f"{node.value!r} is not a date ({e})",
                                                    node.start_mark) from None


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:timestamp", _UniqueKeyLoader.construct_yaml_timestamp)


def _apply_override(raw: dict[str, Any], item: str) -> None:
    """Apply ``dotted.key=value`` (list items by index: ``system.mirrors.0.reflectance=0.9``)."""
    if "=" not in item:
        raise UserError(f"--set {item!r}: expected dotted.key=value, e.g. --set transfer.estimator=pairwise.")
    key, value = item.split("=", 1)
    parts = key.strip().split(".")
    node: Any = raw
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        where = ".".join(parts[:i]) or "the config"
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise UserError(f"--set {item!r}: {where} is a list of {len(node)} item(s); {part!r} is not an index in it.")
            if last:
                node[int(part)] = _override_value(item, value)
            else:
                node = node[int(part)]
        elif isinstance(node, dict):
            if last:
                node[part] = _override_value(item, value)
            else:
                if node.get(part) is None:
                    node[part] = {}
                node = node[part]
        else:
            raise UserError(f"--set {item!r}: {where} is a value, not a section, so it has no key {part!r}.")


# union members of subject.surface, by the key that selects each
_SURFACE_MEMBERS = {"phantom": ("MeshSurface", "ArtefactSurface"), "mesh": ("ArtefactSurface", "tagged-union"),
                    "artefact": ("MeshSurface", "tagged-union")}


# reconstruct.images: the key that says which kind it is -> the other kind's member (in error locations)
_IMAGES_MEMBERS = {"capture": "ImageFiles", "files": "CaptureSource"}


def _section(raw: Any, *keys: str):
    for k in keys:
        raw = raw.get(k) if isinstance(raw, dict) else None
    return raw if isinstance(raw, dict) else None


def _not_chosen(errors: list, section, members: dict, match) -> list:
    """``errors`` without those of the union members ``section`` (the user's mapping) did not choose."""
    if section is None:
        return errors
    for key, others in members.items():
        if key in section:
            kept = [e for e in errors if not any(isinstance(x, str) and match(x, others) for x in e["loc"])]
            return kept or errors
    return errors


def _relevant(errors: list, raw: Any) -> list:
    """Drop errors from union members the user did not choose (a phantom with a bad radius
    is not also 'missing its mesh key'; images from a capture are not also 'missing their
    files'), and a list's 'too short' when one of its items failed."""
    items = {tuple(e["loc"][:i]) for e in errors for i, x in enumerate(e["loc"]) if isinstance(x, int)}
    errors = [e for e in errors if not (e["type"] == "too_short" and tuple(e["loc"]) in items)]
    errors = _not_chosen(errors, _section(raw, "subject", "surface"), _SURFACE_MEMBERS, lambda x, o: x.startswith(o))
    return _not_chosen(errors, _section(raw, "reconstruct", "images"), _IMAGES_MEMBERS,
                       lambda x, o: x == o or x.endswith(f", {o}]"))


def _format_validation_error(err: ValidationError, path: Path, raw: Any = None, what: str = "config") -> str:
    lines = []
    errors = _relevant(err.errors(), raw)
    for e in errors[:6]:
        loc = _user_loc(e["loc"], raw, keep_last=e["type"] == "missing")
        if e["type"] == "extra_forbidden":
            msg = "unknown key (check its spelling against the README's config reference)"
        elif e["type"] == "missing" and e["loc"] and isinstance(e["loc"][-1], int):  # a fixed-length list, short
            loc = loc.rsplit(".", 1)[0]
            msg = f"too few values: item {e['loc'][-1] + 1} of this fixed-length list is missing (e.g. x, y, z)"
        elif e["type"] == "missing":
            msg = "required key is missing"
        elif e["type"] in ("union_tag_not_found", "union_tag_invalid"):  # the key that picks a variant
            ctx = e.get("ctx") or {}
            tag = str(ctx.get("discriminator", "")).strip("'")
            kinds = _UNION_CHOICES.get(tag, "")
            loc = f"{loc}.{tag}" if loc else tag
            msg = (f"{ctx.get('tag')!r} is not one of {kinds}" if e["type"] == "union_tag_invalid"
                   else f"required key is missing: one of {kinds}")
        else:
            msg = e["msg"].removeprefix("Value error, ")
            if msg.endswith(EMPTY_PATH):  # raised by the section holding the key: name the key itself
                key, msg = msg.split(": ", 1)
                loc = f"{loc}.{key}" if loc else key
        lines.append(f"'{loc}': {msg}" if loc else msg)
    more = "" if len(errors) <= 6 else f" (and {len(errors) - 6} more)"
    text = "; ".join(lines) + more
    return f"{what} {path}: " + text + ("" if text.endswith((".", "?", "!")) else ".")


# the values of the keys that pick a variant of a section, for the messages that name them
def _tags(union: Any, key: str) -> str:
    members = get_args(get_args(union)[0])
    return ", ".join(str(get_args(m.model_fields[key].annotation)[0]) for m in members)


_UNION_CHOICES = {"model": _tags(Emission, "model"), "kind": _tags(Flux, "kind"), "phantom": _tags(Phantom, "phantom")}


def _user_loc(loc, raw: Any, keep_last: bool = False) -> str:
    """An error's location as the user wrote it: pydantic's names for a union's members (the
    variant a tag picked, ``diffuse`` in ``subject.emission.diffuse.absorption_per_mm``) left out,
    unless the user's own data holds that name as a key at that place (a key ``file`` is not the
    flux kind ``file``), or it is the missing key itself (``keep_last``: a table's ``file``)."""
    out, cur = [], raw
    for i, x in enumerate(loc):
        member = isinstance(x, str) and (x in _UNION_TAGS or x in _TAG_VALUES or x.startswith(_MEMBER_NAMES))
        if keep_last and i == len(loc) - 1:
            member = False
        if member and not (isinstance(cur, dict) and x in cur):
            continue
        out.append(str(x))
        if isinstance(cur, dict):
            cur = cur.get(x)
        elif isinstance(cur, list) and isinstance(x, int) and -len(cur) <= x < len(cur):
            cur = cur[x]
        else:
            cur = None
    return ".".join(out)


# pydantic puts union member names into error locations; they are not keys the user wrote.
_UNION_TAGS = {"cylinder", "ring", "sphere", "patch", "MeshSurface", "ArtefactSurface",
               "gaussian", "uniform", "file", "diffusion", "float", "literal['auto']",
               "function-after[_check(), Lens]", "ImageFiles", "CaptureSource", "tagged-union[CylinderPhantom,BoxPhantom,RingPhantom,SpherePhantom,PatchPhantom]"}
_MEMBER_NAMES = ("function-after[", "tagged-union[")  # a member with a validator, a tagged union: never a key
_TAG_VALUES = {t.strip().strip("'") for v in _UNION_CHOICES.values() for t in v.split(",")}  # every variant's tag


def _camera_from_file(raw: dict[str, Any], base_dir: Path, path: Path) -> None:
    """Resolve ``system.camera`` given as a file (what ``calibrate`` writes as camera.yaml).

    ``system.camera: calib/camera.yaml`` takes the file's top-level ``camera:`` block;
    ``system.camera: {file: calib/camera.yaml, <key>: ...}`` does too, and the keys given beside
    ``file`` replace the file's (sections are merged key by key)."""
    system = raw.get("system")
    if not isinstance(system, dict):
        return
    cam = system.get("camera")
    if isinstance(cam, str):
        ref, overrides = cam, {}
    elif isinstance(cam, dict) and "file" in cam:
        ref, overrides = cam["file"], {k: v for k, v in cam.items() if k != "file"}
    else:
        return
    if not isinstance(ref, str) or not ref:
        raise UserError(f"config {path}: 'system.camera.file' must be the path of a camera YAML file.")
    hint = "run `fluxmap calibrate` to make one, or give the camera block inline"
    loaded = _block_from_file(ref, "camera", dict, "system.camera", base_dir, path, hint)
    merged = _merge(loaded, overrides)
    if isinstance(merged.get("assumed"), dict):  # a value given beside the file is the user's, no longer assumed
        given = {k for k, v in overrides.items() if not isinstance(v, dict)}
        given |= {k for v in overrides.values() if isinstance(v, dict) for k in v}
        merged["assumed"] = {k: v for k, v in merged["assumed"].items() if k.split(".")[-1] not in given}
    system["camera"] = merged


def _block_from_file(ref: str, block: str, kind: type, key: str, base_dir: Path, path: Path, hint: str):
    """The top-level ``block`` (a mapping or a list) of the YAML file ``ref`` names (relative to the
    config), for config keys given as a file (``system.camera``, ``system.mirrors``)."""
    file = Path(ref) if Path(ref).is_absolute() else (base_dir / ref).resolve()
    if not file.is_file():
        raise UserError(f"config {path}: '{key}': file {file} does not exist ({hint}).")
    try:
        loaded = yaml.load(file.read_text(), Loader=_UniqueKeyLoader)
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise UserError(f"config {path}: '{key}': file {file} is not valid YAML: {e}".replace("\n", " ")) from None
    if not isinstance(loaded, dict) or not isinstance(loaded.get(block), kind):
        what = "block" if kind is dict else "list"
        raise UserError(f"config {path}: '{key}': file {file} has no top-level '{block}:' {what}.")
    return loaded[block]


def _mirrors_from_file(raw: dict[str, Any], base_dir: Path, path: Path) -> None:
    """``system.mirrors: calib/camera.yaml`` takes the file's top-level ``mirrors:`` list (refined by calibrate)."""
    system = raw.get("system")
    if not isinstance(system, dict) or not isinstance(system.get("mirrors"), str):
        return
    system["mirrors"] = _block_from_file(system["mirrors"], "mirrors", list, "system.mirrors", base_dir, path,
                                         "calibrate writes it beside camera.yaml")


def _projectors_from_file(raw: dict[str, Any], base_dir: Path, path: Path) -> None:
    """``rig.projectors: calib/camera.yaml`` takes the file's top-level ``projectors:`` mapping (what
    calibrate writes); ``rig.projectors: {file: calib/camera.yaml, left: {display: window}}`` too, with
    the keys beside ``file`` merged into the file's entries.  ``calibrate.projectors[k].simulated.camera:
    truth.yaml`` takes that file's ``camera:`` block."""
    rig = raw.get("rig")
    projs = rig.get("projectors") if isinstance(rig, dict) else None
    if isinstance(projs, str) or (isinstance(projs, dict) and "file" in projs):
        ref, overrides = (projs, {}) if isinstance(projs, str) else (projs["file"], {k: v for k, v in projs.items() if k != "file"})
        if not isinstance(ref, str) or not ref:
            raise UserError(f"config {path}: 'rig.projectors.file' must be the path of a YAML file (calibrate's camera.yaml).")
        loaded = _block_from_file(ref, "projectors", dict, "rig.projectors", base_dir, path,
                                  "calibrate writes it beside camera.yaml when calibrate.projectors is given")
        rig["projectors"] = _merge(loaded, overrides)
    cal = raw.get("calibrate")
    for k, pc in enumerate((cal.get("projectors") or []) if isinstance(cal, dict) else []):
        sim = pc.get("simulated") if isinstance(pc, dict) else None
        if isinstance(sim, dict) and isinstance(sim.get("camera"), str):
            sim["camera"] = _block_from_file(sim["camera"], "camera", dict, f"calibrate.projectors[{k}].simulated.camera",
                                             base_dir, path, "give the true camera's YAML file or the block inline")


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out




def require(cfg: "LoadedConfig", stage: str, keys: tuple[str, ...] | list[str]) -> None:
    """Refuse (exit 2) when a section the stage needs is absent, naming the first such key."""
    for key in keys:
        node: Any = cfg.model
        for part in key.split("."):
            node = getattr(node, part, None)
            if node is None:
                raise UserError(f"config {cfg.path}: '{stage}' needs '{key}', which the config does not give.")


def emission_profile(cfg: "LoadedConfig"):
    """The subject's emission profile (:class:`fluxcli.optics.emission.Profile`); Lambertian when
    ``subject.emission`` is absent.  A table file that cannot be read or is not a valid profile is
    a UserError naming it."""
    from .optics import emission as E

    em = cfg.model.subject.emission if cfg.model.subject is not None else None
    if em is None:
        return E.lambertian()
    if isinstance(em, TableEmission):
        f = cfg.resolve(em.file)
        if not f.is_file():
            what = ("is a folder, not a CSV file" if f.is_dir() else "is not a regular file (a device or a pipe?)"
                    if f.exists() else "does not exist")
            raise UserError(f"config {cfg.path}: 'subject.emission.file': {f} {what}.")
        try:
            raw = f.read_bytes()
            if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):  # a spreadsheet's "Unicode text": UTF-16 with its BOM
                text = raw.decode("utf-16")
            else:
                try:
                    text = raw.decode("utf-8-sig")
                except UnicodeDecodeError:  # a spreadsheet's ANSI code page ("angle (°)" in Windows-1252)
                    text = raw.decode("latin-1")
            return E.table_from_csv(text, source=f.name)
        except (ValueError, OSError, UnicodeDecodeError) as e:
            raise UserError(f"config {cfg.path}: 'subject.emission.file': {f} {e}.") from None
    try:
        return E.profile(em)
    except ValueError as e:
        raise UserError(f"config {cfg.path}: 'subject.emission': {e}.") from None


def load_config(path: Path | str, overrides: list[str] | tuple[str, ...] = ()) -> LoadedConfig:
    """Read, override and validate a config; raise UserError with one clear paragraph."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"config file {path} is a folder; give the YAML file itself.")
    if not path.is_file():
        raise UserError(f"config file {path} does not exist.")
    try:
        raw = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        raise UserError(f"config file {path} is not valid YAML: {_yaml_problem(e)}.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"config file {path} cannot be read: {e}.") from None
    if not isinstance(raw, dict):
        raise UserError(f"config file {path} must hold a mapping of keys (workdir, system, subject, ...).")
    _camera_from_file(raw, path.resolve().parent, path)
    _mirrors_from_file(raw, path.resolve().parent, path)
    _projectors_from_file(raw, path.resolve().parent, path)
    for item in overrides:
        _apply_override(raw, item)
    try:
        model = Config.model_validate(raw)
    except ValidationError as e:
        raise UserError(_format_validation_error(e, path, raw)) from None
    loaded = LoadedConfig(model, path.resolve(), raw)
    emission_profile(loaded)  # a table file that is missing or malformed exits 2 now, naming it
    surf = model.subject.surface if model.subject is not None else None
    for attr in ("mesh", "artefact"):
        p = getattr(surf, attr, None)
        if p is not None and not loaded.resolve(p).is_file():
            if attr == "artefact" and loaded.resolve(p) == loaded.captured_surface_path:
                continue  # this config's capture-surface makes it; stages that need it say so
            raise UserError(f"config {path}: 'subject.surface.{attr}': file {loaded.resolve(p)} does not exist.")
    return loaded


Simulate.model_rebuild()
Config.model_rebuild()
