"""Find a calibration grid in an image and label its points with the contract's indices.

Dots: OpenCV's SimpleBlobDetector (on the image scaled to 8 bit) finds candidate dots; a
lattice is grown from the central dot along the two dominant neighbour directions (local
steps, so perspective is followed) and cleaned with a homography; the labels are then
turned into the contract's (i, j) by the grid's symmetry: the labelling is the one with the
handedness of a camera looking down at the grid and whose +y is nearest to image up
(the camera's ``up`` is the world direction nearest +y).  When some dots are out of the
field the labels are offset by which side is cut; when both sides could be cut the image
is reported ambiguous and labelled later from a camera fitted to the other images.
Checkerboards: OpenCV's ``findChessboardCornersSB`` (inner corners), then the same
labelling.

Pixel coordinates here are (col, row) with pixel centres at integers (OpenCV's); the
fluxmap convention (pixel (r, c) spans [c, c+1)) is these plus 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree


class GridNotFound(ValueError):
    """The grid could not be found (or labelled) in an image."""


class GridShapeMismatch(ValueError):
    """What is seen does not fit the stated grid shape."""


@dataclass
class Detection:
    """Grid points found in one image.

    Attributes
    ----------
    ij : ndarray (n, 2) int
        Contract indices (i along x, j along y) of the points found.
    xy_px : ndarray (n, 2)
        Their image positions (col, row), pixel centres at integers.
    ambiguous : bool
        The labels' offset along some axis is unknown (grid cut on both sides).
    spacing_px : float
        Median distance between neighbouring points (px).
    notes : list of str
        What happened (partial detection, ...).
    """

    ij: np.ndarray
    xy_px: np.ndarray
    ambiguous: bool = False
    spacing_px: float = 0.0
    notes: list[str] = field(default_factory=list)
    lattice_ij: np.ndarray | None = None  # raw lattice labels (before the offset), for relabelling


# ----------------------------------------------------------------------------- image prep
def to_unit(image: np.ndarray) -> np.ndarray:
    """Float image scaled so that the background is ~0 and the features ~1, features bright.

    Works for 16-bit counts or float photons, bright dots on dark or dark on bright.
    """
    img = np.asarray(image, float)
    if img.ndim != 2 or img.size == 0:
        raise ValueError(f"an image must be 2-D, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError("the image holds NaN or infinite values")
    lo, med, hi = np.percentile(img, [0.5, 50, 99.5])
    if hi - lo <= 0:
        raise GridNotFound("the image is uniform (no grid visible)")
    if (hi - med) < (med - lo):  # the median (background) is near the top: dark features
        img = -img
        lo, med, hi = -hi, -med, -lo
    return (img - med) / (hi - med)


def to_uint8(unit: np.ndarray) -> np.ndarray:
    return (np.clip(unit, 0, 1) * 255).round().astype(np.uint8)


def blob_points(unit: np.ndarray, *, max_area_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 2) and diameters (n,) of bright blobs (tuned SimpleBlobDetector)."""
    ny, nx = unit.shape
    img8 = to_uint8(cv2.GaussianBlur(unit, (0, 0), 0.7))
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = 20, 235, 15
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 2.0
    p.filterByColor, p.blobColor = True, 255
    p.filterByArea, p.minArea = True, 3.0
    p.maxArea = float(nx * ny) / 8 if max_area_px is None else float(max_area_px)
    p.filterByCircularity, p.minCircularity = True, 0.5
    p.filterByConvexity, p.minConvexity = True, 0.7
    p.filterByInertia, p.minInertiaRatio = True, 0.25
    kps = cv2.SimpleBlobDetector_create(p).detect(img8)
    if not kps:
        return np.zeros((0, 2)), np.zeros(0)
    return np.array([k.pt for k in kps], float), np.array([k.size for k in kps], float)


def peak_points(unit: np.ndarray, *, sigma_px: float = 1.0) -> np.ndarray:
    """Local maxima of the smoothed image well above the background noise (n, 2): dots too blurred
    or too close for thresholding to separate still have one maximum each."""
    from scipy.ndimage import gaussian_filter, maximum_filter

    sm = gaussian_filter(unit, sigma_px)
    bg = sm[sm < np.percentile(sm, 50)]
    noise = 1.4826 * np.median(np.abs(bg - np.median(bg))) if bg.size else 0.0
    thr = max(0.2 * np.percentile(sm, 99.5), 6 * noise)
    peaks = (sm == maximum_filter(sm, size=3)) & (sm > thr)
    r, c = np.nonzero(peaks)
    return np.column_stack([c, r]).astype(float)


