"""An independent renderer for checking ``fluxmap reconstruct`` from the outside.

It shares no code with fluxcli (no ``fluxcli`` import at all): plain numpy Monte Carlo
of a Lambertian surface seen through an ideal thin lens, directly and through plane
mirrors, written from DESIGN.md §3 alone.

- Emission: every triangle of the mesh is split into ``k²`` sub-triangles; each ray draws
  its own uniform point in its sub-triangle (stratified, jittered) and carries the power
  ``J(p) dA · cosθ_s cosθ_l A_lens / (π d² K)`` towards one of ``K`` stratified points on
  the lens disk. ``J`` is a continuous exitance field (a Gaussian blob), so the truth per
  element is the integral of ``J`` over its faces, finer than any element.
- Lens: a point imaged through lens point ``l`` lands where the line ``p → l`` meets the
  front focal plane (distance ``u`` in front of the lens); that plane is mapped onto the
  sensor with pixel ``pitch · u / v`` (1/f = 1/u + 1/v); columns run along look × up,
  rows along −up; light outside the sensor is lost. Extra circular apertures in front of
  the lens clip rays.
- Mirrors: the surface point is reflected in the mirror plane and traced to the real
  lens; the ray counts when it crosses the mirror inside its rectangle; its power is
  scaled by the reflectance.
- Occlusion: the subject is convex (a cylinder prism), so a surface point sees along
  every direction its face looks towards; the segments from the mirror to the lens, and
  every segment, are also tested against the stage plate, the mirrors (thin rectangles)
  and the subject by half-space clipping (Cyrus–Beck).
"""

from __future__ import annotations

import numpy as np


