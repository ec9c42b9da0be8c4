"""The compiled T kernel: same occlusion answers as embreex, bytes independent of threads and
chunking, an error estimate that covers the true error, and checkpoints that resume to the
same bytes.  (Its physics is checked against closed forms in test_optics.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from fluxcli.optics.camera import Aperture, PlaneMirror, ThinLensCamera
from fluxcli.optics.raycast import OcclusionScene
from fluxcli.optics.transfer import Checkpoint, LensSampling, build_transfer, views_for
from fluxcli.surface import phantoms
from fluxcli.surface.mesh import rectangle


def _camera(n=64, pitch=0.05, R=5.0, u=100.0, apertures=()):
    return ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                    aperture_radius_mm=R, focus_distance_mm=u, nx=n, ny=n, pixel_pitch_mm=pitch,
                                    apertures=apertures)


def _scene():
    """A small cylinder seen directly and in a mirror, half shadowed by a plate: occlusion,
    defocus, apertures and a mirror all take part."""
    cyl = phantoms.cylinder(radius_mm=3.0, length_mm=6.0, n_angular=12, n_axial=4)[0]
    cyl = cyl.transformed(np.eye(3), np.array([0.0, 0.0, -105.0]))
    cam = _camera(apertures=(Aperture(20.0, 3.0),))
    mirror = PlaneMirror.from_axis([0, -6.0, -104.0], [0, 1, 1], [1, 0, 0], (30.0, 20.0))
    plate = rectangle([2.5, 0.0, -99.0], [1, 0, 0], [0, 1, 0], (5.0, 5.0))
    return cyl, views_for(cam, [("m", mirror, 0.9)]), [plate]


def test_native_occlusion_answers_exactly_as_embreex():
    cyl = phantoms.cylinder(radius_mm=12.5, length_mm=50, n_angular=50, n_axial=32)[0]
    scene = OcclusionScene(cyl.vertices_mm, cyl.faces)
    rng = np.random.default_rng(1)
    n = 50_000
    # half the rays start on the surface (just off it, as the estimator casts them)
    faces = rng.integers(0, len(cyl.faces), n // 2)
    on = cyl.face_vertices_mm[faces].mean(axis=1) + 1e-3 * cyl.face_normals[faces]
    origins = np.concatenate([on, rng.normal(size=(n - n // 2, 3)) * 15])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    lengths = rng.random(n) * 60
    native = scene.blocked(origins, d, lengths)
    ref = scene.blocked_embreex(origins, d, lengths)
    assert 0.2 < native.mean() < 0.8
    assert np.array_equal(native, ref)
    # the T kernel's 16-ray packets, rays in an order as coherent as the kernel's (by origin)
    # and as they come (incoherent)
    from fluxcli.optics import embree_native

    nat = scene.native
    for order in (np.argsort(faces.tolist() + [len(cyl.faces)] * (n - n // 2), kind="stable"), np.arange(n)):
        packets = np.zeros(n, bool)
        embree_native.blocked_packets(nat.occluded16, nat.scene, origins[order], d[order], lengths[order], packets)
        assert np.array_equal(packets, ref[order])


def test_T_bytes_do_not_depend_on_threads_or_chunk_size():
    surf, views, occ = _scene()
    runs = [build_transfer(surf, views, occ, threads=t, rays_per_batch=b) for t, b in ((1, 100_000), (2, 3000),
                                                                                      (3, 1000))]
    a = runs[0]
    assert a.T.nnz > 100 and all(T.sum() > 0 for T in a.T_per_view)
    for b in runs[1:]:
        for x, y in zip([a.T, *a.T_per_view], [b.T, *b.T_per_view]):
            assert np.array_equal(x.indptr, y.indptr) and np.array_equal(x.indices, y.indices)
            assert x.data.tobytes() == y.data.tobytes()
        assert a.column_error.tobytes() == b.column_error.tobytes()


def test_column_error_estimate_covers_the_true_error():
    """Against a much finer T, the per-column estimate (|even - odd half| summed over pixels)
    is at least the actual L1 error for nearly every column, and in total."""
    cam = _camera(n=48, pitch=0.05, R=5.0, u=100.0)
    surf = phantoms.patch(size_mm=(1.5, 1.5), n=(3, 3), center_mm=[0.3, 0.1, -110.0], normal=[0.2, 0, 1])[0]
    plate = rectangle([-1.0, 0.0, -60.0], [1, 0, 0], [0, 1, 0], (4.0, 30.0))  # shadows part of the lens
    views = views_for(cam, [])
    ref = build_transfer(surf, views, [plate], lens_sampling=LensSampling(surface_samples_per_pixel=6,
                                                                          lens_samples_min=2048,
                                                                          lens_samples_max=8192)).T.toarray()
    res = build_transfer(surf, views, [plate])
    true = np.abs(res.T.toarray() - ref).sum(axis=0)
    est = res.column_error
    assert np.all(np.isfinite(est)) and np.all(est > 0)
    assert est.sum() >= true.sum()
    assert np.mean(est >= true) >= 0.85
    # and it is an estimate, not a bound pulled from the air: within 20x of the truth in total
    assert est.sum() < 20 * true.sum()


def test_finer_sampling_converges_and_its_estimate_shrinks():
    cam = _camera(n=48, pitch=0.05, R=5.0, u=100.0)
    surf = phantoms.patch(size_mm=(1.5, 1.5), n=(2, 2), center_mm=[0.3, 0.1, -110.0], normal=[0.2, 0, 1])[0]
    views = views_for(cam, [])
    ref = build_transfer(surf, views, lens_sampling=LensSampling(surface_samples_per_pixel=6, lens_samples_min=2048,
                                                                 lens_samples_max=8192)).T.toarray()
    errs, ests = [], []
    for s in (LensSampling(lens_samples_per_blur_pixel=1, lens_samples_min=8), LensSampling(),
              LensSampling(surface_samples_per_pixel=4, lens_samples_per_blur_pixel=16, lens_samples_min=128)):
        r = build_transfer(surf, views, lens_sampling=s)
        errs.append(np.abs(r.T.toarray() - ref).sum() / ref.sum())
        ests.append(r.column_error.sum() / ref.sum())
    assert errs[0] > errs[1] > errs[2]
    assert ests[0] > ests[1] > ests[2]
    assert errs[2] < 0.01


class _MemoryCheckpoint(Checkpoint):
    def __init__(self, rays_per_block, stop_after=None):
        self.rays_per_block, self.saved, self.stop_after, self.loads = rays_per_block, {}, stop_after, 0

    def load(self, view, spans):
        got = self.saved.get((view, tuple(spans)))
        self.loads += got is not None
        return got

    def save(self, view, spans, results):
        self.saved[(view, tuple(spans))] = results
        if self.stop_after is not None and len(self.saved) >= self.stop_after:
            raise KeyboardInterrupt  # the user pressed Ctrl-C right after this block


def test_an_interrupted_build_resumes_from_its_blocks_to_the_same_bytes():
    surf, views, occ = _scene()
    whole = build_transfer(surf, views, occ, rays_per_batch=2000)
    cp = _MemoryCheckpoint(rays_per_block=6000, stop_after=3)
    with pytest.raises(KeyboardInterrupt):
        build_transfer(surf, views, occ, rays_per_batch=2000, checkpoint=cp)
    cp.stop_after = None
    resumed = build_transfer(surf, views, occ, rays_per_batch=2000, checkpoint=cp)
    assert cp.loads == 3  # the three finished blocks were not cast again
    assert len(cp.saved) > 3
    assert resumed.T.data.tobytes() == whole.T.data.tobytes()
    assert np.array_equal(resumed.T.indices, whole.T.indices) and np.array_equal(resumed.T.indptr, whole.T.indptr)
    assert resumed.column_error.tobytes() == whole.column_error.tobytes()


def test_partial_files_resume_a_pose_and_are_removed_when_it_is_written(tmp_path, monkeypatch):
    from fluxcli.transfer_cache import build as B
    from fluxcli.artefacts import transfer as AT
    from fluxcli.config import Transfer
    from fluxcli.scene import PlacedScene, Pose

    surf, views, occ = _scene()
    scene = PlacedScene(Pose(0.0, 0.0), surf, occ)
    tr = Transfer(rays_per_batch=2000)
    target = tmp_path / "abc.h5"
    whole = tmp_path / "whole.h5"
    monkeypatch.setattr(B, "CHECKPOINT_RAYS", 6000)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    B.build_and_store(scene, views, tr, whole, "x")

    calls = {"n": 0}
    real_save = B.PartialFiles.save

    def save_then_die(self, view, spans, results):
        real_save(self, view, spans, results)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(B.PartialFiles, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        B.build_and_store(scene, views, tr, target, "x")
    part = tmp_path / "abc.part"
    assert len(list(part.glob("*.npz"))) == 2 and not target.exists()
    monkeypatch.setattr(B.PartialFiles, "save", real_save)
    # a rerun with another chunking must not take blocks that hold other samples
    other = tmp_path / "other.h5"
    B.build_and_store(scene, views, Transfer(rays_per_batch=1500), other, "x")
    assert AT.load_T(other).data.tobytes() == AT.load_T(whole).data.tobytes()
    import shutil

    shutil.copytree(part, tmp_path / "other.part")
    B.build_and_store(scene, views, Transfer(rays_per_batch=1500), other, "x")
    assert AT.load_T(other).data.tobytes() == AT.load_T(whole).data.tobytes() and not (tmp_path / "other.part").exists()
    loaded = []
    real_load = B.PartialFiles.load
    monkeypatch.setattr(B.PartialFiles, "load",
                        lambda self, v, b: loaded.append(real_load(self, v, b) is not None) or real_load(self, v, b))
    B.build_and_store(scene, views, tr, target, "x")
    assert sum(loaded) == 2
    assert not part.exists()
    a, b = AT.load_T(target), AT.load_T(whole)
    assert a.data.tobytes() == b.data.tobytes() and np.array_equal(a.indices, b.indices)
    err = AT.load_column_error(target)
    assert err is not None and err.shape == (surf.n_elements,) and np.all(err >= 0)


# ------------------------------------------------------------------ rays not cast (issue 14)
def test_skipping_provably_clear_faces_leaves_T_unchanged_to_the_bit():
    """Faces whose whole lens cone is clear are not cast; the plate shadows part of the
    direct view and the mirror part of the scene, so some faces are cast and some not."""
    surf, views, occ = _scene()
    cast = build_transfer(surf, views, occ, skip_clear=False)
    skipped = build_transfer(surf, views, occ, skip_clear=True)
    for x, y in zip([cast.T, *cast.T_per_view], [skipped.T, *skipped.T_per_view]):
        assert np.array_equal(x.indptr, y.indptr) and np.array_equal(x.indices, y.indices)
        assert x.data.tobytes() == y.data.tobytes()
    assert cast.column_error.tobytes() == skipped.column_error.tobytes()
    for name in ("direct", "m"):
        assert cast.stats[name]["rays"] > 0 and 0 < skipped.stats[name]["rays"] < 0.9 * cast.stats[name]["rays"]


def test_a_face_called_clear_has_no_blocked_segment_to_its_lens():
    """Against Embree itself: from every face the cone test calls clear, random segments to
    random lens points (and, through the mirror, to the real lens) are all unblocked; and
    the test is not vacuous (faces called not clear include blocked ones)."""
    from fluxcli.optics import visibility
    from fluxcli.surface.mesh import merge

    surf, views, occ = _scene()
    v, f = merge(surf, *occ)
    scene = OcclusionScene(v, f)
    tree = visibility.occluder_tree(v, f, 0.5)
    rng = np.random.default_rng(3)
    tri, nrm = surf.face_vertices_mm, surf.face_normals
    n = 400
    any_blocked_unclear = False
    for view in views:
        cam, mirror = view.camera, view.mirror
        flags = visibility.clear_faces(tree, tri, nrm, cam.center_mm, cam.aperture_radius_mm, 1e-3, mirror)
        full = 3 if mirror is not None else 1
        assert 0 < np.count_nonzero(flags == full) < len(flags)
        for face in range(len(tri)):
            ab = rng.random((n, 2))
            ab = np.where(ab.sum(axis=1, keepdims=True) > 1, 1 - ab, ab)
            q = tri[face, 0] + ab[:, :1] * (tri[face, 1] - tri[face, 0]) + ab[:, 1:] * (tri[face, 2] - tri[face, 0])
            o = q + 1e-3 * nrm[face]
            r = np.sqrt(rng.random(n)) * cam.aperture_radius_mm
            phi = rng.random(n) * 2 * np.pi
            L = cam.center_mm + r[:, None] * (np.cos(phi)[:, None] * cam.right + np.sin(phi)[:, None] * cam.down)
            d = L - o
            ok = d @ nrm[face] > 0
            if mirror is None:
                segs = [(o, d)]
            else:
                t = ((mirror.center_mm - o) @ mirror.normal) / (d @ mirror.normal)
                M = o + t[:, None] * d
                ok &= (t > 0) & (t < 1) & mirror.contains(M) & (np.abs(d @ mirror.normal) > 0.2 * np.linalg.norm(d, axis=1))
                # both real segments, each stopping short of the mirror as the kernel's do
                u1 = M - o
                real = mirror.reflect_points(L)
                u2 = real - M
                segs = [(o, u1 * (1 - 1e-3 / np.linalg.norm(u1, axis=1))[:, None]),
                        (M + 1e-3 * u2 / np.linalg.norm(u2, axis=1)[:, None],
                         u2 * (1 - 1e-3 / np.linalg.norm(u2, axis=1))[:, None])]
            for bit, (start, seg) in enumerate(segs):
                length = np.linalg.norm(seg[ok], axis=1)
                blocked = scene.blocked(start[ok], seg[ok] / length[:, None], length)
                if flags[face] & (1 << bit):
                    assert not blocked.any(), (view.name, face, bit)
                elif blocked.any():
                    any_blocked_unclear = True
    assert any_blocked_unclear


def test_a_plate_cutting_the_lens_rim_leaves_no_face_clear():
    """A plate 3 mm in front of the lens covers the outer part of its disk (x > 4 mm of 5):
    every facing face has segments that hit it (Embree says so), so none may be called
    clear; a cone test that shrank the lens, or dropped the plate's pieces, would."""
    from fluxcli.optics import visibility
    from fluxcli.surface.mesh import merge

    surf, views, occ = _scene()
    rim = rectangle([7.0, 0.0, -3.0], [1, 0, 0], [0, 1, 0], (6.0, 30.0))
    v, f = merge(surf, *occ, rim)
    scene = OcclusionScene(v, f)
    cam = views[0].camera
    flags = visibility.clear_faces(visibility.occluder_tree(v, f, 0.5), surf.face_vertices_mm, surf.face_normals,
                                   cam.center_mm, cam.aperture_radius_mm, 1e-3)
    facing = np.einsum("fk,fk->f", surf.face_normals, cam.center_mm - surf.face_vertices_mm.mean(axis=1)) > 0
    assert facing.sum() > 20 and np.all(flags[facing] == 0)
    # and the rim does block part of every facing face's cone: the answer is right, not only safe
    phi = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    L = cam.center_mm + 4.9 * (np.cos(phi)[:, None] * cam.right + np.sin(phi)[:, None] * cam.down)
    for face in np.flatnonzero(facing):
        o = surf.face_vertices_mm[face].mean(axis=0) + 1e-3 * surf.face_normals[face]
        d = L - o
        length = np.linalg.norm(d, axis=1)
        assert scene.blocked(np.repeat(o[None], len(L), 0), d / length[:, None], length).any()
