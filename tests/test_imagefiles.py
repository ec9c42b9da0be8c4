"""Image files: exact round trips, row order, metadata, atomic writes, clear errors."""

import numpy as np
import OpenImageIO as oiio
import pytest

from fluxcli.imaging import imagefiles
from fluxcli.imaging.imagefiles import read_image, write_image

NY, NX = 5, 7  # not square, so a transpose would be caught too

FITS_BLOCK = 2880


def asymmetric_image(dtype):
    """An image no flip, transpose or scaling maps onto itself."""
    rows, cols = np.mgrid[0:NY, 0:NX]
    if dtype == np.uint16:
        image = (rows * 1000 + cols * 10 + 1).astype(np.uint16)
        image[0, 0], image[-1, -1] = 0, 65535  # the full range survives
        return image
    image = (rows * 1000.0 + cols * 10.0 + 0.125).astype(np.float32)
    image[0, 1] = -3.5e-7
    image[-1, 0] = 3.4e38
    image[2, 3] = np.float32(1 / 3)
    return image


def parse_fits(path):
    """The primary HDU of a FITS file as (header dict, data with the first stored row first)."""
    raw = path.read_bytes()
    header, offset = {}, 0
    while True:
        card = raw[offset : offset + 80].decode("ascii")
        offset += 80
        if card.startswith("END"):
            break
        if card[8:10] == "= ":
            header[card[:8].strip()] = card[10:].split("/")[0].strip()
    offset = -(-offset // FITS_BLOCK) * FITS_BLOCK
    dtype = {"16": ">i2", "32": ">i4", "-32": ">f4", "-64": ">f8"}[header["BITPIX"]]
    ny, nx = int(header["NAXIS2"]), int(header["NAXIS1"])
    data = np.frombuffer(raw, dtype=dtype, count=ny * nx, offset=offset).reshape(ny, nx)
    return header, data


def write_plain_fits(path, data):
    """Write float32 ``data`` the way astropy does: data[0] is the first stored row."""
    ny, nx = data.shape
    cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                  -32",
        "NAXIS   =                    2",
        f"NAXIS1  = {nx:20d}",
        f"NAXIS2  = {ny:20d}",
        "END",
    ]
    header = "".join(card.ljust(80) for card in cards).encode("ascii")
    header += b" " * (-len(header) % FITS_BLOCK)
    payload = data.astype(">f4").tobytes()
    path.write_bytes(header + payload + b"\0" * (-len(payload) % FITS_BLOCK))


@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".fits", ".exr", ".TIF"])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_round_trip_is_exact(tmp_path, suffix, dtype):
    image = asymmetric_image(dtype)
    path = tmp_path / f"image{suffix}"
    write_image(path, image)
    read, metadata = read_image(path)
    assert read.dtype == np.float64 and read.shape == (NY, NX)
    np.testing.assert_array_equal(read, image.astype(np.float64))
    assert metadata == {}


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_fits_stores_row_0_first(tmp_path, dtype):
    # OIIO alone would store row 0 last (FITS bottom-up display convention).
    image = asymmetric_image(dtype)
    path = tmp_path / "image.fits"
    write_image(path, image)
    header, data = parse_fits(path)
    assert header["BITPIX"] == ("32" if dtype == np.uint16 else "-32")
    np.testing.assert_array_equal(data, image)


def test_fits_from_another_writer_reads_row_0_first(tmp_path):
    image = asymmetric_image(np.float32)
    path = tmp_path / "astropy_style.fits"
    write_plain_fits(path, image)
    read, _ = read_image(path)
    np.testing.assert_array_equal(read, image)


def test_tiff_stores_row_0_first(tmp_path):
    # Read with OIIO directly: TIFF row 0 is the first stored row, no flip anywhere.
    image = asymmetric_image(np.uint16)
    path = tmp_path / "image.tif"
    write_image(path, image)
    inp = oiio.ImageInput.open(str(path))
    raw = inp.read_image(oiio.UNKNOWN)
    inp.close()
    np.testing.assert_array_equal(raw[:, :, 0], image)


METADATA = {
    "fluxmap:units": "photons",
    "fluxmap:exposure_s": 0.1,
    "fluxmap:pose": 3,
    "fluxmap:em_gain": 300.0,
    "note": "a/b = 'c', 1234567890 " + "long " * 40 + "é",
    "digits": "0123",
}


