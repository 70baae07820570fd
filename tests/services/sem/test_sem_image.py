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


def _jpeg(pixels: np.ndarray, quality: int = 95) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def test_jpeg_is_read_with_a_note_that_its_compression_biases_matching():
    image = _textured(rows=128, cols=160)
    smooth = np.round(
        np.clip(128 + 60 * np.sin(np.arange(160) / 9.0)[None, :] * np.cos(np.arange(128) / 7.0)[:, None], 0, 255)
    ).astype(np.uint8)
    read = read_sem_image(_jpeg(smooth), field="left.jpg")
    assert read.pixels.shape == (128, 160) and read.pixels.dtype == np.uint8
    assert np.abs(read.pixels.astype(float) - smooth).mean() < 3  # lossy, but the same picture
    assert read.notes and read.notes[0].startswith("left.jpg: a JPEG file") and "biases the matching" in read.notes[0]
    assert image_shape(_jpeg(image), field="left.jpg") == (128, 160)


def test_colour_is_reduced_to_bt601_luminance_with_a_note():
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, size=(96, 120, 3)).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="PNG")
    read = read_sem_image(buffer.getvalue(), field="colour.png")
    expected = np.round(rgb.astype(float) @ [0.299, 0.587, 0.114])
    assert read.pixels.dtype == np.uint8 and np.abs(read.pixels - expected).max() <= 1
    assert any("luminance" in note and note.startswith("colour.png: ") for note in read.notes)
    grey_as_rgb = np.repeat(_textured(96, 120)[..., None], 3, axis=-1)  # a grey image saved as RGB: no note
    read = read_sem_image(_tiff(grey_as_rgb))
    np.testing.assert_array_equal(read.pixels, grey_as_rgb[..., 0])
    assert read.notes == ()


def test_a_16_bit_tiff_keeps_its_full_depth():
    image = _textured(dtype=np.uint16)
    read = read_sem_image(_tiff(image))
    assert read.pixels.dtype == np.uint16 and read.notes == ()
    np.testing.assert_array_equal(read.pixels, image)


def _zeiss_like_tiff() -> bytes:
    """A TIFF laid out as SmartSEM writes one: pixel strips first, the directory and its long tag
    values (metadata) at the end of the file."""
    image = _textured(256, 300)
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, image, rowsperstrip=8, description="x" * 4000, metadata=None)
    return buffer.getvalue()


@pytest.mark.parametrize("keep", [0.5, 0.97, 0.999])
def test_a_truncated_tiff_is_refused_naming_the_file(keep):
    """A copy cut short once read as an image with its metadata silently dropped (tifffile reads
    what is there), and a pair matched for half a minute before anything failed."""
    content = _zeiss_like_tiff()
    cut = content[: int(len(content) * keep)]
    for read in (read_sem_image, image_shape):
        with pytest.raises(InvalidInputError) as refused:
            read(cut, field="pot_00.tif")
        assert refused.value.field == "pot_00.tif" and "truncated" in refused.value.message
        assert str(refused.value).startswith("pot_00.tif: ")


@pytest.mark.real_data
def test_the_real_zeiss_file_cut_short_is_refused(pollen_series):
    content = (pollen_series / "pot_00.tif").read_bytes()
    assert read_sem_image(content).tilt_deg == pytest.approx(-9.0)
    for keep in (0.5, 0.99, 0.9999):  # before, inside and after the directory (which SmartSEM writes last)
        with pytest.raises(InvalidInputError, match="truncated") as refused:
            read_sem_image(content[: int(len(content) * keep)], field="pot_00.tif")
        assert refused.value.field == "pot_00.tif"


def test_a_garbage_file_is_refused_naming_the_file():
    garbage = np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes()
    for content in (garbage, b"II*\x00" + garbage, b"\xff\xd8\xff" + garbage):
        with pytest.raises(InvalidInputError) as refused:
            read_sem_image(content, field="garbage.tif")
        assert refused.value.field == "garbage.tif"


def test_size_messages_are_width_by_height():
    with pytest.raises(InvalidInputError, match="got 300x20"):
        read_sem_image(_tiff(_textured(20, 300)))
