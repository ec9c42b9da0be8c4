"""The compiled inner loop of the ``lens`` estimator: one pass per ray, T straight into columns.

For a run of surface samples sorted by element, :func:`lens_columns` makes every ray
(surface point x lens point), weighs it, maps it to its pixel, tests the extra apertures
and the mirror window, casts it through Embree (GIL released) and adds its weight into
the element's column; when the element ends its column is written out, pixels sorted.
Nothing per ray is stored: memory is O(pixels) scratch per thread plus the output.

Columns are summed in a fixed order (samples in order, lens samples in order), so the
bytes do not depend on threads or timing.  Each ray also goes into one of two halves
(even / odd lens sample); ``sum_pixels |half_even - half_odd|`` per column is the error
estimate stored with T (:mod:`fluxcli.optics.transfer`).  Segments known to be clear
(:mod:`fluxcli.optics.visibility`) are not cast but added in the same order; with an error
target an element is cast in doubling rounds until its estimate meets it.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .embree_native import new_packet, packet_cast, packet_put

_QUEUE = 64  # rays queued before a flush (known-clear ones need no packet slot)

_F8 = np.float64
# The camera as the kernel reads it (one record: numba reads a field at a fixed offset, as it
# read a slot of the array this replaces): lens centre, optical axis (towards the subject), the
# sensor's right and down directions (world, unit), the focus distance u (mm), a pixel's pitch
# on the focal plane (mm) and the lens aperture's radius squared (mm^2).
CAMERA = np.dtype([("center_x", _F8), ("center_y", _F8), ("center_z", _F8),
                   ("axis_x", _F8), ("axis_y", _F8), ("axis_z", _F8),
                   ("right_x", _F8), ("right_y", _F8), ("right_z", _F8),
                   ("down_x", _F8), ("down_y", _F8), ("down_z", _F8),
                   ("focus_distance_mm", _F8), ("focal_pixel_mm", _F8), ("aperture_radius2_mm2", _F8)])
# The mirror of a mirror view: ``present`` 0 for the direct view (then nothing else is read),
# its centre (mm), unit normal, the two unit in-plane axes and the half sizes along them (mm).
MIRROR = np.dtype([("present", _F8), ("center_x", _F8), ("center_y", _F8), ("center_z", _F8),
                   ("normal_x", _F8), ("normal_y", _F8), ("normal_z", _F8),
                   ("axis_u_x", _F8), ("axis_u_y", _F8), ("axis_u_z", _F8),
                   ("axis_v_x", _F8), ("axis_v_y", _F8), ("axis_v_z", _F8),
                   ("half_u_mm", _F8), ("half_v_mm", _F8)])


def camera_record(cam) -> np.record:
    """The :data:`CAMERA` record of a :class:`fluxcli.optics.camera.ThinLensCamera`."""
    rec = np.zeros(1, CAMERA)
    rec[0] = (*cam.center_mm, *cam.axis, *cam.right, *cam.down, cam.focus_distance_mm, cam.focal_pixel_mm,
              cam.aperture_radius_mm**2)
    return rec[0]


def mirror_record(mirror) -> np.record:
    """The :data:`MIRROR` record of a :class:`fluxcli.optics.camera.PlaneMirror`, or of no mirror (None)."""
    rec = np.zeros(1, MIRROR)
    if mirror is not None:
        rec[0] = (1.0, *mirror.center_mm, *mirror.normal, *mirror.axis_u, *mirror.axis_v, *mirror.half_size_mm)
    return rec[0]


@nb.njit(nogil=True, cache=True)
def lens_columns(fn16, scene, cam, mirror, ap_dist, ap_r2, eps,
                 points, normals, edges, ray_area, element, box_lo, box_hi, disk_center, disk_radius, use_box,
                 n_lens, pat_off,
                 disk_unit, square_unit, jitter, s0, s1, n_pix, nx, ny,
                 acc_even, acc_odd, mark, touched, record, clear, margin, target, n_cap, spin,
                 emis, tang, acc_t, tframe):
    """Columns of the elements whose samples are ``[s0, s1)`` (whole elements, sorted).

    Parameters
    ----------
    fn16, scene : addresses of rtcOccluded16 and of the scene
        (:attr:`fluxcli.optics.raycast.OcclusionScene.native`).
    cam : a :data:`CAMERA` record (:func:`camera_record`).
    mirror : a :data:`MIRROR` record (:func:`mirror_record`; ``present`` 0 for the direct view).
    ap_dist, ap_r2 : extra apertures: distance (mm) and radius^2 (mm^2).
    points, normals, edges : per surface sample its point (S, 3) mm, the face's unit normal (S, 3)
        and the two edges of its sub-triangle (S, 2, 3) mm (each ray jitters its own point in it).
    ray_area : lens-plane area per lens sample x the sample's fraction of its element's area (S,) mm^2.
    element : element of each sample (S,), non-decreasing over ``[s0, s1)``.
    box_lo, box_hi, disk_center, disk_radius, use_box : per sample its lens sampling region in
        lens-plane coordinates (right, down; mm): the box of lens points whose rays reach the
        sensor (S, 2), the disk of the aperture seen from the sample (centre (S, 2), radius (S,)),
        and whether the box (True) or the disk is sampled.
    n_lens, pat_off : lens samples per surface sample, and where its pattern starts.
    disk_unit, square_unit, jitter : the patterns (M, 2), concatenated per count.
    acc_even, acc_odd, mark, touched : per-thread scratch of n_pix (zero / False on entry,
        left so on exit).
    record : float32 (R, 7), usually (0, 7): the first R segments cast are written here
        (origin, unit direction, length) so that a benchmark can cast the very same rays
        through embreex.
    clear : uint8 (S,): bit 1 when every surface -> lens (surface -> mirror) segment of the
        sample is known clear, bit 2 when every mirror -> lens segment is
        (:func:`fluxcli.optics.visibility.clear_faces`); those segments are not cast.
    margin : mm; a mirror segment is taken as known clear only when it ends at least
        2 x ``margin`` in front of the mirror plane (its offset is not lost to rounding).
    spin : float64 (S, 4): per sample, the cosine and sine of the turn given to its disk
        pattern and the shift (mod 1) given to its square pattern, so that the samples of an
        element do not all use the same lens points (their lens errors then average out).
    emis : float64 (M,): the emission profile's ray weights pi p(theta_s) on cos theta_s =
        i / (M - 1) (:class:`fluxcli.optics.emission.Profile`), or (0,) for Lambertian (weight 1:
        no multiplication, the arithmetic of a Lambertian T is unchanged).  theta_s is the
        angle at the real surface between its normal and the ray leaving it (for a mirror view
        the ray towards the virtual lens point runs along the real surface -> mirror segment).
    tang, acc_t, tframe : the tangential-flux term (:attr:`fluxcli.optics.emission.Profile.tangent`):
        ray weights ``pi p g`` (mm) on the same cos grid, or (0,) when off; per-thread scratch
        (n_pix, 2) (zero on entry, left so), or (0, 2) when off; and per sample the two in-plane
        unit vectors of its face (S, 2, 3) (:func:`fluxcli.optics.emission.face_frames`: they
        turn with the subject, so the values do not depend on the pose's placement).  Each ray
        adds its geometric weight x ``tang(cos theta_s)`` x the components of its unit direction
        leaving the real surface along those two vectors into the pixel's 2-vector: the
        column's ``-grad_t M . (that)`` (times the face area) is the light the term sends there.
        The scalar weights are computed exactly as without it.
    target, n_cap : adaptive sampling.  An element's samples are cast in rounds: round 0
        takes lens samples ``[0, n_lens)`` of each sample's nested pattern, round p
        ``[n_lens 2^(p-1), n_lens 2^p)`` (the weights of all rounds so far halved, exactly);
        after each round the column's error estimate ``sum |even - odd|`` is compared with
        ``target`` x the column sum, and the element stops once it is met or when another
        round would exceed ``n_cap`` lens samples for one of its samples (``target <= 0``:
        one round).  The patterns must hold ``n_cap`` points from ``pat_off``.

    Returns
    -------
    (elements (K,), column starts (K + 1,), pixel (nnz,), value (nnz,), column error (K,),
    rays cast, rays evaluated, segments recorded, tangential values (nnz, 2) or (0, 2) when off)
    """
    pk, pku, valid = new_packet()
    pk2, pku2, _ = new_packet()
    seg2 = np.empty((_QUEUE, 7), np.float64)  # mirror views: the mirror -> lens segment of each queued ray
    q_pix = np.empty(_QUEUE, np.int64)
    q_w = np.empty(_QUEUE, np.float64)
    use_t = len(tang) > 0
    q_t = np.zeros((_QUEUE, 2), np.float64)  # the tangential weights of each queued ray (face frame)
    q_odd = np.empty(_QUEUE, np.int64)
    q_slot = np.empty(_QUEUE, np.int64)  # the ray's slot in the packet, -1 when known clear
    q_need2 = np.empty(_QUEUE, np.bool_)  # mirror views: the mirror -> lens segment must be cast
    m = 0  # rays queued
    n_slot = 0  # of them, in the packet
    cx, cy, cz = cam.center_x, cam.center_y, cam.center_z
    ax, ay, az = cam.axis_x, cam.axis_y, cam.axis_z
    rx, ry, rz = cam.right_x, cam.right_y, cam.right_z
    dx_, dy_, dz_ = cam.down_x, cam.down_y, cam.down_z
    u, pf, R2 = cam.focus_distance_mm, cam.focal_pixel_mm, cam.aperture_radius2_mm2
    fx, fy, fz = cx + u * ax, cy + u * ay, cz + u * az  # focal-plane centre
    has_mirror = mirror.present > 0
    mcx, mcy, mcz = mirror.center_x, mirror.center_y, mirror.center_z
    mnx, mny, mnz = mirror.normal_x, mirror.normal_y, mirror.normal_z
    mux, muy, muz, half_u = mirror.axis_u_x, mirror.axis_u_y, mirror.axis_u_z, mirror.half_u_mm
    mvx, mvy, mvz, half_v = mirror.axis_v_x, mirror.axis_v_y, mirror.axis_v_z, mirror.half_v_mm
    n_rays = 0
    for s in range(s0, s1):
        n_rays += n_lens[s]
    cap = max(n_rays, 1)  # grows when later rounds touch more pixels
    out_pix = np.empty(cap, np.int32)
    out_val = np.empty(cap, np.float64)
    out_t = np.empty((cap if use_t else 0, 2), np.float64)
    n_el = 1
    for s in range(s0 + 1, s1):
        if element[s] != element[s - 1]:
            n_el += 1
    elements = np.empty(n_el, np.int64)
    starts = np.zeros(n_el + 1, np.int64)
    col_err = np.zeros(n_el, np.float64)
    n_touched = 0
    nnz = 0
    k_el = 0
    cast = 0
    n_rec = 0
    n_rays = 0
    e0 = s0  # the element's samples are [e0, e1)
    while e0 < s1:
        e1 = e0 + 1
        while e1 < s1 and element[e1] == element[e0]:
            e1 += 1
        last_round = 0
        if target > 0:
            last_round = 62
            for s in range(e0, e1):
                q = 0
                while (n_lens[s] << (q + 1)) <= n_cap:
                    q += 1
                last_round = min(last_round, q)
        rnd = 0
        while True:
            scale = 1.0 / (1 << rnd)
            for s in range(e0, e1):
                px, py, pz = points[s, 0], points[s, 1], points[s, 2]
                nx_, ny_, nz_ = normals[s, 0], normals[s, 1], normals[s, 2]
                lens_start = 0 if rnd == 0 else n_lens[s] << (rnd - 1)
                lens_end = n_lens[s] << rnd
                n_rays += lens_end - lens_start
                base = pat_off[s]
                r = disk_radius[s]
                dA_s = ray_area[s] * scale
                clear1 = (clear[s] & 1) != 0
                clear2 = (clear[s] & 2) != 0
                for i_lens in range(lens_start, lens_end):
                    # the lens point, in lens-plane coordinates (right, down) then in the world
                    if use_box[s]:
                        ux_ = square_unit[base + i_lens, 0] + spin[s, 2]
                        uy_ = square_unit[base + i_lens, 1] + spin[s, 3]
                        ux_ -= math.floor(ux_)
                        uy_ -= math.floor(uy_)
                        ox2 = box_lo[s, 0] + (box_hi[s, 0] - box_lo[s, 0]) * ux_
                        oy2 = box_lo[s, 1] + (box_hi[s, 1] - box_lo[s, 1]) * uy_
                        ex, ey = ox2 - disk_center[s, 0], oy2 - disk_center[s, 1]
                        if ex * ex + ey * ey > r * r:
                            continue
                    else:
                        du, dv = disk_unit[base + i_lens, 0], disk_unit[base + i_lens, 1]
                        ox2 = disk_center[s, 0] + r * (spin[s, 0] * du - spin[s, 1] * dv)
                        oy2 = disk_center[s, 1] + r * (spin[s, 1] * du + spin[s, 0] * dv)
                    offx = ox2 * rx + oy2 * dx_
                    offy = ox2 * ry + oy2 * dy_
                    offz = ox2 * rz + oy2 * dz_
                    if offx * offx + offy * offy + offz * offz > R2:
                        continue
                    Lx, Ly, Lz = cx + offx, cy + offy, cz + offz
                    # the surface point: this ray's own point of the sample's sub-triangle
                    ja, jb = jitter[base + i_lens, 0], jitter[base + i_lens, 1]
                    qx = px + ja * edges[s, 0, 0] + jb * edges[s, 1, 0]
                    qy = py + ja * edges[s, 0, 1] + jb * edges[s, 1, 1]
                    qz = pz + ja * edges[s, 0, 2] + jb * edges[s, 1, 2]
                    vx, vy, vz = Lx - qx, Ly - qy, Lz - qz
                    r2 = vx * vx + vy * vy + vz * vz
                    inv = 1.0 / math.sqrt(r2)
                    cos_s = (nx_ * vx + ny_ * vy + nz_ * vz) * inv
                    if not cos_s > 0:
                        continue
                    cos_l = -(vx * ax + vy * ay + vz * az) * inv
                    w = cos_s * cos_l / (math.pi * r2) * dA_s
                    wt = 0.0
                    if use_t:
                        wt = w * emission_weight(tang, cos_s) * inv
                    if len(emis) > 0:
                        w *= emission_weight(emis, cos_s)
                    if not w > 0:
                        continue
                    # the pixel: where the line meets the front focal plane
                    zz = (qx - cx) * ax + (qy - cy) * ay + (qz - cz) * az
                    t = u / zz
                    hx, hy, hz = Lx + t * (qx - Lx) - fx, Ly + t * (qy - Ly) - fy, Lz + t * (qz - Lz) - fz
                    col = (hx * rx + hy * ry + hz * rz) / pf + nx / 2
                    row = (hx * dx_ + hy * dy_ + hz * dz_) / pf + ny / 2
                    if not (col >= 0 and row >= 0 and col < nx and row < ny):
                        continue
                    pix = int(math.floor(row)) * nx + int(math.floor(col))
                    # beta: inside every extra aperture nearer the lens than the point
                    ok = True
                    for a in range(len(ap_dist)):
                        sa = ap_dist[a] / zz
                        if sa >= 1:
                            continue
                        x0 = Lx + sa * (qx - Lx) - cx
                        x1 = Ly + sa * (qy - Ly) - cy
                        x2 = Lz + sa * (qz - Lz) - cz
                        along = x0 * ax + x1 * ay + x2 * az
                        q0, q1, q2 = x0 - along * ax, x1 - along * ay, x2 - along * az
                        if q0 * q0 + q1 * q1 + q2 * q2 > ap_r2[a]:
                            ok = False
                            break
                    if not ok:
                        continue
                    # alpha: the segment(s) to the lens are clear, cast 16 at a time (rays of one
                    # surface point are coherent: one packet traversal costs far less than 16 rays)
                    Ox, Oy, Oz = qx + eps * nx_, qy + eps * ny_, qz + eps * nz_
                    ux, uy, uz = Lx - Ox, Ly - Oy, Lz - Oz
                    if not has_mirror:
                        if clear1:
                            q_slot[m] = -1
                        else:
                            length = math.sqrt(ux * ux + uy * uy + uz * uz)
                            packet_put(pk, pku, n_slot, Ox, Oy, Oz, ux / length, uy / length, uz / length, length)
                            if n_rec < len(record):
                                _record(record, n_rec, Ox, Oy, Oz, ux / length, uy / length, uz / length, length)
                                n_rec += 1
                            q_slot[m] = n_slot
                            n_slot += 1
                    else:
                        denom = ux * mnx + uy * mny + uz * mnz
                        tm = ((mcx - Ox) * mnx + (mcy - Oy) * mny + (mcz - Oz) * mnz) / denom
                        if not (tm > 0 and tm < 1):
                            continue
                        Mx, My, Mz = Ox + tm * ux, Oy + tm * uy, Oz + tm * uz
                        m0, m1, m2 = Mx - mcx, My - mcy, Mz - mcz  # the hit, from the mirror's centre
                        if abs(m0 * mux + m1 * muy + m2 * muz) > half_u:
                            continue
                        if abs(m0 * mvx + m1 * mvy + m2 * mvz) > half_v:
                            continue
                        dist = (Lx - mcx) * mnx + (Ly - mcy) * mny + (Lz - mcz) * mnz
                        Rx, Ry, Rz = Lx - 2 * dist * mnx, Ly - 2 * dist * mny, Lz - 2 * dist * mnz  # the real lens point
                        s1x, s1y, s1z = Mx - Ox, My - Oy, Mz - Oz
                        l1 = math.sqrt(s1x * s1x + s1y * s1y + s1z * s1z)
                        s2x, s2y, s2z = Rx - Mx, Ry - My, Rz - Mz
                        l2 = math.sqrt(s2x * s2x + s2y * s2y + s2z * s2z)
                        e2x, e2y, e2z = s2x / l2, s2y / l2, s2z / l2
                        # both segments end ``eps`` from the mirror along the ray: known clear only when
                        # that is well in front of the plane
                        far = eps * abs(denom) >= 2 * margin * math.sqrt(ux * ux + uy * uy + uz * uz)
                        # surface -> mirror now; mirror -> lens for those that pass (second packet)
                        if clear1 and far:
                            q_slot[m] = -1
                        else:
                            packet_put(pk, pku, n_slot, Ox, Oy, Oz, s1x / l1, s1y / l1, s1z / l1, l1 - eps)
                            if n_rec < len(record):
                                _record(record, n_rec, Ox, Oy, Oz, s1x / l1, s1y / l1, s1z / l1, l1 - eps)
                                n_rec += 1
                            q_slot[m] = n_slot
                            n_slot += 1
                        q_need2[m] = not (clear2 and far)
                        seg2[m, 0], seg2[m, 1], seg2[m, 2] = Mx + eps * e2x, My + eps * e2y, Mz + eps * e2z
                        seg2[m, 3], seg2[m, 4], seg2[m, 5], seg2[m, 6] = e2x, e2y, e2z, l2 - eps
                    q_pix[m] = pix
                    q_w[m] = w
                    if use_t:  # along the ray leaving the real surface (to the lens, or to the mirror)
                        q_t[m, 0] = wt * (vx * tframe[s, 0, 0] + vy * tframe[s, 0, 1] + vz * tframe[s, 0, 2])
                        q_t[m, 1] = wt * (vx * tframe[s, 1, 0] + vy * tframe[s, 1, 1] + vz * tframe[s, 1, 2])
                    q_odd[m] = i_lens % 2
                    m += 1
                    if n_slot == 16 or m == _QUEUE:
                        cast, n_touched, n_rec = _flush(fn16, scene, pk, pku, valid, pk2, pku2, m, n_slot, has_mirror, seg2,
                                                        q_pix, q_w, q_odd, q_slot, q_need2, acc_even, acc_odd, mark, touched,
                                                        n_touched, cast, record, n_rec, use_t, q_t, acc_t)
                        m = 0
                        n_slot = 0
                if m > 0:  # the surface point's last rays
                    cast, n_touched, n_rec = _flush(fn16, scene, pk, pku, valid, pk2, pku2, m, n_slot, has_mirror,
                                                    seg2, q_pix, q_w, q_odd, q_slot, q_need2, acc_even, acc_odd, mark,
                                                    touched, n_touched, cast, record, n_rec, use_t, q_t, acc_t)
                    m = 0
                    n_slot = 0
            if rnd >= last_round:
                break
            err = 0.0
            tot = 0.0
            for i in range(n_touched):
                q = touched[i]
                err += abs(acc_even[q] - acc_odd[q])
                tot += acc_even[q] + acc_odd[q]
            if err <= target * tot:
                break
            for i in range(n_touched):  # the next round's rays weigh half as much: so do these
                q = touched[i]
                acc_even[q] *= 0.5
                acc_odd[q] *= 0.5
                if use_t:
                    acc_t[q, 0] *= 0.5
                    acc_t[q, 1] *= 0.5
            rnd += 1
        # the element's column is complete
        if nnz + n_touched > len(out_pix):
            grown = max(2 * len(out_pix), nnz + n_touched)
            p2 = np.empty(grown, np.int32)
            v2 = np.empty(grown, np.float64)
            p2[:nnz] = out_pix[:nnz]
            v2[:nnz] = out_val[:nnz]
            out_pix, out_val = p2, v2
            if use_t:
                t2 = np.empty((grown, 2), np.float64)
                t2[:nnz] = out_t[:nnz]
                out_t = t2
        order = np.sort(touched[:n_touched])
        err = 0.0
        for i in range(n_touched):
            q = order[i]
            out_pix[nnz] = q
            out_val[nnz] = acc_even[q] + acc_odd[q]
            if use_t:
                out_t[nnz, 0], out_t[nnz, 1] = acc_t[q, 0], acc_t[q, 1]
                acc_t[q, 0] = 0.0
                acc_t[q, 1] = 0.0
            err += abs(acc_even[q] - acc_odd[q])
            nnz += 1
            acc_even[q] = 0.0
            acc_odd[q] = 0.0
            mark[q] = False
        elements[k_el] = element[e0]
        col_err[k_el] = err
        k_el += 1
        starts[k_el] = nnz
        n_touched = 0
        e0 = e1
    return (elements, starts, out_pix[:nnz].copy(), out_val[:nnz].copy(), col_err, cast, n_rays, n_rec,
            out_t[:nnz].copy() if use_t else out_t)


@nb.njit(nogil=True, cache=True, inline="always")
def emission_weight(emis, cos_s):
    """Linear interpolation of the ray-weight table ``emis`` at ``cos_s`` in (0, 1] (the same
    arithmetic as :func:`fluxcli.optics.emission.interp_weight`)."""
    t = min(cos_s, 1.0) * (len(emis) - 1)
    i = min(int(t), len(emis) - 2)
    f = t - i
    return emis[i] + (emis[i + 1] - emis[i]) * f


@nb.njit(nogil=True, cache=True, inline="always")
def _record(record, i, ox, oy, oz, dx, dy, dz, length):
    record[i, 0], record[i, 1], record[i, 2] = ox, oy, oz
    record[i, 3], record[i, 4], record[i, 5] = dx, dy, dz
    record[i, 6] = max(length, 0.0)


@nb.njit(nogil=True, cache=True)
def _flush(fn16, scene, pk, pku, valid, pk2, pku2, m, n_slot, has_mirror, seg2, q_pix, q_w, q_odd, q_slot, q_need2,
           acc_even, acc_odd, mark, touched, n_touched, cast, record, n_rec, use_t, q_t, acc_t):
    """Cast the ``n_slot`` packed rays of the ``m`` queued ones (the others are known clear; for
    a mirror view then the mirror -> lens segments of those that reach the mirror and are not
    known clear, 16 at a time) and add the visible ones, in queue order, into the column."""
    if n_slot > 0:
        packet_cast(fn16, scene, pk, valid, n_slot)
        cast += n_slot
    clear = np.empty(_QUEUE, np.bool_)
    for j in range(m):
        clear[j] = q_slot[j] < 0 or not pk[128 + q_slot[j]] < 0
    if has_mirror:
        idx = np.empty(16, np.int64)
        m2 = 0
        for j in range(m):
            if clear[j] and q_need2[j]:
                packet_put(pk2, pku2, m2, seg2[j, 0], seg2[j, 1], seg2[j, 2], seg2[j, 3], seg2[j, 4], seg2[j, 5],
                           seg2[j, 6])
                if n_rec < len(record):
                    _record(record, n_rec, seg2[j, 0], seg2[j, 1], seg2[j, 2], seg2[j, 3], seg2[j, 4], seg2[j, 5],
                            seg2[j, 6])
                    n_rec += 1
                idx[m2] = j
                m2 += 1
                if m2 == 16:
                    packet_cast(fn16, scene, pk2, valid, m2)
                    cast += m2
                    for i in range(m2):
                        clear[idx[i]] = not pk2[128 + i] < 0
                    m2 = 0
        if m2 > 0:
            packet_cast(fn16, scene, pk2, valid, m2)
            cast += m2
            for i in range(m2):
                clear[idx[i]] = not pk2[128 + i] < 0
    for j in range(m):
        if clear[j]:
            pix = q_pix[j]
            if not mark[pix]:
                mark[pix] = True
                touched[n_touched] = pix
                n_touched += 1
            if q_odd[j]:
                acc_odd[pix] += q_w[j]
            else:
                acc_even[pix] += q_w[j]
            if use_t:
                acc_t[pix, 0] += q_t[j, 0]
                acc_t[pix, 1] += q_t[j, 1]
    return cast, n_touched, n_rec