def candidate_points(unit: np.ndarray) -> list[np.ndarray]:
    """Candidate dot centres by several detectors (blobs at decreasing size limits, local maxima)."""
    n = unit.size
    out = [blob_points(unit)[0]]
    for frac in (64, 512):
        out.append(blob_points(unit, max_area_px=n / frac)[0])
    out.append(peak_points(unit))
    return out


# ----------------------------------------------------------------------------- lattice
def _dominant_steps(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    tree = cKDTree(pts)
    d, idx = tree.query(pts, k=min(5, len(pts)))
    d0 = float(np.median(d[:, 1]))
    vec = (pts[idx[:, 1:]] - pts[:, None, :]).reshape(-1, 2)
    ln = np.linalg.norm(vec, axis=1)
    vec = vec[(ln > 0.7 * d0) & (ln < 1.4 * d0)]
    ang = np.mod(np.arctan2(vec[:, 1], vec[:, 0]), np.pi)
    hist, edges = np.histogram(ang, bins=90, range=(0, np.pi))
    hist = hist + np.roll(hist, 1) + np.roll(hist, -1)
    a1 = edges[np.argmax(hist)] + np.pi / 180
    near = np.abs(np.angle(np.exp(2j * (ang - a1)))) / 2 < np.pi / 8
    a1 = np.angle(np.mean(np.exp(2j * ang[near]))) / 2
    off = np.abs(np.angle(np.exp(2j * (ang - a1)))) / 2
    near2 = off > np.pi / 4
    if near2.sum() < 3:
        raise GridNotFound("the dots do not form a two-dimensional lattice")
    a2 = np.angle(np.mean(np.exp(2j * ang[near2]))) / 2
    l1 = float(np.median(ln[(ln > 0.7 * d0) & (ln < 1.4 * d0)][near])) if near.any() else d0
    l2 = float(np.median(ln[(ln > 0.7 * d0) & (ln < 1.4 * d0)][near2]))
    return l1 * np.array([np.cos(a1), np.sin(a1)]), l2 * np.array([np.cos(a2), np.sin(a2)]), d0


def grow_lattice(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Integer lattice labels for the points that form one regular 2-D lattice.

    Returns (index of labelled points, labels (n, 2), neighbour spacing px).
    """
    if len(pts) < 6:
        raise GridNotFound(f"only {len(pts)} dot-like blobs found")
    a, b, d0 = _dominant_steps(pts)
    if d0 < 3.0:  # dots closer than 3 px cannot be told apart (and noise maxima sit ~2 px apart)
        raise GridNotFound(f"the candidate dots lie {d0:.1f} px apart, too close to be a grid")
    tree = cKDTree(pts)
    centre = np.median(pts, axis=0)
    seed = int(tree.query(centre)[1])
    labels = {seed: (0, 0)}
    steps = {seed: (a.copy(), b.copy())}
    where = {(0, 0): seed}
    queue = [seed]
    tol = 0.3 * min(np.linalg.norm(a), np.linalg.norm(b))
    while queue:
        k = queue.pop(0)
        i, j = labels[k]
        sa, sb = steps[k]
        for (di, dj), step in (((1, 0), sa), ((-1, 0), -sa), ((0, 1), sb), ((0, -1), -sb)):
            lab = (i + di, j + dj)
            if lab in where:
                continue
            dist, m = tree.query(pts[k] + step, distance_upper_bound=tol)
            if not np.isfinite(dist) or m in labels:
                continue
            labels[m] = lab
            where[lab] = m
            real = pts[m] - pts[k]
            na = real * (1 if di + dj > 0 else -1)
            if np.linalg.norm(na - (sa if di else sb)) > 0.15 * np.linalg.norm(sa if di else sb):
                na = sa if di else sb  # a step unlike its neighbours' is not followed further
            steps[m] = (na, sb) if di else (sa, na)
            queue.append(m)
    idx = np.array(list(labels.keys()))
    lab = np.array([labels[k] for k in idx])
    # clean: homography from labels to image, drop points far from it, relabel by rounding
    for _ in range(2):
        if len(idx) < 6:
            break
        # RANSAC: points of another lattice (a mirror's view) that the growth stepped into are outliers
        H, inl = cv2.findHomography(lab.astype(np.float64), pts[idx], cv2.RANSAC, 0.2 * d0)
        if H is None:
            break
        Hi = np.linalg.inv(H)
        q = cv2.perspectiveTransform(pts[None].astype(np.float64), Hi)[0]
        r = np.rint(q)
        core = lab[inl.ravel().astype(bool)] if inl is not None and inl.any() else lab
        lo_l, hi_l = core.min(axis=0), core.max(axis=0)
        # relabel within the block the growth found (points beyond it may be another lattice's)
        good = (np.linalg.norm(q - r, axis=1) < 0.25) & np.all((r >= lo_l) & (r <= hi_l), axis=1)
        # keep one point per label (the closest)
        order = np.argsort(np.linalg.norm(q - r, axis=1))
        seen, keep = set(), []
        for k in order:
            if good[k] and tuple(r[k]) not in seen:
                seen.add(tuple(r[k]))
                keep.append(k)
        keep = np.array(sorted(keep))
        # keep only the connected component that contains the seed label region
        idx, lab = keep, r[keep].astype(int)
    return idx, lab, d0


# ----------------------------------------------------------------------------- labelling
_ROT = [np.array(m) for m in ([[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]])]


def orient_labels(lab: np.ndarray, xy: np.ndarray, shape: tuple[int, int], *, mirrored: bool = False
                  ) -> tuple[np.ndarray, float]:
    """Map lattice labels to (i', j') along the grid's x and y (before the offset).

    The grid seen from above is not mirrored: in image (col, -row) coordinates +x then +y
    turn counter-clockwise (``mirrored`` flips that, for mirror views).  Of the labellings
    the grid's symmetry allows (180 deg, or 90 deg when nx == ny) and that fit its shape,
    the one whose +y points nearest image up wins.  Returns labels and the cosine of the
    angle between grid +y and image up.
    """
    nx, ny = shape
    H, _ = cv2.findHomography(lab.astype(np.float64), xy.astype(np.float64), 0)
    c = lab.mean(axis=0)
    p0 = cv2.perspectiveTransform(np.array([[c]], float), H)[0, 0]
    pa = cv2.perspectiveTransform(np.array([[c + [1, 0]]], float), H)[0, 0] - p0
    pb = cv2.perspectiveTransform(np.array([[c + [0, 1]]], float), H)[0, 0] - p0
    J = np.stack([pa, pb], axis=1)  # image step per label step
    J[1] *= -1  # to (col, up)
    best, best_cos = None, -np.inf
    for flip in (False, True):
        F = np.array([[1, 0], [0, -1]]) if flip else np.eye(2, dtype=int)
        for Rm in _ROT:
            M = Rm @ F  # new = M @ old
            Jn = J @ np.linalg.inv(M)  # image step per new-label step
            det = np.linalg.det(Jn)
            if (det > 0) == mirrored:
                continue
            new = lab @ M.T
            ext = new.max(axis=0) - new.min(axis=0) + 1
            if ext[0] > nx or ext[1] > ny:
                continue
            ey = Jn[:, 1]
            cosv = ey[1] / np.linalg.norm(ey)
            if cosv > best_cos + 1e-9:
                best, best_cos = new, cosv
    if best is None:
        ext = lab.max(axis=0) - lab.min(axis=0) + 1
        raise GridShapeMismatch(f"{ext[0]} x {ext[1]} points were found, more than the stated shape "
                                f"[{nx}, {ny}] allows in any orientation")
    return best, float(best_cos)


def place_labels(new: np.ndarray, xy: np.ndarray, shape: tuple[int, int], image_shape: tuple[int, int],
                 ) -> tuple[np.ndarray | None, list[str]]:
    """Offset oriented labels into 0..nx-1, 0..ny-1 using which sides of the grid are cut.

    Returns (ij or None when ambiguous, notes).
    """
    nx, ny = shape
    H, _ = cv2.findHomography(new.astype(np.float64), xy.astype(np.float64), 0)
    lo, hi = new.min(axis=0), new.max(axis=0)
    h, w = image_shape
    notes = []
    offset = np.zeros(2, int)
    amb = False
    for ax, n in ((0, nx), (1, ny)):
        missing = n - (hi[ax] - lo[ax] + 1)
        if missing == 0:
            offset[ax] = -lo[ax]
            continue
        cut, maybe = [], []
        for side, val in (("low", lo[ax] - 1), ("high", hi[ax] + 1)):
            other = new[new[:, ax] == (lo[ax] if side == "low" else hi[ax])]
            probe = other.astype(float).copy()
            probe[:, ax] = val
            p = cv2.perspectiveTransform(probe[None], H)[0]
            step = np.linalg.norm(p - cv2.perspectiveTransform(other.astype(float)[None], H)[0], axis=1).mean()
            margin = 0.5 * step  # a dot centred nearer the border than this is not found whole
            outside = (p[:, 0] < margin - 0.5) | (p[:, 0] > w - 0.5 - margin) | (p[:, 1] < margin - 0.5) | (p[:, 1] > h - 0.5 - margin)
            cut.append(bool(outside.mean() >= 0.5))
            maybe.append(bool(outside.any()))
        name = "x" if ax == 0 else "y"
        # a side whose next row of points would lie mostly inside the image cannot hide it
        if cut[0] and cut[1]:
            amb = True
        elif cut[0]:
            offset[ax] = -lo[ax] + missing
        elif cut[1]:
            offset[ax] = -lo[ax]
        else:
            raise GridShapeMismatch(f"{hi[ax] - lo[ax] + 1} points are seen along {name} with room in the image "
                                    f"for more, but the stated shape has {n}")
        notes.append(f"{missing} column(s) of points along {name} out of the field")
    if amb:
        return None, notes
    return new + offset, notes


def detect_dots(image: np.ndarray, shape: tuple[int, int], *, mirrored: bool = False) -> Detection:
    """Find and label a dot grid of ``shape`` = [nx, ny] points in one image."""
    unit = to_unit(image)
    best = None
    for pts in candidate_points(unit):
        if len(pts) < 6:
            continue
        try:
            idx, lab, d0 = grow_lattice(pts)
        except GridNotFound:
            continue
        if best is None or len(idx) > len(best[1]):
            best = (pts, idx, lab, d0)
    if best is None or len(best[1]) < 6:
        raise GridNotFound("no regular grid of dots was found among the bright blobs")
    pts, idx, lab, d0 = best
    xy = pts[idx]
    new, _ = orient_labels(lab, xy, shape, mirrored=mirrored)
    ij, notes = place_labels(new, xy, shape, unit.shape)
    n_expected = shape[0] * shape[1]
    if ij is None:
        return Detection(np.zeros((0, 2), int), xy, True, d0, notes, new)
    if len(ij) < n_expected:
        notes.append(f"{len(ij)} of {n_expected} points found")
    return Detection(ij.astype(int), xy, False, d0, notes, new)


def detect_checkerboard(image: np.ndarray, shape: tuple[int, int]) -> Detection:
    """Inner corners of a checkerboard (``shape`` = inner corners [nx, ny]) by ``findChessboardCornersSB``.

    Tried on the image scaled to 8 bit, then (small or blurred boards) upsampled 2x.
    """
    img = np.asarray(image, float)
    if not np.all(np.isfinite(img)):
        raise ValueError("the image holds NaN or infinite values")
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        raise GridNotFound("the image is uniform (no grid visible)")
    img8 = to_uint8((img - lo) / (hi - lo))
    flag_sets = (cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY, cv2.CALIB_CB_NORMALIZE_IMAGE, 0)
    for up in (1, 2):
        src = img8 if up == 1 else cv2.resize(img8, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
        for size in (tuple(shape), tuple(shape[::-1])):
            for flags in flag_sets:
                ok, corners = cv2.findChessboardCornersSB(src, size, flags=flags)
                if not ok:
                    continue
                xy = (corners.reshape(-1, 2).astype(float) + 0.5) / up - 0.5
                n0, n1 = size
                lab = np.stack(np.meshgrid(np.arange(n0), np.arange(n1)), -1).reshape(-1, 2)
                new, _ = orient_labels(lab, xy, shape)
                ij, notes = place_labels(new, xy, shape, img.shape)
                if ij is None:
                    continue
                d0 = float(np.median(np.linalg.norm(np.diff(xy.reshape(n1, n0, 2), axis=1), axis=-1)))
                return Detection(ij.astype(int), xy, False, d0, notes, new)
    raise GridNotFound("no checkerboard with the stated inner-corner shape was found (the whole board must be in view)")


def relabel_from_prediction(det: Detection, predicted_xy: np.ndarray, predicted_ij: np.ndarray) -> Detection:
    """Resolve an ambiguous detection's offset from predicted positions of all grid points."""
    best, best_cost = None, np.inf
    lab = det.lattice_ij
    tree = cKDTree(predicted_xy)
    d, k = tree.query(det.xy_px)
    guess = predicted_ij[k] - lab
    for off in {tuple(g) for g in guess}:
        ij = lab + np.array(off)
        key = {tuple(v): n for n, v in enumerate(predicted_ij)}
        rows = [key.get(tuple(v)) for v in ij]
        if any(r is None for r in rows):
            continue
        cost = np.median(np.linalg.norm(predicted_xy[rows] - det.xy_px, axis=1))
        if cost < best_cost:
            best, best_cost = ij, cost
    if best is None or best_cost > 0.4 * det.spacing_px:
        raise GridNotFound("the partly visible grid could not be matched to the camera fitted on the other images")
    det.ij = best.astype(int)
    det.ambiguous = False
    det.notes.append(f"labels matched to the camera fitted on the other images ({len(best)} points)")
    return det
