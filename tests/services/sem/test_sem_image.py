import io
import warnings

import numpy as np
import pytest
import tifffile
from PIL import Image

from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import detect_data_bar_rows, image_shape, read_sem_image


def _textured(rows=256, cols=300, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    return rng.integers(top // 5, 4 * top // 5, size=(rows, cols)).astype(dtype)


def _with_data_bar(image, bar_rows):
    top = np.iinfo(image.dtype).max
    bar = np.zeros((bar_rows, image.shape[1]), image.dtype)
    bar[bar_rows // 3 : bar_rows // 3 + 4, 20:120:3] = top  # "text"
    return np.vstack([image, bar])


@pytest.mark.real_data
def test_zeiss_metadata_of_the_real_series(pollen_series):
    expected_tilts = [-9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0]
    for index, tilt in enumerate(expected_tilts):
        image = read_sem_image((pollen_series / f"pot_0{index}.tif").read_bytes())
        assert image.tilt_deg == pytest.approx(tilt)  # 'Stage at T', not 'Tilt Angle' (30°)
        assert image.pixel_size_um == pytest.approx(0.05582, rel=1e-4)  # not 'Pixel Size' (111.6 nm)
        assert image.pixels.shape == (2048, 1536)  # stored rotated: 1536 wide, 2048 tall
        assert image.pixels.dtype == np.uint8
        assert image.data_bar_rows <= 2
        assert 40 < image.pixels.mean() < 200  # palette mapped to grey, not raw indices


def test_fei_metadata_gives_tilt_pixel_size_and_data_bar():
    image = _with_data_bar(_textured(dtype=np.uint16), 40)
    ini = "[Stage]\nStageT=0.0872665\n[Scan]\nPixelWidth=2.5e-08\n[Image]\nResolutionX=300\nResolutionY=256\n"
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, image, extratags=[(34682, "s", 0, ini, True)])
    read = read_sem_image(buffer.getvalue())
    assert read.tilt_deg == pytest.approx(5.0, abs=1e-4)
    assert read.pixel_size_um == pytest.approx(0.025)
    assert read.data_bar_rows == 40
    assert read.image.shape == (256, 300)


def _fei_tiff(image, ini) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, image, extratags=[(34682, "s", 0, ini, True)])
    return buffer.getvalue()


def test_metadata_that_leaves_too_few_rows_above_the_data_bar_is_refused_naming_the_file():
    """ResolutionY=1 once cut 255 of 256 rows off as a data bar, and the pair came back 0 % valid."""
    ini = "[Stage]\nStageT=0.0872665\n[Scan]\nPixelWidth=2.5e-08\n[Image]\nResolutionX=300\nResolutionY=1\n"
    with pytest.raises(InvalidInputError) as refused:
        read_sem_image(_fei_tiff(_textured(), ini), field="left.tif")
    assert refused.value.field == "left.tif" and "ResolutionY" in refused.value.message


def test_one_hot_pixel_does_not_crush_a_float_image_into_one_grey_level():
    image = _textured(dtype=np.uint16).astype(np.float32)
    hot = image.copy()
    hot[10, 10] = 1e30
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, hot)
    read = read_sem_image(buffer.getvalue()).pixels.astype(np.float64)
    assert np.corrcoef(read[hot < 1e30], image[hot < 1e30])[0, 1] > 0.999
    assert read.std() > 0.1 * read.max()


def test_png_16_bit_without_metadata():
    image = _textured(dtype=np.uint16)
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    read = read_sem_image(buffer.getvalue())
    np.testing.assert_array_equal(read.pixels, image)
    assert read.tilt_deg is None and read.pixel_size_um is None and read.data_bar_rows == 0


def test_data_bar_is_detected_and_textured_bottom_is_not():
    image = _textured()
    assert detect_data_bar_rows(image) == 0
    assert detect_data_bar_rows(_with_data_bar(image, 30)) == 30


@pytest.mark.parametrize(
    "content", [b"", b"not an image at all", b"II*\x00" + b"\x00" * 20, b"\x89PNG\r\n\x1a\n" + b"\x01" * 30]
)
def test_unreadable_files_raise_a_named_error(content):
    with pytest.raises(InvalidInputError) as error:
        read_sem_image(content, field="images[0].image")
    assert error.value.field == "images[0].image"


def _tiff(pixels: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    with warnings.catch_warnings():  # tifffile warns that a 0 x 0 page is nonconformant, as meant here
        warnings.simplefilter("ignore")
        tifffile.imwrite(buffer, pixels)
    return buffer.getvalue()


def _declaring(tag: str, value: int) -> bytes:
    """A 64 x 64 TIFF whose header says `tag` (ImageWidth, ImageLength) is `value` (< 65536)."""
    content = bytearray(_tiff(_textured(64, 64)))
    with tifffile.TiffFile(io.BytesIO(bytes(content))) as tiff:
        offset = tiff.pages.first.tags[tag].valueoffset
    content[offset : offset + 2] = value.to_bytes(2, "little")  # a SHORT, or a LONG's low half
    return bytes(content)


@pytest.mark.parametrize(
    "content",
    [
        pytest.param(_tiff(np.zeros((0, 0), np.uint8)), id="0x0"),
        pytest.param(_tiff(np.zeros((1, 100), np.uint8)), id="1x100"),
        pytest.param(_declaring("ImageWidth", 0), id="declared width 0"),
        pytest.param(_declaring("ImageLength", 0), id="declared height 0"),
    ],
)
def test_images_too_small_to_match_are_refused_by_their_header_and_when_decoded(content):
    """The memory estimate reads the declared size before decoding; it once divided by a width of 0."""
    for read in (image_shape, read_sem_image):
        with pytest.raises(InvalidInputError, match="at least 32x32 pixels") as error:
            read(content, field="images[0].image")
        assert error.value.field == "images[0].image"


@pytest.mark.parametrize("planar", ["contig", "separate"])
def test_rgb_tiffs_are_read_as_grey_whichever_way_their_planes_are_stored(planar):
    grey = _textured(64, 80)
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, np.stack([grey] * 3, axis=-1 if planar == "contig" else 0), photometric="rgb", planarconfig=planar
    )
    pixels = read_sem_image(buffer.getvalue()).pixels
    assert pixels.shape == (64, 80) and np.corrcoef(pixels.ravel(), grey.ravel())[0, 1] > 0.999
