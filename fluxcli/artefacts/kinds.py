"""What each artefact kind holds: its schema version, datasets, units and meaning, in one place.

Writers take units from here (:func:`fluxcli.artefacts.put`), readers check that every
required dataset is present when a file is opened (an incomplete file is named with the
missing dataset and the stage that remakes it), and ``fluxmap info`` prints these
descriptions next to what a file holds.  A new artefact kind is one more :class:`Kind`
in :data:`KINDS`; a kind with a container module (``simulation``, ``surface``, ``tetmesh``)
registers itself there, its datasets made from the container's fields.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields


@dataclass(frozen=True)
class Dataset:
    """One dataset (or group) of an artefact: its path in the file, unit and meaning."""

    name: str
    unit: str = ""
    meaning: str = ""
    required: bool = True


@dataclass(frozen=True)
class Kind:
    """An artefact kind: name, schema version, the stage that makes it, and its datasets."""

    name: str
    schema_version: int
    made_by: str  # the command that (re)makes it, for messages
    description: str
    datasets: tuple[Dataset, ...] = field(default=())

    def dataset(self, name: str) -> Dataset | None:
        for d in self.datasets:
            if d.name == name:
                return d
        return None

    @property
    def required(self) -> list[str]:
        return [d.name for d in self.datasets if d.required]


_SURFACE = (
    Dataset("surface/vertices", "mm", "vertex positions (V, 3)"),
    Dataset("surface/faces", "", "triangles (F, 3), counter-clockwise seen from outside"),
    Dataset("surface/element_of_face", "", "element of each face, -1 for occluder-only faces"),
    Dataset("surface/areas", "mm^2", "area of each element"),
)

KINDS: dict[str, Kind] = {}
SCHEMA_VERSIONS: dict[str, int] = {}  # kind -> schema version this fluxmap reads and writes


def register(kind: Kind) -> Kind:
    """Add an artefact kind (other packages add theirs at import time)."""
    KINDS[kind.name] = kind
    SCHEMA_VERSIONS[kind.name] = kind.schema_version
    return kind


register(Kind("transfer", 2, "fluxmap build-T", "transfer matrix T of one pose (a T-cache entry)", (
    Dataset("T/data", "dimensionless", "fraction of an element's power reaching a pixel (CSR data)"),
    Dataset("T/indices", "", "CSR column (element) indices"),
    Dataset("T/indptr", "", "CSR row pointers; row = pixel, flat index row * nx + col"),
    *_SURFACE,
    Dataset("views", "", "per view k: its T (CSR), weight, sampling statistics and column_error"),
    Dataset("T/column_error", "dimensionless",
            "estimated L1 error of each column of T (sum over pixels of |even - odd half-sample estimates|; "
            "NaN: no estimate, e.g. pairwise)", required=False),
)))

register(Kind("transfer-index", 2, "fluxmap build-T", "which T-cache entry belongs to which pose", (
    Dataset("heights_mm", "mm", "stage height of each pose"),
    Dataset("rotations_deg", "deg", "rotation of each pose"),
    Dataset("keys", "", "content address (sha256) of each pose's T"),
    Dataset("paths", "", "T file of each pose"),
    Dataset("efficiency", "dimensionless", "collection efficiency [pose, view]"),
)))

register(Kind("reconstruction", 2, "fluxmap reconstruct", "surface flux reconstructed from images", (
    *_SURFACE,
    Dataset("flux/power", "photons per element (NaN: unobserved)", "the result (joint over poses when several)"),
    Dataset("flux/exitance", "photons mm^-2", "power / element area"),
    Dataset("flux/observed", "", "element seen by some camera view"),
    Dataset("flux/sigma", "photons (1 sd)", "per-element uncertainty"),
    Dataset("flux/total", "photons over observed elements", "sum of power"),
    Dataset("per_pose/power", "photons", "each pose on its own [pose, element]"),
    Dataset("per_pose/sigma", "photons", "[pose, element]"),
    Dataset("per_pose/observed", "", "[pose, element]"),
    Dataset("per_pose/total", "photons", "[pose]"),
    Dataset("per_pose/lambda", "", "regularisation used per pose"),
    Dataset("per_pose/heights_mm", "mm", "stage height of each pose"),
    Dataset("per_pose/rotations_deg", "deg", "rotation of each pose"),
    Dataset("per_pose/vertices_mm", "mm", "the surface placed at each pose", required=False),
    Dataset("per_pose/backprojection_total", "photons (T'a summed)", "", required=False),
    Dataset("per_pose/direct_roi_photons", "photons", "measured photons over the pixels the direct view reaches",
            required=False),
    Dataset("fit/measured", "photons", "images [pose, row, col]"),
    Dataset("fit/fitted", "photons", "T b [pose, row, col], NaN where not fitted"),
    Dataset("fit/residual", "photons", "measured - fitted"),
    Dataset("fit/valid", "", "pixels used (finite, not saturated)"),
    Dataset("geometry", "", "what the report draws: subject axis, camera look/up, view names, T files"),
    Dataset("truth/power", "photons", "ground truth at the reconstructed level", required=False),
    Dataset("flux/observation", "", "0 unobserved, 1 poorly observed, 2 well observed", required=False),
    Dataset("flux/well_observed", "", "observed and pinned down by the data", required=False),
    Dataset("flux/total_well_observed", "photons", "sum of power over well-observed elements", required=False),
    Dataset("flux/total_poorly_observed", "photons", "sum of power over poorly observed elements", required=False),
    Dataset("flux/headline_total", "photons", "the total to read first: over observed elements, or over well-observed "
            "ones when the warnings say the former is not pinned down (attrs over, reason)", required=False),
    Dataset("per_pose/headline_total", "photons", "flux/headline_total per pose [pose]", required=False),
    Dataset("per_pose/headline_reason", "", "why a pose's headline is over well-observed elements ('' if not) [pose]",
            required=False),
    Dataset("per_pose/chi2_per_pixel", "", "chi^2 per pixel under the noise model [pose]", required=False),
    Dataset("per_pose/observation", "", "[pose, element] 0/1/2 as flux/observation", required=False),
    Dataset("warnings", "", "what the solves detected (lambda at an edge, chi^2 far from 1, ...)", required=False),
    # issue 24: regions of interest, [roi, map] with maps the poses ('1', '2', ...) then 'joint' (attrs names, maps)
    Dataset("rois/total_photons_per_s", "photons/s (per exposure when no exposure is known)",
            "total over the region's observed elements [roi, map]", required=False),
    Dataset("rois/sigma_photons_per_s", "photons/s (1 sd)", "sqrt(w'Cw) from the solve's covariance [roi, map]",
            required=False),
    Dataset("rois/mean_radiance", "photons s^-1 cm^-2 sr^-1", "Lambertian L = M/pi over the observed area [roi, map]",
            required=False),
    Dataset("rois/peak_radiance", "photons s^-1 cm^-2 sr^-1", "of the brightest observed element [roi, map]",
            required=False),
    Dataset("rois/area_mm2", "mm^2", "[roi, map]", required=False),
    Dataset("rois/observed_share", "", "share of the area observed [roi, map]", required=False),
    Dataset("rois/well_observed_share", "", "share of the area well observed [roi, map]", required=False),
    Dataset("rois/status", "", "'' or why the number does not stand for the region [roi, map]", required=False),
    Dataset("rois/members", "", "elements of each region [roi, map, element]", required=False),
    Dataset("filters", "", "several filters in one run: /filters/<name>/{flux, per_pose_power, rois, ...}; "
            "attrs transmission, rate_exposure_s (s, that filter's frames)",
            required=False),
    Dataset("truth/error_per_pose", "", "L1 error of each pose against the truth (paper Eq. 15) [pose]", required=False),
    Dataset("truth/total_ratio_per_pose", "", "reconstructed / true total [pose]", required=False),
    Dataset("emission/angle_deg", "deg", "angle from the normal", required=False),
    Dataset("emission/relative_radiance", "", "L(theta) / L(0) of subject.emission", required=False),
    Dataset("emission/joint_light_beyond_deg", "", "all poses jointly: share of the light from beyond each band",
            required=False),
    Dataset("emission/joint_total_beyond_deg", "", "all poses jointly: share of the total resting beyond each band",
            required=False),
    Dataset("per_pose/light_beyond_deg", "", "share of the model image's light from beyond each angle [pose, band]",
            required=False),
    Dataset("per_pose/total_beyond_deg", "", "share of the total resting on views beyond each angle [pose, band]",
            required=False),
    Dataset("per_pose/residual_vs_angle", "", "relative residual change per 10 deg and its t [pose, 2]",
            required=False),
    Dataset("budget/total", "photons", "each total (poses, then joint)", required=False),
    Dataset("budget/sigma_noise", "photons", "1 sd from photon noise [total]", required=False),
    Dataset("budget/sigma_regularisation", "photons", "1 sd from the regularisation [total]", required=False),
    Dataset("budget/sigma_calibration", "photons", "1 sd from the calibration [total]", required=False),
    Dataset("budget/sigma", "photons", "the three in quadrature [total]", required=False),
    Dataset("budget/deltas", "photons", "change of each total per calibrated parameter +1 sd [total, parameter]",
            required=False),
    Dataset("budget/rois", "photons", "each region's sigma by cause [roi, total]", required=False),
    Dataset("budget/shift_px", "px", "per pose: the fitted image's shift that best explains the residual",
            required=False),
    Dataset("budget/shift_z", "", "per pose: |shift| over its standard error", required=False),
    Dataset("budget/shift_flank_z", "", "per pose: the shift as each flank of the image alone sees it, in its sd",
            required=False),
    Dataset("sweep", "", "the study sweep: error[method, level, pose, repeat], mean, sd, max_snr, "
            "levels_peak_photons", required=False),
)))

register(Kind("calibration", 1, "fluxmap calibrate", "camera model from grid images, sensor from frames", (
    Dataset("camera_yaml", "", "the camera.yaml written beside this file (text)"),
    Dataset("geometric/lens_center_mm", "mm", "lens centre C in the grid's frame", required=False),
    Dataset("geometric/rotation", "", "rows: camera right, down, look (world directions)", required=False),
    Dataset("geometric/images", "", "per image k: plane_z_mm, ij, xy_px, residual_px, residual_mm, "
            "blur_diameter_px, axial_mm (pixel centres at integer (col, row))", required=False),
    Dataset("radiometric", "", "bias/dark/flat maps, PTC, sensor scalars", required=False),
)))


register(Kind("capture", 1, "fluxmap capture-surface", "emission images acquired on the rig, frame by frame", (
    Dataset("frames/counts", "ADC counts", "counts[frame, row, col]; frame k is plan slot k, row 0 first"),
    Dataset("frames/time_unix", "s", "when the frame was read out (s since 1970-01-01 UTC)"),
    Dataset("frames/stage_height_mm", "mm", "stage height read back from the stage"),
    Dataset("frames/filter_position", "", "filter-wheel position read back (1-based)"),
    Dataset("frames/filter_name", "", "name of that position in rig.filter_wheel.filters"),
    Dataset("frames/exposure_s", "s", "exposure read back from the camera"),
    Dataset("frames/em_gain", "", "EM gain read back from the camera"),
    Dataset("frames/temperature_c", "deg C", "sensor temperature read back from the camera"),
    Dataset("frames/shutter_open", "", "1 light frame, 0 dark frame (shutter closed)"),
    Dataset("frames/committed", "", "1 once frame k and its metadata are durable (written last); 0: not taken"),
    Dataset("plan/dark", "", "1 for a planned dark frame"),
    Dataset("plan/height_mm", "mm", "planned stage height of each frame"),
    Dataset("plan/filter", "", "planned filter of each frame"),
    Dataset("plan/repeat", "", "repeat index of each frame"),
    Dataset("plan/exposure_s", "s", "planned exposure time of each frame"),
    Dataset("truth", "photons per element per second (subject at rest)",
            "simulated camera only: truth/<filter>/power, what reaches the camera through each filter", required=False),
    # structured-light pattern frames (capture.surface), taken before the emission frames
    Dataset("patterns/counts", "ADC counts", "counts[pattern frame, row, col] at capture.surface.binning", required=False),
    Dataset("patterns/committed", "", "1 once pattern frame k and its metadata are durable", required=False),
    Dataset("patterns/projector", "", "projector showing the pattern (rig.projectors key)", required=False),
    Dataset("patterns/pattern_index", "", "position of the pattern in the sequence", required=False),
    Dataset("patterns/label", "", "white, black, grayB, grayB-inverse or phaseK", required=False),
    Dataset("patterns/gray_bit", "", "Gray-code bit shown (0 least significant), -1: not a code frame", required=False),
    Dataset("patterns/inverse", "", "1 for the inverse of a code frame", required=False),
    Dataset("patterns/phase_step", "", "phase-shift step K, -1: not a fringe frame", required=False),
    Dataset("patterns/phase_shift_rad", "rad", "the fringe's shift 2 pi K / n_steps (nan: not a fringe frame)", required=False),
    Dataset("patterns/stage_height_mm", "mm", "stage height read back", required=False),
    Dataset("patterns/exposure_s", "s", "exposure read back", required=False),
    Dataset("patterns/em_gain", "", "EM gain read back", required=False),
    # calibration frames (capture.calibration), taken first: what calibrate.capture reads
    Dataset("calibration/counts", "ADC counts", "counts[calibration frame, row, col]", required=False),
    Dataset("calibration/committed", "", "1 once calibration frame k and its metadata are durable", required=False),
    Dataset("calibration/kind", "", "grid, bias, dark, flat, ptc_off (EM gain 1) or ptc_on", required=False),
    Dataset("calibration/series", "", "series within the kind (grid: the height; dark, PTC: the exposure)",
            required=False),
    Dataset("calibration/repeat", "", "frame number in its series (pairs 0-1, 2-3, ...)", required=False),
    Dataset("calibration/plan_height_mm", "mm", "planned stage height (nan: not moved)", required=False),
    Dataset("calibration/plan_exposure_s", "s", "planned exposure", required=False),
    Dataset("calibration/plan_em_gain", "", "planned EM gain", required=False),
    Dataset("calibration/filter", "", "planned filter ('': shutter closed)", required=False),
    Dataset("calibration/stage_height_mm", "mm", "stage height read back (grid plane z = stage top + this + "
            "grid thickness)", required=False),
    Dataset("calibration/exposure_s", "s", "exposure read back", required=False),
    Dataset("calibration/em_gain", "", "EM gain read back", required=False),
)))

# ------------------------------------------------------------------ containers (one module per kind)
def quantity(path: str, unit: str = "", meaning: str = "", *, required: bool = True, default=MISSING,
             default_factory=MISSING):
    """A container field stored as dataset (or group) ``path``, with its unit and meaning: what
    the kind's schema lists (:func:`datasets_of`) and :func:`fluxcli.artefacts.put` writes."""
    return field(default=default, default_factory=default_factory,
                 metadata={"path": path, "unit": unit, "meaning": meaning, "required": required})


def attribute(where: str, unit: str = "", meaning: str = "", *, default=MISSING, default_factory=MISSING):
    """A container field stored as HDF5 attribute ``where`` (``group@name``; ``@name`` at the root)."""
    return field(default=default, default_factory=default_factory,
                 metadata={"attribute": where, "unit": unit, "meaning": meaning})


def datasets_of(container) -> tuple[Dataset, ...]:
    """The datasets a container class declares (its :func:`quantity` fields, in order)."""
    return tuple(Dataset(f.metadata["path"], f.metadata["unit"], f.metadata["meaning"], f.metadata["required"])
                 for f in fields(container) if "path" in f.metadata)


SURFACE_DATASETS = _SURFACE