@pytest.mark.parametrize("suffix", [".tif", ".fits", ".exr"])
def test_metadata_round_trips_with_types(tmp_path, suffix):
    path = tmp_path / f"image{suffix}"
    write_image(path, asymmetric_image(np.float32), metadata=METADATA)
    _, metadata = read_image(path)
    assert metadata == METADATA
    assert {key: type(value) for key, value in metadata.items()} == {
        key: type(value) for key, value in METADATA.items()
    }


def test_foreign_file_metadata_is_the_files_attributes(tmp_path):
    path = tmp_path / "foreign.tif"
    spec = oiio.ImageSpec(NX, NY, 1, oiio.UINT16)
    spec.attribute("ImageDescription", "written by another program")
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(asymmetric_image(np.uint16)[:, :, None])
    out.close()
    image, metadata = read_image(path)
    np.testing.assert_array_equal(image, asymmetric_image(np.uint16))
    assert metadata["ImageDescription"] == "written by another program"


def test_overwrite_replaces_file(tmp_path):
    path = tmp_path / "image.tif"
    write_image(path, np.zeros((2, 3), np.float32), metadata={"v": 1})
    write_image(path, asymmetric_image(np.float32), metadata={"v": 2})
    image, metadata = read_image(path)
    np.testing.assert_array_equal(image, asymmetric_image(np.float32))
    assert metadata == {"v": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.tif"]


@pytest.mark.parametrize("bad", [np.zeros((3, 4)), np.zeros((3, 4), np.int32), np.zeros((3, 4), bool)])
def test_unsupported_dtype_raises_and_leaves_no_file(tmp_path, bad):
    with pytest.raises(ValueError, match="dtype"):
        write_image(tmp_path / "image.tif", bad)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_old_file_and_no_partial_file(tmp_path, monkeypatch):
    path = tmp_path / "image.fits"
    write_image(path, asymmetric_image(np.float32))
    before = path.read_bytes()

    def fail_halfway(tmp, pixels, spec):
        tmp.write_bytes(b"SIMPLE  =  partial")
        raise OSError("disk full")

    monkeypatch.setattr(imagefiles, "_write_pixels", fail_halfway)
    with pytest.raises(OSError, match="disk full"):
        write_image(path, np.zeros((2, 2), np.float32))
    assert [p.name for p in tmp_path.iterdir()] == ["image.fits"]
    assert path.read_bytes() == before


@pytest.mark.parametrize("name", ["image.png", "image.jpg", "image", "image.fit"])
def test_unsupported_suffix_raises(tmp_path, name):
    with pytest.raises(ValueError, match="suffix"):
        write_image(tmp_path / name, asymmetric_image(np.float32))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "image, metadata, match",
    [
        (np.zeros((2, 3, 1), np.float32), None, "2-D"),
        (np.zeros((0, 3), np.float32), None, "2-D"),
        (np.zeros(3, np.float32), None, "2-D"),
        (np.zeros((2, 3), np.float32), {"units": ["photons"]}, "units"),
        (np.zeros((2, 3), np.float32), {"flag": True}, "flag"),
        (np.zeros((2, 3), np.float32), {1: "x"}, "key"),
        (np.zeros((2, 3), np.float32), "units=photons", "dict"),
    ],
)
def test_bad_arguments_raise(tmp_path, image, metadata, match):
    with pytest.raises(ValueError, match=match):
        write_image(tmp_path / "image.tif", image, metadata=metadata)


def test_missing_directory_raises(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        write_image(tmp_path / "nowhere" / "image.tif", np.zeros((2, 2), np.float32))


def test_missing_file_raises_naming_it(tmp_path):
    path = tmp_path / "missing.tif"
    with pytest.raises(ValueError, match="missing.tif"):
        read_image(path)


def test_unreadable_file_raises_naming_it(tmp_path):
    path = tmp_path / "garbage.tif"
    path.write_bytes(b"this is not a TIFF file")
    with pytest.raises(ValueError, match="garbage.tif"):
        read_image(path)


def test_multichannel_file_raises(tmp_path):
    path = tmp_path / "rgb.tif"
    spec = oiio.ImageSpec(NX, NY, 3, oiio.UINT8)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.zeros((NY, NX, 3), np.uint8))
    out.close()
    with pytest.raises(ValueError, match="3 channels"):
        read_image(path)


def _fits_hdu(cards, payload=b""):
    header = "".join(card.ljust(80) for card in [*cards, "END"]).encode("ascii")
    header += b" " * (-len(header) % FITS_BLOCK)
    return header + payload + b"\0" * (-len(payload) % FITS_BLOCK)


