"""Embree called from compiled (numba) code, without the GIL.

embreex holds the GIL while it casts, so threads around it do not run in parallel, and a
Python call per batch forces the rays through intermediate numpy arrays.  This module
builds a second Embree scene on the same triangles through the C API of the very library
embreex ships (its symbols are looked up through embreex's own extension module, so no
path is guessed), and exposes :func:`segment_blocked`, which numba kernels call per ray:
one occlusion query, GIL released, any number of threads on one committed scene
(Embree's queries are thread-safe).  Same library, same float32 ray, same answer as
embreex's ``query="OCCLUDED"`` (tests/test_transfer_kernel.py checks this bit for bit).
"""

from __future__ import annotations

import ctypes

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

# Embree 4 C API constants (include/embree4/rtcore_{common,buffer,geometry}.h)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003

_LIB = None


def _library() -> ctypes.CDLL:
    """libembree4 as loaded by embreex (dlsym searches the extension's dependencies)."""
    global _LIB
    if _LIB is None:
        from embreex import rtcore_scene

        lib = ctypes.CDLL(rtcore_scene.__file__)
        vp = ctypes.c_void_p
        lib.rtcNewDevice.restype, lib.rtcNewDevice.argtypes = vp, [ctypes.c_char_p]
        lib.rtcNewScene.restype, lib.rtcNewScene.argtypes = vp, [vp]
        lib.rtcNewGeometry.restype, lib.rtcNewGeometry.argtypes = vp, [vp, ctypes.c_int]
        lib.rtcSetNewGeometryBuffer.restype = vp
        lib.rtcSetNewGeometryBuffer.argtypes = [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t,
                                                ctypes.c_size_t]
        for name in ("rtcCommitGeometry", "rtcCommitScene", "rtcReleaseGeometry", "rtcReleaseScene",
                     "rtcReleaseDevice"):
            getattr(lib, name).argtypes = [vp]
            getattr(lib, name).restype = None
        lib.rtcAttachGeometry.restype, lib.rtcAttachGeometry.argtypes = ctypes.c_uint, [vp, vp]
        lib.rtcGetDeviceError.restype, lib.rtcGetDeviceError.argtypes = ctypes.c_int, [vp]
        _LIB = lib
    return _LIB


class NativeScene:
    """A committed Embree scene of ``faces`` over ``vertices_mm`` (float32, as embreex builds it).

    ``scene``, ``occluded1``, ``occluded16``: the addresses of the scene and of the single-ray
    and 16-ray-packet occlusion functions, the integers a numba kernel needs.  The scene lives
    as long as this object.
    """

    def __init__(self, vertices_mm: np.ndarray, faces: np.ndarray):
        lib = _library()
        v = np.ascontiguousarray(vertices_mm, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        self._lib = lib
        self._device = lib.rtcNewDevice(None)
        self._scene = lib.rtcNewScene(self._device)
        geom = lib.rtcNewGeometry(self._device, _GEOMETRY_TYPE_TRIANGLE)
        vb = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, 12, len(v))
        ctypes.memmove(vb, v.ctypes.data, v.nbytes)  # v, f stay referenced until the copies are done
        ib = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, 12, len(f))
        ctypes.memmove(ib, f.ctypes.data, f.nbytes)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self._scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self._scene)
        err = lib.rtcGetDeviceError(self._device)
        if err:
            raise RuntimeError(f"Embree could not build the occlusion scene (error {err})")
        self.scene = int(self._scene)
        self.occluded1 = ctypes.cast(lib.rtcOccluded1, ctypes.c_void_p).value
        self.occluded16 = ctypes.cast(lib.rtcOccluded16, ctypes.c_void_p).value

    def __del__(self):
        lib = getattr(self, "_lib", None)
        if lib is not None:
            lib.rtcReleaseScene(self._scene)
            lib.rtcReleaseDevice(self._device)


@intrinsic
def _occluded1(typingctx, fn_addr, scene_addr, ray):
    """Call ``rtcOccluded1(scene, ray, NULL)`` through its address (kept out of the compiled
    code as a constant, so the kernels can be cached on disk)."""
    sig = types.void(types.intp, types.intp, ray)

    def codegen(context, builder, signature, args):
        fa, sc, arr = args
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p])
        fn = builder.inttoptr(fa, fnty.as_pointer())
        data = context.make_array(signature.args[2])(context, builder, arr).data
        builder.call(fn, [builder.inttoptr(sc, i8p), builder.bitcast(data, i8p), ir.Constant(i8p, None)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def occluded16(typingctx, fn_addr, scene_addr, valid, ray):
    """Call ``rtcOccluded16(valid, scene, ray16, NULL)``: 16 rays in one traversal (a packet of
    coherent rays, e.g. from one surface point to its lens samples, costs far less than 16
    single rays; the answers are the same, tests/test_transfer_kernel.py)."""
    sig = types.void(types.intp, types.intp, valid, ray)

    def codegen(context, builder, signature, args):
        fa, sc, v, r = args
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p, i8p])
        fn = builder.inttoptr(fa, fnty.as_pointer())
        vd = context.make_array(signature.args[2])(context, builder, v).data
        rd = context.make_array(signature.args[3])(context, builder, r).data
        builder.call(fn, [builder.bitcast(vd, i8p), builder.inttoptr(sc, i8p), builder.bitcast(rd, i8p),
                          ir.Constant(i8p, None)])
        return context.get_dummy_value()

    return sig, codegen


