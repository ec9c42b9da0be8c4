"""Single-channel image files (TIFF, FITS, OpenEXR) through OpenImageIO.

Arrays are ``[row, col]`` = ``[ny, nx]`` with row 0 the first row the camera reads out.
What is written is read back unchanged (values, row order, metadata) in every format.

File conventions, including where OpenImageIO needs help:

- **Row order.** TIFF and EXR store row 0 first. FITS stores its first data row
  (``NAXIS2`` index 1) first; viewers such as ds9 draw it at the *bottom*, and
  OpenImageIO flips FITS rows on both read and write so that its row 0 is that bottom
  (last stored) row. fluxmap undoes that flip: row 0 of the array is the first row
  stored in the FITS file, which is also ``astropy.io.fits.getdata(path)[0]``. A FITS
  file therefore looks upside down in ds9 next to the same image as TIFF.
- **Sample types.** ``uint16`` (counts) and ``float32`` (photons) are accepted. TIFF
  stores both natively. OpenImageIO converts ``uint16`` lossily for FITS (to a
  normalised int16) and EXR (to half), so there counts are stored exactly as int32
  (FITS, ``BITPIX = 32``) or float32 (EXR).
- **FITS scaling.** Integer pixels equal to ``BLANK`` (the standard's undefined value) read as NaN,
  which every stage leaves out. A FITS file's ``BZERO`` and ``BSCALE`` are applied (physical = BZERO +
  BSCALE x stored), as the standard says and astropy does: unsigned 16-bit counts, what camera
  software writes, are stored as int16 with ``BZERO = 32768`` and read back as 0..65535
  (OpenImageIO alone returns them shifted by -32768). Such a file's sample type is ``uint16``
  (``uint32`` for int32 with ``BZERO = 2^31``); any other scaling makes it ``float64``.
- **One image per file.** A FITS file whose primary HDU is empty is read from its first image
  extension. A file holding more than one image (TIFF pages, FITS extensions) is refused: which
  of them is the pose's image cannot be guessed.
- **Metadata.** OpenImageIO drops unknown attributes from TIFF, and its FITS writer
  truncates keywords to 8 characters and values to one unquoted card. So the metadata
  dict is stored as one JSON record: in the ``ImageDescription`` attribute (TIFF tag
  270, EXR string attribute), and for FITS base64-encoded across keywords ``FXMD0000``,
  ``FXMD0001``, ….
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

__all__ = ["SUFFIXES", "read_image", "recorded_exposure_s", "sample_type", "write_image"]

SUFFIXES = (".tif", ".tiff", ".fits", ".exr")
"""File name suffixes :func:`write_image` can write (case-insensitive)."""

_RECORD_KEY = "fluxmap_metadata"
_FITS_CHUNK_PREFIX = "FXMD"
_FITS_CHUNK_CHARS = 60  # base64 characters per FITS card (a card value holds at most ~68)
_FITS_MAX_CHUNKS = 10_000

# OIIO attributes describing the file encoding, not the image: not returned as metadata.
_ENCODING_ATTRIBUTES = {"oiio:subimages", "oiio:BitsPerSample", "oiio:RowsPerChunk"}


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(
            f"Image file '{path}' has an unsupported suffix {path.suffix!r}; "
            f"use one of {', '.join(SUFFIXES)}."
        )
    return suffix


def _check_metadata(metadata) -> dict[str, str | float | int]:
    if metadata is None:
        return {}
    if not isinstance(metadata, dict):
        raise ValueError(f"Image metadata must be a dict, not {type(metadata).__name__}.")
    for key, value in metadata.items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"Image metadata key {key!r} must be a non-empty string.")
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise ValueError(
                f"Image metadata value for {key!r} must be a str, int or float, "
                f"not {type(value).__name__}."
            )
    return dict(metadata)


def _fits_chunks(record: str) -> dict[str, str]:
    encoded = base64.urlsafe_b64encode(record.encode("ascii")).decode("ascii")
    pieces = [
        encoded[i : i + _FITS_CHUNK_CHARS] for i in range(0, len(encoded), _FITS_CHUNK_CHARS)
    ]
    if len(pieces) > _FITS_MAX_CHUNKS:
        raise ValueError("Image metadata is too large to store in a FITS header.")
    # The leading letter keeps OIIO from parsing an all-digit piece as a number.
    return {f"{_FITS_CHUNK_PREFIX}{i:04d}": "b" + piece for i, piece in enumerate(pieces)}


def _write_pixels(path: Path, pixels: np.ndarray, spec: oiio.ImageSpec) -> None:
    """Write ``pixels`` [ny, nx, 1] with ``spec`` to ``path`` (format from its suffix)."""
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"OpenImageIO cannot create image file '{path}': {oiio.geterror()}")
    try:
        if not out.open(str(path), spec):
            raise OSError(f"OpenImageIO cannot open '{path}' for writing: {out.geterror()}")
        if not out.write_image(pixels):
            raise OSError(f"OpenImageIO failed to write '{path}': {out.geterror()}")
    finally:
        out.close()


def write_image(
    path, image: np.ndarray, *, metadata: dict[str, str | float | int] | None = None
) -> None:
    """Write a 2-D image atomically as TIFF, FITS or OpenEXR (chosen by suffix).

    The image is written to a temporary file in the destination directory, then
    renamed over ``path``: readers never see a partial file, and a failed write leaves
    an existing ``path`` untouched.

    Parameters
    ----------
    path : str or os.PathLike
        Destination; its suffix (``.tif``, ``.tiff``, ``.fits``, ``.exr``, any case)
        selects the format. The directory must exist.
    image : numpy.ndarray, shape (ny, nx), dtype uint16 or float32
        ``[row, col]`` image, row 0 first: uint16 for counts, float32 for photons
        (cast float64 data with ``image.astype(numpy.float32)`` first).
    metadata : dict of str to str, int or float, optional
        Attributes stored with the image, e.g. ``{"fluxmap:units": "photons"}``;
        :func:`read_image` returns them unchanged (same keys, values and types).

    Raises
    ------
    ValueError
        Unsupported suffix, missing directory, image not 2-D or empty, unsupported
        dtype, or metadata that is not a dict of str to str/int/float.
    OSError
        OpenImageIO failed to write the file.
    """
    path = Path(path)
    suffix = _suffix(path)
    if not path.parent.is_dir():
        raise ValueError(
            f"Cannot write image file '{path}': directory '{path.parent}' does not exist."
        )
    image = np.asarray(image)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(
            f"Image for '{path}' must be a non-empty 2-D array [ny, nx], got shape {image.shape}."
        )
    if image.dtype not in (np.dtype(np.uint16), np.dtype(np.float32)):
        raise ValueError(
            f"Image for '{path}' must have dtype uint16 (counts) or float32 (photons), "
            f"got {image.dtype}."
        )
    metadata = _check_metadata(metadata)

    pixels = image
    if image.dtype == np.uint16 and suffix == ".fits":
        pixels, pixel_type = image.astype(np.int32), oiio.INT32
    elif image.dtype == np.uint16 and suffix == ".exr":
        pixels, pixel_type = image.astype(np.float32), oiio.FLOAT
    elif image.dtype == np.uint16:
        pixel_type = oiio.UINT16
    else:
        pixel_type = oiio.FLOAT
    if suffix == ".fits":
        pixels = pixels[::-1]  # OIIO flips FITS rows on write; pre-flip to store row 0 first.

    ny, nx = image.shape
    spec = oiio.ImageSpec(nx, ny, 1, pixel_type)
    record = json.dumps({_RECORD_KEY: metadata}, ensure_ascii=True, sort_keys=True)
    if suffix == ".fits":
        for key, value in _fits_chunks(record).items():
            spec.attribute(key, value)
    else:
        spec.attribute("ImageDescription", record)
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch.isdigit():  # reproducible files: the fixed time, not now (TIFF's DateTime)
        spec.attribute("DateTime", time.strftime("%Y:%m:%d %H:%M:%S", time.gmtime(int(epoch))))

    # The one atomic writer: a temporary name in the same folder with the same suffix
    # (so OIIO picks the format), fsync, rename.
    from ..artefacts.atomic import atomic_path

    with atomic_path(path) as tmp:
        _write_pixels(tmp, np.ascontiguousarray(pixels[:, :, np.newaxis]), spec)


def _decode_record(text) -> dict | None:
    if not isinstance(text, str):
        return None
    try:
        record = json.loads(text)
    except ValueError:
        return None
    if isinstance(record, dict) and isinstance(record.get(_RECORD_KEY), dict):
        return record[_RECORD_KEY]
    return None


def _fits_record(attributes: dict) -> dict | None:
    pieces = {}
    for name, value in attributes.items():
        upper = name.upper()
        if upper.startswith(_FITS_CHUNK_PREFIX) and upper[len(_FITS_CHUNK_PREFIX) :].isdigit():
            pieces[int(upper[len(_FITS_CHUNK_PREFIX) :])] = value
    if not pieces:
        return None
    if sorted(pieces) != list(range(len(pieces))) or not all(
        isinstance(v, str) and v.startswith("b") for v in pieces.values()
    ):
        return None
    encoded = "".join(pieces[i][1:] for i in range(len(pieces)))
    try:
        text = base64.urlsafe_b64decode(encoded.encode("ascii")).decode("ascii")
    except (binascii.Error, ValueError):
        return None
    return _decode_record(text)


def read_image(path) -> tuple[np.ndarray, dict[str, str | float | int]]:
    """Read a single-channel image file through OpenImageIO.

    Parameters
    ----------
    path : str or os.PathLike
        Image file in any format OpenImageIO reads (format detected from content);
        row order and metadata are handled as described in the module docstring for
        TIFF, FITS and EXR.

    Returns
    -------
    image : numpy.ndarray of float64, shape (ny, nx)
        ``[row, col]`` image, row 0 first, sample values unscaled (a uint16 count of
        1000 reads as 1000.0).
    metadata : dict of str to str, int or float
        For files written by :func:`write_image`, exactly the metadata given there.
        For other files, the file's scalar attributes as OpenImageIO names them (e.g.
        ``"ImageDescription"``, ``"Exptime"`` for a FITS ``EXPTIME`` keyword).

    Raises
    ------
    ValueError
        The file does not exist, cannot be read, or has more than one channel.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"Image file '{path}' does not exist.")
    inp = _open(path)
    try:
        spec = inp.spec()
        is_fits = inp.format_name() == "fits"
        if spec.nchannels != 1:
            raise ValueError(
                f"Image file '{path}' has {spec.nchannels} channels; fluxmap expects a "
                f"single-channel image."
            )
        if spec.depth > 1:  # a FITS cube (NAXIS3 > 1): a kinetic series or an accumulation's frames
            raise ValueError(
                f"Image file '{path}' holds {spec.depth} frames of {spec.width} x {spec.height} (a cube, such as "
                "a kinetic series); fluxmap reads one image per file, one file per pose (save the frame meant, "
                "or the frames' sum, to a file of its own)."
            )
        # TypeUnknown: native sample type, so integer samples are not normalised to [0, 1].
        pixels = inp.read_image(oiio.UNKNOWN)
        if pixels is None:
            reason = inp.geterror().strip().rstrip(".")
            raise ValueError(f"Image file '{path}' cannot be read: {reason}.")
        attributes = {attribute.name: attribute.value for attribute in spec.extra_attribs}
    finally:
        inp.close()

    image = np.asarray(pixels, dtype=np.float64).reshape(spec.height, spec.width)
    if is_fits:
        image = image[::-1]  # undo OIIO's flip: row 0 is the first row stored in the file
        blank = attributes.get("Blank", attributes.get("BLANK"))
        if isinstance(blank, (int, float)) and not isinstance(blank, bool) and np.issubdtype(np.asarray(pixels).dtype,
                                                                                               np.integer):
            image = np.where(image == float(blank), np.nan, image)  # the standard's undefined pixels (integer data)
        zero, scale = _fits_scaling(attributes)
        if (zero, scale) != (0.0, 1.0):  # the standard's physical values (OIIO returns the stored ones)
            image = zero + scale * image
    image = np.ascontiguousarray(image)

    if is_fits:
        record = _fits_record(attributes)
    else:
        record = _decode_record(attributes.get("ImageDescription"))
    if record is not None:
        return image, record
    metadata = {
        name: value
        for name, value in attributes.items()
        if name not in _ENCODING_ATTRIBUTES
        and isinstance(value, (str, int, float))
        and not isinstance(value, bool)
    }
    return image, metadata