def _image_cards(first, bitpix, ny, nx, extra=()):
    head = ["SIMPLE  =                    T"] if first else ["XTENSION= 'IMAGE   '"]
    cards = [*head, f"BITPIX  = {bitpix:20d}", "NAXIS   =                    2", f"NAXIS1  = {nx:20d}",
             f"NAXIS2  = {ny:20d}"]
    return cards + ([] if first else ["PCOUNT  =                    0", "GCOUNT  =                    1"]) + list(extra)


def test_unsigned_16_bit_fits_as_camera_software_writes_it_reads_as_0_to_65535(tmp_path):
    """The FITS standard stores uint16 as int16 with BZERO = 32768 (astropy, Andor Solis,
    MicroManager do); the physical value is BZERO + BSCALE x stored. Read unscaled, every count
    would be 32768 too low (0 -> -32768)."""
    counts = asymmetric_image(np.uint16)
    stored = (counts.astype(np.int32) - 32768).astype(">i2")
    path = tmp_path / "camera.fits"
    path.write_bytes(_fits_hdu(_image_cards(True, 16, NY, NX, ["BZERO   =                32768",
                                                              "BSCALE  =                    1"]), stored.tobytes()))
    read, _ = read_image(path)
    np.testing.assert_array_equal(read, counts.astype(np.float64))
    assert imagefiles.sample_type(path) == "uint16"  # counts, as a TIFF of them would say
    # a scaled image holds physical values that are not whole: floating point, with BZERO and BSCALE
    path2 = tmp_path / "scaled.fits"
    path2.write_bytes(_fits_hdu(_image_cards(True, 16, NY, NX, ["BZERO   =                  5.0",
                                                               "BSCALE  =                 0.25"]),
                                np.arange(NY * NX, dtype=">i2").reshape(NY, NX).tobytes()))
    read2, _ = read_image(path2)
    np.testing.assert_allclose(read2, 5.0 + 0.25 * np.arange(NY * NX).reshape(NY, NX), rtol=1e-7)
    assert imagefiles.sample_type(path2) == "float64"


def test_fits_with_an_empty_primary_reads_its_image_extension_and_two_images_are_refused(tmp_path):
    image = asymmetric_image(np.float32)
    ext = _fits_hdu(_image_cards(False, -32, NY, NX), image.astype(">f4").tobytes())
    one = tmp_path / "ext.fits"
    one.write_bytes(_fits_hdu(["SIMPLE  =                    T", "BITPIX  =                    8",
                               "NAXIS   =                    0", "EXTEND  =                    T"]) + ext)
    read, _ = read_image(one)
    np.testing.assert_array_equal(read, image.astype(np.float64))
    two = tmp_path / "two.fits"
    two.write_bytes(_fits_hdu(_image_cards(True, -32, NY, NX, ["EXTEND  =                    T"]),
                              image.astype(">f4").tobytes()) + ext)
    with pytest.raises(ValueError, match="holds 2 images .FITS extensions.; fluxmap reads one image per file"):
        read_image(two)


def test_fits_blank_pixels_read_as_nan_and_a_cube_is_refused_by_its_frames(tmp_path):
    """Integer FITS marks undefined pixels with BLANK (the standard; astropy reads them as NaN once
    scaled): they were read as counts (-1, or 32767 + BZERO). And a cube of 5 frames (a kinetic
    series, NAXIS3 = 5) stopped with numpy's "cannot reshape array of size 46080 into shape
    (96,96)"; it is now refused saying it holds 5 frames."""
    stored = np.arange(NY * NX, dtype=np.int32).reshape(NY, NX) % 3000
    stored[2, 3] = stored[NY - 1, 0] = -1
    path = tmp_path / "blank.fits"
    path.write_bytes(_fits_hdu(_image_cards(True, 16, NY, NX, ["BLANK   =                   -1"]),
                               stored.astype(">i2").tobytes()))
    read, _ = read_image(path)
    np.testing.assert_array_equal(np.isnan(read), stored == -1)
    np.testing.assert_array_equal(read[stored != -1], stored[stored != -1].astype(np.float64))
    cube = tmp_path / "cube.fits"
    cards = ["SIMPLE  =                    T", "BITPIX  =                  -32", "NAXIS   =                    3",
             f"NAXIS1  = {NX:20d}", f"NAXIS2  = {NY:20d}", "NAXIS3  =                    5"]
    cube.write_bytes(_fits_hdu(cards, np.zeros((5, NY, NX), ">f4").tobytes()))
    with pytest.raises(ValueError, match=f"holds 5 frames of {NX} x {NY} .a cube"):
        read_image(cube)
