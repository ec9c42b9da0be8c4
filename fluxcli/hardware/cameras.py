"""Which camera ``rig.camera.backend`` names: one place that opens a real camera.

To add a backend (another vendor, another driver library):

1. subclass :class:`fluxcli.hardware.camera.Camera` in a module of this package: the
   settable ``exposure_s``, ``binning``, ``em_gain``, ``cooler_on``, ``shutter_open``, the
   read-only ``temperature_c`` and ``shape``, ``snap()``, ``sequence(n)``, ``identity()``,
   ``close()``; read every setting back from the camera and raise
   :class:`~fluxcli.hardware.errors.DeviceError` (``self._error(...)``) naming the camera
   for anything it refuses; import the vendor's library inside ``__init__`` (it is an
   optional extra) and accept a stand-in for it (``driver=``/``api=``) for the tests;
2. add its name to :data:`REAL_BACKENDS` below and to the ``backend`` choices of
   ``RigCamera`` in ``fluxcli/config.py`` (with any keys it needs);
3. write a fake of the vendor library with the real one's call names and signatures
   (``tests/fake_pylablib.py`` is the pattern), tests against it, a ``capture-surface`` run
   through it, and a real-device test that runs only when ``FLUXMAP_CAMERA`` names the
   backend (``tests/test_cameras.py``).
"""

from __future__ import annotations

from .camera import Camera

REAL_BACKENDS = ("dcam", "andor_sdk2", "andor_sdk3", "pvcam")


def open_real_camera(cc) -> Camera:
    """Open the real camera that ``cc`` (a validated ``rig.camera``) names, at its binning.

    Raises DeviceError (exit 2) naming the camera when it cannot be opened or set."""
    if cc.backend == "dcam":
        from .dcam import DcamCamera

        cam: Camera = DcamCamera(cc.device_index, shutter_property=cc.shutter_property)
    elif cc.backend in ("andor_sdk2", "andor_sdk3", "pvcam"):
        from .pylablib_cameras import AndorSDK2, AndorSDK3, Pvcam

        common = dict(serial=cc.serial, setpoint_c=cc.setpoint_c, linux_sdk=cc.linux_sdk)
        if cc.backend == "andor_sdk2":
            cam = AndorSDK2(cc.device_index, em_gain_advanced=cc.em_gain_advanced, fan=cc.fan,
                            em_gain_range=tuple(cc.em_gain_range), **common)
        elif cc.backend == "andor_sdk3":
            cam = AndorSDK3(cc.device_index, **common)
        else:
            cam = Pvcam(cc.device_index, em_gain_range=tuple(cc.em_gain_range), **common)
    else:
        raise ValueError(f"rig.camera.backend {cc.backend!r} is not a real camera")
    try:
        cam.binning = cc.binning
    except BaseException:
        cam.close()
        raise
    return cam