# ------------------------------------------------------------------ the subject
def cylinder(*, radius_mm=12.5, length_mm=50.0, n_angular=48, n_axial=24, group=2, axis_z_mm=12.5):
    """A closed cylinder prism along x, its side quads grouped ``group`` x ``group`` into
    elements (caps: one element each), resting with its axis at height ``axis_z_mm``.

    Returns vertices (V, 3), faces (F, 3) wound outward, element (F,) int.
    """
    phi = 2 * np.pi * (np.arange(n_angular) + 0.5) / n_angular  # no vertex exactly on top
    x = np.linspace(-length_mm / 2, length_mm / 2, n_axial + 1)
    ring = np.stack([radius_mm * np.sin(phi), radius_mm * np.cos(phi)], axis=1)
    verts = [[xi, y, z + axis_z_mm] for xi in x for y, z in ring]
    faces, elem = [], []
    ne_x = n_axial // group
    for ix in range(n_axial):
        for ia in range(n_angular):
            a, b = ix * n_angular + ia, ix * n_angular + (ia + 1) % n_angular
            c, d = a + n_angular, b + n_angular
            e = (ia // group) * ne_x + ix // group
            faces += [[a, b, c], [b, d, c]]
            elem += [e, e]
    n_side_el = (n_angular // group) * ne_x
    centre = len(verts)
    verts += [[-length_mm / 2, 0, axis_z_mm], [length_mm / 2, 0, axis_z_mm]]
    for k, ix in enumerate((0, n_axial)):
        for ia in range(n_angular):
            a, b = ix * n_angular + ia, ix * n_angular + (ia + 1) % n_angular
            faces.append([centre + k, a, b])
            elem.append(n_side_el + k)
    verts, faces = np.array(verts, float), np.array(faces)
    # wind every face outward (away from the axis on the side, along ±x on the caps)
    cen = verts[faces].mean(axis=1)
    nrm = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    out = np.c_[np.zeros(len(cen)), cen[:, 1], cen[:, 2] - axis_z_mm]
    cap = np.arange(len(faces)) >= 2 * n_axial * n_angular
    out[cap] = np.c_[np.sign(cen[cap, 0]), np.zeros((cap.sum(), 2))]
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces, np.array(elem)


def convex_planes(verts, faces):
    """Outward half-spaces (normal n, offset d: inside where n·x < d) of a convex mesh's faces."""
    t = verts[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = np.einsum("ij,ij->i", n, t[:, 0])
    key = np.round(np.c_[n, d], 9)
    _, keep = np.unique(key, axis=0, return_index=True)
    return n[keep], d[keep]


def box_planes(lo, hi):
    n = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    d = np.array([hi[0], -lo[0], hi[1], -lo[1], hi[2], -lo[2]], float)
    return n, d


def segment_hits_convex(p0, p1, planes, eps=1e-6):
    """Bool (N,): the open segment p0 → p1 passes through the convex body's interior."""
    n, d = planes
    u = p1 - p0
    t0 = np.full(len(p0), eps)
    t1 = np.full(len(p0), 1 - eps)
    for k in range(len(n)):
        num = d[k] - p0 @ n[k]  # inside: n·(p0 + t u) < d  <=>  t (n·u) < num
        den = u @ n[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        enter = den < 0  # moving inwards across this plane: t > t_k
        leave = den > 0
        t0 = np.where(enter, np.maximum(t0, t), t0)
        t1 = np.where(leave, np.minimum(t1, t), t1)
        outside = (den == 0) & (num <= 0)
        t1 = np.where(outside, -1.0, t1)
    return t0 < t1


# ------------------------------------------------------------------ the optics
class Camera:
    """Ideal thin lens looking along ``look``; ``up`` is at the top of the image."""

    def __init__(self, *, lens_center_mm, look, up, focal_length_mm, f_number, focus_distance_mm,
                 pixels, pixel_pitch_mm, apertures=()):
        self.C = np.asarray(lens_center_mm, float)
        self.n = np.asarray(look, float) / np.linalg.norm(look)
        u = np.asarray(up, float) - np.dot(up, self.n) * self.n
        self.up = u / np.linalg.norm(u)
        self.right = np.cross(self.n, self.up)
        self.f, self.u = float(focal_length_mm), float(focus_distance_mm)
        self.v = 1.0 / (1.0 / self.f - 1.0 / self.u)
        self.R = self.f / (2.0 * f_number)
        self.nx, self.ny = pixels
        self.pix_focal = pixel_pitch_mm * self.u / self.v
        self.apertures = [(float(a["distance_mm"]), float(a["diameter_mm"]) / 2) for a in apertures]

    def lens_points(self, n, K, rng):
        """(n·K, 3): for each of n surface points, K stratified points on the lens disk
        (rings of equal area x angular strata, jittered; K = nr x na)."""
        nr = max(int(round(np.sqrt(K))), 1)
        na = K // nr
        assert nr * na == K, "K must be nr x na"
        i, j = np.divmod(np.arange(K), na)
        r = self.R * np.sqrt((i + rng.random((n, K))) / nr)
        th = 2 * np.pi * (j + rng.random((n, K))) / na + 2 * np.pi * rng.random((n, 1))
        r, th = r.ravel(), th.ravel()
        return self.C + (r * np.cos(th))[:, None] * self.right + (r * np.sin(th))[:, None] * self.up

    def pixel(self, src, lens):
        """Flat pixel index of rays from points ``src`` through lens points (−1: missed)."""
        z = (src - self.C) @ self.n
        q = lens + (self.u / z)[:, None] * (src - lens)
        rel = q - (self.C + self.u * self.n)
        col = np.floor(rel @ self.right / self.pix_focal + self.nx / 2).astype(np.int64)
        row = np.floor(-(rel @ self.up) / self.pix_focal + self.ny / 2).astype(np.int64)
        ok = (col >= 0) & (col < self.nx) & (row >= 0) & (row < self.ny) & (z > 0)
        for dist, rad in self.apertures:  # the ray at axial distance dist in front of the lens
            s = dist / np.where(z > 0, z, 1.0)
            x = lens + s[:, None] * (src - lens) - self.C
            radial = x - (x @ self.n)[:, None] * self.n
            ok &= (np.einsum("ij,ij->i", radial, radial) <= rad * rad) | (s >= 1)
        return np.where(ok, row * self.nx + col, -1)


class Mirror:
    def __init__(self, *, center_mm, normal, axis, size_mm, reflectance=1.0, **_):
        self.c = np.asarray(center_mm, float)
        self.n = np.asarray(normal, float) / np.linalg.norm(normal)
        a = np.asarray(axis, float) - np.dot(axis, self.n) * self.n
        self.a = a / np.linalg.norm(a)
        self.b = np.cross(self.n, self.a)
        self.half = np.asarray(size_mm, float) / 2
        self.rho = float(reflectance)

    def reflect(self, p):
        return p - 2 * ((p - self.c) @ self.n)[:, None] * self.n

    def crossing(self, p0, p1):
        """Parameter t and point where p0 → p1 crosses the plane, and whether inside the rectangle."""
        d0, d1 = (p0 - self.c) @ self.n, (p1 - self.c) @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = d0 / (d0 - d1)
        x = p0 + t[:, None] * (p1 - p0)
        rel = x - self.c
        inside = (np.abs(rel @ self.a) <= self.half[0]) & (np.abs(rel @ self.b) <= self.half[1])
        return t, x, inside & (t > 1e-9) & (t < 1 - 1e-9)


# ------------------------------------------------------------------ rendering
def gaussian_exitance(p, centre_mm, width_mm, peak=1.0):
    """Exitance at points ``p``: ``peak · exp(−|p − c|² / (2 w²))`` (photons mm⁻²)."""
    d2 = np.sum((p - np.asarray(centre_mm, float)) ** 2, axis=1)
    return peak * np.exp(-0.5 * d2 / width_mm**2)


def _subtriangles(tri, k):
    """Corners (F·k², 3, 3) of the k² congruent sub-triangles of each triangle (F, 3, 3)."""
    A, B, C = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = (B - A) / k, (C - A) / k
    out = []
    for i in range(k):
        for j in range(k - i):
            p = A + i * e1 + j * e2
            out.append(np.stack([p, p + e1, p + e2], axis=1))
            if j < k - i - 1:
                out.append(np.stack([p + e1, p + e1 + e2, p + e2], axis=1))
    return np.stack(out, axis=1).reshape(-1, 3, 3)


def render(verts, faces, element, exitance, camera, *, mirrors=(), occluders=(), k=12, K=16, seed=0,
           chunk=200_000):
    """Noiseless image (ny, nx) in photons and the truth per element (photons).

    ``exitance`` maps points (N, 3) to photons mm⁻²; ``element`` (F,) groups faces (−1:
    no element). ``occluders`` are lists of convex half-space sets (see :func:`box_planes`)
    besides the subject itself; mirrors are also thin occluders.
    """
    rng = np.random.default_rng(seed)
    tri = verts[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    nrm /= (2 * area)[:, None]
    subject = convex_planes(verts, faces)
    n_el = int(element.max()) + 1
    image = np.zeros(camera.nx * camera.ny)
    truth = np.zeros(n_el)
    sub = _subtriangles(tri, k)  # (F k², 3, 3)
    face_of_sub = np.repeat(np.arange(len(faces)), k * k)
    sub_area = area[face_of_sub] / (k * k)
    cen = sub.mean(axis=1)
    j_cen = exitance(cen)
    np.add.at(truth, element[face_of_sub], np.where(element[face_of_sub] >= 0, j_cen * sub_area, 0.0))
    live = j_cen > 1e-9 * j_cen.max()
    sub, face_of_sub, sub_area = sub[live], face_of_sub[live], sub_area[live]
    lens_area = np.pi * camera.R**2
    views = [(None, 1.0)] + [(m, m.rho) for m in mirrors]
    thin = list(mirrors)
    for start in range(0, len(sub), max(chunk // K, 1)):
        s = sub[start:start + max(chunk // K, 1)]
        fo = face_of_sub[start:start + len(s)]
        # K jittered points per sub-triangle (uniform in the triangle), one per ray
        r1, r2 = rng.random((len(s), K)), rng.random((len(s), K))
        flip = r1 + r2 > 1
        r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
        p = (s[:, None, 0] + r1[..., None] * (s[:, None, 1] - s[:, None, 0])
             + r2[..., None] * (s[:, None, 2] - s[:, None, 0])).reshape(-1, 3)
        fo = np.repeat(fo, K)
        w_src = exitance(p) * np.repeat(sub_area[start:start + len(s)], K)
        lens = camera.lens_points(len(s), K, rng)
        for mirror, rho in views:
            src = p if mirror is None else mirror.reflect(p)
            d = lens - src
            dist = np.linalg.norm(d, axis=1)
            u = d / dist[:, None]
            cos_l = -(u @ camera.n)
            if mirror is None:
                first_end = lens
                ok = np.ones(len(p), bool)
            else:
                _, m_pt, ok = mirror.crossing(src, lens)
                first_end = m_pt
            out_dir = first_end - p
            cos_s = np.einsum("ij,ij->i", nrm[fo], out_dir) / np.linalg.norm(out_dir, axis=1)
            ok &= (cos_s > 0) & (cos_l > 0)
            pix = camera.pixel(src, lens)
            ok &= pix >= 0
            idx = np.flatnonzero(ok)
            segs = [(p[idx], first_end[idx])]
            if mirror is not None:
                segs.append((first_end[idx], lens[idx]))
            blocked = np.zeros(idx.size, bool)
            for si, (a0, a1) in enumerate(segs):
                for planes in occluders:
                    blocked |= segment_hits_convex(a0, a1, planes)
                if si == 1:  # mirror -> lens may pass through the subject
                    blocked |= segment_hits_convex(a0, a1, subject)
                for other in thin:
                    if other is mirror and si == 0:
                        continue  # the segment ends on this mirror
                    if other is mirror and si == 1:
                        continue  # it starts on it
                    blocked |= other.crossing(a0, a1)[2]
            idx = idx[~blocked]
            w = rho * w_src[idx] * cos_s[idx] * cos_l[idx] * lens_area / (np.pi * dist[idx] ** 2 * K)
            image += np.bincount(pix[idx], weights=w, minlength=image.size)
    return image.reshape(camera.ny, camera.nx), truth


def write_vtk_mesh(path, verts, faces, element):
    """A legacy ASCII VTK PolyData file with an integer cell array ``element``."""
    lines = ["# vtk DataFile Version 4.2", "cylinder with elements", "ASCII", "DATASET POLYDATA",
             f"POINTS {len(verts)} double"]
    lines += [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in verts]
    lines.append(f"POLYGONS {len(faces)} {4 * len(faces)}")
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    lines += [f"CELL_DATA {len(faces)}", "SCALARS element int 1", "LOOKUP_TABLE default"]
    lines += [str(int(e)) for e in element]
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def write_float_tiff(path, image):
    """A 32-bit float TIFF (photons per pixel), written with OpenImageIO."""
    import OpenImageIO as oiio

    img = np.ascontiguousarray(image, dtype=np.float32)
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 1, "float")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise RuntimeError(f"cannot write {path}: {oiio.geterror()}")
    out.write_image(img[:, :, None])  # (height, width, channels)
    out.close()


# ------------------------------------------------------------------ a whole scene, as files
CAMERA = {"pixels": [128, 128], "pixel_pitch_mm": 0.065,
          "lens": {"focal_length_mm": 23.9, "f_number": 2.8, "focus_distance_mm": 317.0},
          "pose": {"lens_center_mm": [0, 0, 338.0], "look": [0, 0, -1], "up": [0, 1, 0]},
          "apertures": [{"distance_mm": 30.0, "diameter_mm": 25.0}]}
MIRRORS = [  # 45 degrees, either side of the subject, bottom edges on the stage
    {"name": "left", "center_mm": [0, -31.14, 14.14], "normal": [0, 1, 1], "axis": [1, 0, 0],
     "size_mm": [70, 40], "reflectance": 0.9},
    {"name": "right", "center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1], "axis": [1, 0, 0],
     "size_mm": [70, 40], "reflectance": 0.9},
]
STAGE = {"top_z_mm": 0.0, "size_mm": [100, 34], "thickness_mm": 5}


def blob_scene(folder, *, mirrors: bool, max_snr: float = 30.0, n_angular=48, n_axial=24, k=12, K=16,
               blob_centre_deg=20.0, blob_x_mm=4.0, width_mm=6.0, seed=1, camera=None, noise_draw=0):
    """Render the Gaussian-blob cylinder (direct view, or with two 45° mirrors), add Poisson
    noise at ``max_snr`` (√ of the brightest pixel's expected photons) and write what a user
    has: ``cylinder.vtk`` (integer cell array ``element``), ``image.tif`` (photons) and
    ``fluxmap.yaml`` reading them. Returns (config path, truth per element in photons of
    the exposure, noiseless image). ``noise_draw`` picks another Poisson draw of the same
    rendering."""
    from pathlib import Path

    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cam_cfg = dict(camera or CAMERA)
    verts, faces, element = cylinder(n_angular=n_angular, n_axial=n_axial, group=2)
    R = 12.5
    ang = np.deg2rad(blob_centre_deg)  # from the top towards +y
    centre = [blob_x_mm, R * np.sin(ang), 12.5 + R * np.cos(ang)]
    cam = Camera(**cam_cfg["pose"], **cam_cfg["lens"], pixels=cam_cfg["pixels"],
                 pixel_pitch_mm=cam_cfg["pixel_pitch_mm"], apertures=cam_cfg.get("apertures", ()))
    mir = [Mirror(**m) for m in MIRRORS] if mirrors else []
    lo = [-STAGE["size_mm"][0] / 2, -STAGE["size_mm"][1] / 2, STAGE["top_z_mm"] - STAGE["thickness_mm"]]
    hi = [STAGE["size_mm"][0] / 2, STAGE["size_mm"][1] / 2, STAGE["top_z_mm"]]
    clean, truth = render(verts, faces, element, lambda p: gaussian_exitance(p, centre, width_mm), cam,
                          mirrors=mir, occluders=[box_planes(lo, hi)], k=k, K=K, seed=seed)
    scale = max_snr**2 / clean.max()  # photons per unit exitance, so that sqrt(max a) = max_snr
    clean, truth = clean * scale, truth * scale
    noisy = np.random.default_rng(seed + 1000 + 7919 * noise_draw).poisson(clean).astype(np.float32)
    write_vtk_mesh(folder / "cylinder.vtk", verts, faces, element)
    write_float_tiff(folder / "image.tif", noisy)
    cfg = {"workdir": "run",
           "system": {"camera": cam_cfg, "mirrors": MIRRORS if mirrors else [], "stage": STAGE},
           "subject": {"surface": {"mesh": "cylinder.vtk"}},
           "reconstruct": {"images": {"files": ["image.tif"], "units": "photons"}}}
    path = folder / "fluxmap.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path, truth, clean


# ------------------------------------------------------------------ issue 25's scene
# A cylinder r 12.5 mm x 50 mm with its axis along y (centred at the origin), a thin lens
# 317 mm above the axis, optionally two 45-degree mirrors at x = +-40 mm. The reconstruction
# mesh is a 96-gon prism (the user's file); the images come from the *true* cylinder (a
# smooth surface, normals radial) seen by a camera displaced within calibration errors:
# the model fluxmap inverts is never the one that made the images.
SCENE25_CAMERA = {"pixels": [256, 256], "pixel_pitch_mm": 0.052,
                  "lens": {"focal_length_mm": 23.9, "aperture_diameter_mm": 10.0, "focus_distance_mm": 317.0},
                  "pose": {"lens_center_mm": [0.0, 0.0, 317.0], "look": [0, 0, -1], "up": [0, 1, 0]}}
SCENE25_MIRRORS = [
    {"name": "right", "center_mm": [40.0, 0.0, 0.0], "normal": [-0.7071067811865476, 0.0, 0.7071067811865476],
     "axis": [0, 1, 0], "size_mm": [80, 50], "reflectance": 1.0},
    {"name": "left", "center_mm": [-40.0, 0.0, 0.0], "normal": [0.7071067811865476, 0.0, 0.7071067811865476],
     "axis": [0, 1, 0], "size_mm": [80, 50], "reflectance": 1.0},
]
# What the renderer's camera differs by from the config's (within what a grid calibration
# leaves, DESIGN §6: lens centre to ~0.1 mm across, ~0.5 mm along the axis, f to ~0.2 %,
# the in-plane rotation to ~0.1 degree).
SCENE25_PERTURBATION = {"lens_center_mm": [0.08, -0.06, 0.4], "focal_length_factor": 1.002, "roll_deg": 0.1}


def cylinder_y(*, radius_mm=12.5, length_mm=50.0, n_angular=96, n_axial=48, cap_bands=6, group=2,
               cap_sectors=4, cap_rings=2):
    """The issue-25 reconstruction mesh: a closed ``n_angular``-gon prism along y, centred at
    the origin; side quads grouped ``group`` x ``group`` into elements, each cap ``cap_bands``
    rings of triangles grouped into ``cap_sectors`` x ``cap_rings`` elements.

    Angle φ is measured from +z towards +x (a vertex on top); side element
    ``(ia // group) * (n_axial // group) + iy // group``; then per cap (−y, +y)
    ``sector * cap_rings + ring``. Defaults: 5666 vertices, 11328 triangles, 1168 elements.

    Returns vertices (V, 3), faces (F, 3) wound outward, element (F,) int.
    """
    R, L = float(radius_mm), float(length_mm)
    phi = 2 * np.pi * np.arange(n_angular) / n_angular
    ys = np.linspace(-L / 2, L / 2, n_axial + 1)
    verts = [[R * np.sin(p), y, R * np.cos(p)] for y in ys for p in phi]
    faces, elem = [], []
    ne_y = n_axial // group
    for iy in range(n_axial):
        for ia in range(n_angular):
            a, b = iy * n_angular + ia, iy * n_angular + (ia + 1) % n_angular
            c, d = a + n_angular, b + n_angular
            e = (ia // group) * ne_y + iy // group
            faces += [[a, b, c], [b, d, c]]
            elem += [e, e]
    n_side = (n_angular // group) * ne_y
    per_sector = n_angular // cap_sectors
    per_ring = cap_bands // cap_rings
    for k, (iy_edge, y) in enumerate(((0, -L / 2), (n_axial, L / 2))):
        base = len(verts)
        verts.append([0.0, y, 0.0])
        # interior rings 1..cap_bands-1; ring cap_bands is the side's edge ring
        for band in range(1, cap_bands):
            r = R * band / cap_bands
            verts += [[r * np.sin(p), y, r * np.cos(p)] for p in phi]

        def ring_vertex(band, ia):
            if band == cap_bands:
                return iy_edge * n_angular + ia % n_angular
            return base + 1 + (band - 1) * n_angular + ia % n_angular

        for ia in range(n_angular):
            e0 = n_side + k * cap_sectors * cap_rings + (ia // per_sector) * cap_rings
            faces.append([base, ring_vertex(1, ia), ring_vertex(1, ia + 1)])
            elem.append(e0)
            for band in range(1, cap_bands):
                e = e0 + band // per_ring
                a, b = ring_vertex(band, ia), ring_vertex(band, ia + 1)
                c, d = ring_vertex(band + 1, ia), ring_vertex(band + 1, ia + 1)
                faces += [[a, b, c], [b, d, c]]
                elem += [e, e]
    verts, faces = np.array(verts, float), np.array(faces)
    cen = verts[faces].mean(axis=1)
    nrm = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    out = np.c_[cen[:, 0], np.zeros(len(cen)), cen[:, 2]]
    cap = np.arange(len(faces)) >= 2 * n_axial * n_angular
    out[cap] = np.c_[np.zeros(cap.sum()), np.sign(cen[cap, 1]), np.zeros(cap.sum())]
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces, np.array(elem)


def true_cylinder_samples(*, radius_mm=12.5, length_mm=50.0, n_el_angular=48, n_el_axial=24, cap_sectors=4,
                          cap_rings=2, n_phi=768, n_y=384, n_theta=768, n_r=96, rng=None):
    """Jittered stratified points on the *smooth* cylinder (axis y), with their outward
    normals, the area each stands for (mm²) and the element of :func:`cylinder_y` whose
    angular / axial / radial range holds them (elements are bins of φ, y and r, so the
    truth per element is an integral over the true surface, not over the prism's facets)."""
    rng = rng or np.random.default_rng(0)
    R, L = float(radius_mm), float(length_mm)
    i, j = np.meshgrid(np.arange(n_phi), np.arange(n_y), indexing="ij")
    phi = 2 * np.pi * (i.ravel() + rng.random(i.size)) / n_phi
    y = -L / 2 + L * (j.ravel() + rng.random(j.size)) / n_y
    side_p = np.c_[R * np.sin(phi), y, R * np.cos(phi)]
    side_n = np.c_[np.sin(phi), np.zeros(phi.size), np.cos(phi)]
    side_w = np.full(phi.size, 2 * np.pi * R * L / phi.size)
    ia = np.minimum((phi / (2 * np.pi) * n_el_angular).astype(int), n_el_angular - 1)
    iy = np.minimum(((y + L / 2) / L * n_el_axial).astype(int), n_el_axial - 1)
    side_e = ia * n_el_axial + iy
    n_side = n_el_angular * n_el_axial
    pts, nrm, w, el = [side_p], [side_n], [side_w], [side_e]
    for k, sign in enumerate((-1.0, 1.0)):
        i, j = np.meshgrid(np.arange(n_theta), np.arange(n_r), indexing="ij")
        th = 2 * np.pi * (i.ravel() + rng.random(i.size)) / n_theta
        r = R * np.sqrt((j.ravel() + rng.random(j.size)) / n_r)  # equal-area rings
        pts.append(np.c_[r * np.sin(th), np.full(th.size, sign * L / 2), r * np.cos(th)])
        nrm.append(np.tile([0.0, sign, 0.0], (th.size, 1)))
        w.append(np.full(th.size, np.pi * R * R / th.size))
        sector = np.minimum((th / (2 * np.pi) * cap_sectors).astype(int), cap_sectors - 1)
        ring = np.minimum((r / R * cap_rings).astype(int), cap_rings - 1)
        el.append(n_side + k * cap_sectors * cap_rings + sector * cap_rings + ring)
    return np.concatenate(pts), np.concatenate(nrm), np.concatenate(w), np.concatenate(el)


def segment_hits_cylinder_y(p0, p1, radius_mm, length_mm, eps=1e-6):
    """Bool (N,): the open segment p0 → p1 passes through the inside of the solid cylinder
    |(x, z)| < r, |y| < L/2."""
    d = p1 - p0
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (p0[:, 0] * d[:, 0] + p0[:, 2] * d[:, 2])
    c = p0[:, 0] ** 2 + p0[:, 2] ** 2 - radius_mm**2
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        t_in, t_out = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
        # parallel to the axis: inside the infinite cylinder for all t or for none
        t_in = np.where(a > 0, t_in, np.where(c < 0, -np.inf, np.inf))
        t_out = np.where(a > 0, t_out, np.where(c < 0, np.inf, -np.inf))
        ty0, ty1 = (-length_mm / 2 - p0[:, 1]) / d[:, 1], (length_mm / 2 - p0[:, 1]) / d[:, 1]
    ylo = np.where(d[:, 1] != 0, np.minimum(ty0, ty1), np.where(np.abs(p0[:, 1]) < length_mm / 2, -np.inf, np.inf))
    yhi = np.where(d[:, 1] != 0, np.maximum(ty0, ty1), np.where(np.abs(p0[:, 1]) < length_mm / 2, np.inf, -np.inf))
    lo = np.maximum(np.maximum(t_in, ylo), eps)
    hi = np.minimum(np.minimum(t_out, yhi), 1 - eps)
    return (disc > 0) & (lo < hi)


def render_points(p, nrm, w_area, exitance, camera, *, mirrors=(), blocks_subject=None, K=16, seed=0,
                  chunk=400_000):
    """Noiseless image (ny, nx) in photons of surface points ``p`` (N, 3) with outward
    normals ``nrm`` each standing for ``w_area`` mm² of a *convex* subject (a point sees
    every direction its normal faces). ``blocks_subject(a0, a1)`` tells whether a segment
    from a mirror to the lens passes through the subject; mirrors are thin occluders."""
    rng = np.random.default_rng(seed)
    image = np.zeros(camera.nx * camera.ny)
    lens_area = np.pi * camera.R**2
    views = [(None, 1.0)] + [(m, m.rho) for m in mirrors]
    step = max(chunk // K, 1)
    for start in range(0, len(p), step):
        ps = np.repeat(p[start:start + step], K, axis=0)
        ns = np.repeat(nrm[start:start + step], K, axis=0)
        w_src = np.repeat(exitance(p[start:start + step]) * w_area[start:start + step], K)
        lens = camera.lens_points(len(ps) // K, K, rng)
        for mirror, rho in views:
            src = ps if mirror is None else mirror.reflect(ps)
            d = lens - src
            dist = np.linalg.norm(d, axis=1)
            cos_l = -((d / dist[:, None]) @ camera.n)
            if mirror is None:
                first_end, ok = lens, np.ones(len(ps), bool)
            else:
                _, first_end, ok = mirror.crossing(src, lens)
            out_dir = first_end - ps
            cos_s = np.einsum("ij,ij->i", ns, out_dir) / np.linalg.norm(out_dir, axis=1)
            pix = camera.pixel(src, lens)
            ok &= (cos_s > 0) & (cos_l > 0) & (pix >= 0)
            idx = np.flatnonzero(ok)
            blocked = np.zeros(idx.size, bool)
            for other in mirrors:
                if other is not mirror:
                    blocked |= other.crossing(ps[idx], first_end[idx])[2]
                    if mirror is not None:
                        blocked |= other.crossing(first_end[idx], lens[idx])[2]
            if mirror is not None and blocks_subject is not None:
                blocked |= blocks_subject(first_end[idx], lens[idx])
            idx = idx[~blocked]
            wt = rho * w_src[idx] * cos_s[idx] * cos_l[idx] * lens_area / (np.pi * dist[idx] ** 2 * K)
            image += np.bincount(pix[idx], weights=wt, minlength=image.size)
    return image.reshape(camera.ny, camera.nx)


def perturbed_camera(cam_cfg, perturbation=None) -> "Camera":
    """The renderer's camera: ``cam_cfg`` (a ``system.camera`` block) displaced by
    ``perturbation`` (lens centre offset mm, focal-length factor, roll about the look
    direction in degrees); None: exactly the config's camera."""
    pert = perturbation or {}
    lens = cam_cfg["lens"]
    f = lens["focal_length_mm"] * pert.get("focal_length_factor", 1.0)
    f_number = lens["f_number"] if "f_number" in lens else lens["focal_length_mm"] / lens["aperture_diameter_mm"]
    pose = cam_cfg["pose"]
    look = np.asarray(pose["look"], float)
    look /= np.linalg.norm(look)
    up = np.asarray(pose["up"], float)
    a = np.deg2rad(pert.get("roll_deg", 0.0))
    up = up * np.cos(a) + np.cross(look, up) * np.sin(a) + look * np.dot(look, up) * (1 - np.cos(a))
    # the aperture diameter is what a calibration measures; keep it, not the f-number
    return Camera(lens_center_mm=np.asarray(pose["lens_center_mm"], float) + np.asarray(pert.get("lens_center_mm", 0.0)),
                  look=look, up=up, focal_length_mm=f, f_number=f_number * f / lens["focal_length_mm"],
                  focus_distance_mm=lens["focus_distance_mm"], pixels=cam_cfg["pixels"],
                  pixel_pitch_mm=cam_cfg["pixel_pitch_mm"], apertures=cam_cfg.get("apertures", ()))


def write_vtp_mesh(path, verts, faces, element):
    """A VTK XML PolyData file (ASCII) with an integer cell array ``element``."""
    def block(values, fmt):
        return "\n".join(fmt.format(*row) if np.ndim(row) else fmt.format(row) for row in values)

    offsets = 3 * np.arange(1, len(faces) + 1)
    text = f"""<?xml version="1.0"?>
<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">
<PolyData><Piece NumberOfPoints="{len(verts)}" NumberOfPolys="{len(faces)}">
<Points><DataArray type="Float64" NumberOfComponents="3" format="ascii">
{block(verts, "{:.12g} {:.12g} {:.12g}")}
</DataArray></Points>
<Polys><DataArray type="Int64" Name="connectivity" format="ascii">
{block(faces, "{} {} {}")}
</DataArray><DataArray type="Int64" Name="offsets" format="ascii">
{block(offsets, "{}")}
</DataArray></Polys>
<CellData Scalars="element"><DataArray type="Int32" Name="element" format="ascii">
{block(element, "{}")}
</DataArray></CellData>
</Piece></PolyData></VTKFile>
"""
    with open(path, "w") as fh:
        fh.write(text)


def scene25(folder, *, mirrors: bool, peak_photons: float = 2e4, noise_draw: int | None = 0, seed: int = 25,
            blob_centre_mm=(0.0, 4.0, 12.5), width_mm: float = 6.0, perturbation=SCENE25_PERTURBATION,
            n_phi: int = 768, n_y: int = 384, K: int = 16, mesh=None, camera=None):
    """Issue 25's scene as a user's files: ``cylinder.vtp`` (96-gon prism, 1168 elements),
    ``image.tif`` (float32 photons, Poisson at a ``peak_photons`` brightest pixel; noiseless
    when ``noise_draw`` is None), ``fluxmap.yaml``. Rendered on the smooth cylinder with a
    perturbed camera. Returns (config path, truth per element in photons, noiseless image).
    The noiseless rendering is cached in the folder (``clean.npz``) so that noise draws of
    the same scene cost nothing."""
    from pathlib import Path

    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cam_cfg = dict(camera or SCENE25_CAMERA)
    verts, faces, element = mesh or cylinder_y()
    cache = folder / f"clean_{'mirrors' if mirrors else 'direct'}.npz"
    if cache.exists():
        z = np.load(cache)
        clean, truth = z["clean"], z["truth"]
    else:
        rng = np.random.default_rng(seed)
        p, nrm, w, el = true_cylinder_samples(n_phi=n_phi, n_y=n_y, rng=rng)

        def exitance(q):
            return gaussian_exitance(q, blob_centre_mm, width_mm)

        truth = np.bincount(el, weights=exitance(p) * w, minlength=int(element.max()) + 1)
        cam = perturbed_camera(cam_cfg, perturbation)
        mir = [Mirror(**m) for m in SCENE25_MIRRORS] if mirrors else []
        clean = render_points(p, nrm, w, exitance, cam, mirrors=mir, K=K, seed=seed + 1,
                              blocks_subject=lambda a0, a1: segment_hits_cylinder_y(a0, a1, 12.5, 50.0))
        scale = peak_photons / clean.max()
        clean, truth = clean * scale, truth * scale
        np.savez(cache, clean=clean, truth=truth)
    scale = peak_photons / clean.max()
    clean, truth = clean * scale, truth * scale
    image = clean if noise_draw is None else np.random.default_rng(
        seed + 1000 + 7919 * noise_draw).poisson(clean).astype(np.float32)
    write_vtp_mesh(folder / "cylinder.vtp", verts, faces, element)
    write_float_tiff(folder / "image.tif", image)
    cfg = {"workdir": "run",
           "system": {"camera": cam_cfg, "mirrors": SCENE25_MIRRORS if mirrors else []},
           "subject": {"surface": {"mesh": "cylinder.vtp"}},
           "reconstruct": {"images": {"files": ["image.tif"], "units": "photons"}}}
    path = folder / "fluxmap.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path, truth, clean