@nb.njit(nogil=True, cache=True)
def new_packet() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 64-byte-aligned RTCRay16 (structure of arrays, 12 fields x 16 rays) as float32 and
    uint32 views, and its 64-byte-aligned valid mask (int32 x 16)."""
    buf = np.empty(192 + 16, np.float32)
    off = ((64 - buf.ctypes.data % 64) % 64) // 4
    ray = buf[off:off + 192]
    vbuf = np.empty(32, np.int32)
    voff = ((64 - vbuf.ctypes.data % 64) % 64) // 4
    return ray, ray.view(np.uint32), vbuf[voff:voff + 16]


@nb.njit(nogil=True, cache=True, inline="always")
def packet_put(ray, rayu, j, ox, oy, oz, dx, dy, dz, length) -> None:
    """Ray ``j`` of a packet: the segment origin + t * (dx, dy, dz), 0 <= t <= length (float32)."""
    ray[j] = np.float32(ox)
    ray[16 + j] = np.float32(oy)
    ray[32 + j] = np.float32(oz)
    ray[48 + j] = np.float32(0.0)
    ray[64 + j] = np.float32(dx)
    ray[80 + j] = np.float32(dy)
    ray[96 + j] = np.float32(dz)
    ray[112 + j] = np.float32(0.0)
    ray[128 + j] = np.float32(max(length, 0.0))
    rayu[144 + j] = np.uint32(0xFFFFFFFF)
    rayu[160 + j] = np.uint32(0)
    rayu[176 + j] = np.uint32(0)


@nb.njit(nogil=True, cache=True, inline="always")
def packet_cast(fn16, scene, ray, valid, m) -> None:
    """Cast the first ``m`` rays of a packet; afterwards ray j is blocked iff ``ray[128 + j] < 0``."""
    for j in range(16):
        valid[j] = -1 if j < m else 0
    occluded16(fn16, scene, valid, ray)


@nb.njit(nogil=True, cache=True)
def new_ray() -> tuple[np.ndarray, np.ndarray]:
    """A 16-byte-aligned RTCRay (12 x 4 bytes) as float32 and uint32 views of one buffer."""
    buf = np.empty(16, np.float32)
    off = ((16 - buf.ctypes.data % 16) % 16) // 4
    ray = buf[off:off + 12]
    return ray, ray.view(np.uint32)


@nb.njit(nogil=True, cache=True, inline="always")
def segment_blocked(fn, scene, ray, rayu, ox, oy, oz, dx, dy, dz, length) -> bool:
    """True when the segment origin + t * (dx, dy, dz), 0 <= t <= length, hits a triangle.
    Origin, unit direction and length are rounded to float32 exactly as embreex does."""
    ray[0] = np.float32(ox)
    ray[1] = np.float32(oy)
    ray[2] = np.float32(oz)
    ray[3] = np.float32(0.0)
    ray[4] = np.float32(dx)
    ray[5] = np.float32(dy)
    ray[6] = np.float32(dz)
    ray[7] = np.float32(0.0)
    ray[8] = np.float32(max(length, 0.0))
    rayu[9] = np.uint32(0xFFFFFFFF)
    rayu[10] = np.uint32(0)
    rayu[11] = np.uint32(0)
    _occluded1(fn, scene, ray)
    return ray[8] < 0  # Embree sets tfar to -inf on a hit


@nb.njit(nogil=True, cache=True)
def blocked_many(fn, scene, origins, directions, lengths, out) -> None:
    """``out[i]`` = segment i is blocked; float32 or float64 inputs of shape (n, 3), (n, 3), (n,)."""
    ray, rayu = new_ray()
    for i in range(len(lengths)):
        out[i] = segment_blocked(fn, scene, ray, rayu, origins[i, 0], origins[i, 1], origins[i, 2],
                                 directions[i, 0], directions[i, 1], directions[i, 2], lengths[i])


@nb.njit(nogil=True, cache=True)
def blocked_packets(fn16, scene, origins, directions, lengths, out) -> None:
    """:func:`blocked_many` through 16-ray packets (what the T kernel uses)."""
    pk, pku, valid = new_packet()
    n = len(lengths)
    for a in range(0, n, 16):
        m = min(16, n - a)
        for j in range(m):
            i = a + j
            packet_put(pk, pku, j, origins[i, 0], origins[i, 1], origins[i, 2], directions[i, 0], directions[i, 1],
                       directions[i, 2], lengths[i])
        packet_cast(fn16, scene, pk, valid, m)
        for j in range(m):
            out[a + j] = pk[128 + j] < 0