def _open(path: Path):
    """An OpenImageIO input on the file's one image (see the module docstring: an empty FITS
    primary HDU is skipped; a second image is refused)."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        reason = oiio.geterror().strip().rstrip(".") or "unknown format"
        raise ValueError(f"Image file '{path}' cannot be read: {reason}.")
    sizes = []
    k = 0
    while inp.seek_subimage(k, 0):
        spec = inp.spec()
        sizes.append(spec.width * spec.height)
        k += 1
    images = [i for i, n in enumerate(sizes) if n > 0]
    if len(images) > 1:
        inp.close()
        what = "FITS extensions" if inp.format_name() == "fits" else "pages"
        raise ValueError(f"Image file '{path}' holds {len(images)} images ({what}); fluxmap reads one image per "
                         f"file, one file per pose (save each image to its own file).")
    if not images or not inp.seek_subimage(images[0], 0):
        inp.close()
        raise ValueError(f"Image file '{path}' holds no image data (every HDU or page is empty).")
    return inp


def _fits_scaling(attributes: dict) -> tuple[float, float]:
    """(BZERO, BSCALE) of a FITS image, (0, 1) when absent."""
    def number(name, default):
        v = attributes.get(name, attributes.get(name.upper(), default))
        try:
            return float(v)
        except (TypeError, ValueError):
            return default
    scale = number("Bscale", 1.0)
    if abs(scale - 1.0) < 1e-7:  # OIIO keeps BSCALE as float32: 1 is 1
        scale = 1.0
    return number("Bzero", 0.0), scale


def sample_type(path) -> str:
    """The sample type the file stores, as numpy names it (``"uint16"``, ``"float32"``, ...).

    FITS counts written by :func:`write_image` are stored as int32 and EXR counts as
    float32 (see the module docstring), so only TIFF keeps ``uint16`` for counts.

    Raises
    ------
    ValueError
        The file does not exist or cannot be read.
    """
    path = Path(path)
    inp = _open(path)
    try:
        fmt = inp.spec().format
        if inp.format_name() == "fits":
            zero, scale = _fits_scaling({a.name: a.value for a in inp.spec().extra_attribs})
            if (zero, scale) != (0.0, 1.0):
                unsigned = {oiio.INT16: (2.0**15, "uint16"), oiio.INT32: (2.0**31, "uint32")}
                for t, (offset, name) in unsigned.items():
                    if fmt == t and (zero, scale) == (offset, 1.0):
                        return name
                return "float64"
    finally:
        inp.close()
    names = {oiio.UINT8: "uint8", oiio.INT8: "int8", oiio.UINT16: "uint16", oiio.INT16: "int16",
             oiio.UINT32: "uint32", oiio.INT32: "int32", oiio.HALF: "float16", oiio.FLOAT: "float32",
             oiio.DOUBLE: "float64"}
    for t, name in names.items():
        if fmt == t:
            return name
    return str(fmt)


# Where a file records its exposure time (s): fluxmap's own frames (``rig snap``), FITS EXPTIME /
# EXPOSURE (Andor Solis, PVCAM and most astronomy-derived camera software), TIFF EXIF ExposureTime.
EXPOSURE_KEYS = ("fluxmap:exposure_s", "ExposureTime", "Exptime", "Exposure")


def recorded_exposure_s(metadata: dict) -> tuple[float, str] | None:
    """(exposure in s, the metadata key that records it) of an image's metadata (what
    :func:`read_image` returns), or None when it records none.  A key that holds no positive
    finite number (EXPTIME = 0 of a synthetic FITS, text) records none: it can only be trusted
    as a measurement."""
    lower = {k.lower(): k for k in metadata}
    for key in EXPOSURE_KEYS:
        name = lower.get(key.lower())
        if name is None:
            continue
        try:
            t = float(metadata[name])
        except (TypeError, ValueError):
            continue
        if np.isfinite(t) and t > 0:
            if key != "fluxmap:exposure_s":  # OpenImageIO keeps these as float32: 0.3 reads 0.30000001
                t = float(f"{t:.7g}")
            return t, name
    return None
