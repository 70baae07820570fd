"""What a user who feeds `fracto` bad files and flags sees: one line on stderr naming the file or
the flag, exit code 2, never a traceback; and --json output that is JSON."""

import json
import zipfile

import numpy as np
import pytest

from fractoscope.cli.main import main
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import write_height_npz
from fractoscope.formats.x3p import write_x3p

CALIBRATION = Calibration((-5.0, 5.0), ("argument", "tilt_calibration"), (0.5, 0.04), 0.5, "argument")


def _fracto(capsys, *args) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `fracto ARGS`, run in this process."""
    with pytest.raises(SystemExit) as exited:
        main([str(arg) for arg in args])
    out, err = capsys.readouterr()
    return exited.value.code, out, err


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


def _height_map(path, z_um, **options) -> None:
    sigma_um = np.full(z_um.shape, 0.01, np.float32)
    write_height_npz(
        path,
        z_um=z_um,
        sigma_um=sigma_um,
        confidence=np.ones_like(sigma_um),
        local_sigma_um=sigma_um,
        calibration=CALIBRATION,
        record={"tilt_axis_deg": 90.0},
        **options,
    )


def _noise(shape=(64, 64), scale_um=1.0) -> np.ndarray:
    return (np.random.default_rng(1).normal(size=shape) * scale_um).astype(np.float32)


def _unreadable(path) -> None:
    """Writes at `path` the unreadable file its name says."""
    kind = path.stem
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("hello")
    elif kind == "truncated":
        whole = path.with_name(f"whole{path.suffix}")
        if path.suffix == ".x3p":
            write_x3p(whole, _noise(), pixel_size_um=0.5)
        else:
            _height_map(whole, _noise())
        path.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    elif kind == "not_npy":
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("z_um.npy", b"not a npy")
    elif kind == "record_list":
        np.savez(path, z_um=_noise(), record=np.str_("[1, 2]"))
    elif kind == "sigma_shape":
        np.savez(path, z_um=_noise(), sigma_um=np.zeros((3, 3), np.float32))
    elif kind == "bad_xml":
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("main.xml", b"<?xml version='1.0'?><p:ISO5436_2 xmlns:p='x'><Record1>")


@pytest.mark.parametrize(
    "name",
    [
        "empty.npz",
        "text.npz",
        "truncated.npz",
        "not_npy.npz",
        "record_list.npz",
        "sigma_shape.npz",
        "empty.x3p",
        "text.x3p",
        "truncated.x3p",
        "bad_xml.x3p",
    ],
)
def test_an_unreadable_file_is_named_once_with_exit_code_2(capsys, tmp_path, name):
    path = tmp_path / name
    _unreadable(path)
    code, out, err = _fracto(capsys, "roughness", path, "--json")
    line = _one_error_line(err)
    assert code == 2 and out == "" and line.startswith(f"error: {path}: ") and line.count(str(path)) == 1


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e-300", "1e300"])
@pytest.mark.parametrize("recorded", [True, False])
def test_a_bad_pixel_size_flag_is_refused_whether_or_not_the_map_records_one(capsys, tmp_path, value, recorded):
    path = tmp_path / "map.npz"
    if recorded:
        _height_map(path, _noise())
    else:
        np.savez(path, z_um=_noise())
    code, out, err = _fracto(capsys, "roughness", path, "--pixel-size-um", value, "--json")
    assert code == 2 and _one_error_line(err).startswith("error: --pixel-size-um: must be between 1e-5 and 1e4 µm")


def test_a_bad_pixel_size_flag_is_refused_by_export(capsys, tmp_path):
    _height_map(tmp_path / "map.npz", _noise())
    code, _, err = _fracto(
        capsys, "export", tmp_path / "map.npz", "--pixel-size-um", "0", "-o", tmp_path / "map.csv", "--data", tmp_path
    )
    assert code == 2 and _one_error_line(err).startswith("error: --pixel-size-um: must be between")


def test_a_map_with_a_pixel_size_array_and_no_record_needs_no_flag(capsys, tmp_path):
    np.savez(tmp_path / "numpy.npz", z_um=_noise(), pixel_size_um=np.float64(0.25))
    code, out, err = _fracto(capsys, "roughness", tmp_path / "numpy.npz", "--json")
    assert code == 0, err
    assert json.loads(out)["pixel_size_um"] == 0.25


def test_an_absurd_recorded_pixel_size_names_the_file(capsys, tmp_path):
    path = tmp_path / "huge.npz"
    np.savez(path, z_um=_noise(), pixel_size_um=np.float64(1e300))
    code, _, err = _fracto(capsys, "roughness", path, "--json")
    assert code == 2 and _one_error_line(err) == (
        f"error: {path}: its pixel size must be between 1e-5 and 1e4 µm, got 1e+300; give --pixel-size-um"
    )


@pytest.mark.slow
def test_json_output_writes_non_finite_numbers_as_null(capsys, tmp_path):
    path = tmp_path / "big.npz"
    _height_map(path, _noise(scale_um=1e30))  # psd.c_um4 overflows to infinity
    code, out, err = _fracto(capsys, "roughness", path, "--json")
    assert code == 0, err
    values = json.loads(out, parse_constant=lambda name: pytest.fail(f"{name} is not JSON (RFC 8259)"))
    assert None in values["psd"]["c_um4"]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--s-filter-um", "-1"], "error: --s-filter-um: must be a cut-off in µm >= 0"),
        (["--l-filter-um", "nan"], "error: --l-filter-um: must be a cut-off in µm >= 0"),
        (["--window-px", "0"], "error: --window-px: must be 1 to 1000 pixels"),
        (["--min-windows", "0"], "error: --min-windows: must be 0.5 to 100"),
        (["--direction-deg", "inf"], "error: --direction-deg: must be finite"),
        (["--levelling-region", "10,10,0,0"], "error: --levelling-region: min must be smaller than max"),
        (["--levelling-region", "500,500,600,600"], "error: --levelling-region: does not meet the analysed area"),
    ],
)
def test_a_bad_chain_setting_names_its_flag(capsys, tmp_path, flags, message):
    _height_map(tmp_path / "map.npz", _noise())
    code, _, err = _fracto(capsys, "roughness", tmp_path / "map.npz", *flags, "--json")
    assert code == 2 and _one_error_line(err).startswith(message)


@pytest.mark.parametrize(
    ("z_um", "message"),
    [
        (np.full((64, 64), np.nan), "holds fewer than 64 measured points"),
        (np.zeros((1, 4096)), "needs at least 16 x 16 points"),
    ],
)
def test_a_file_too_small_to_analyse_is_named_not_a_region(capsys, tmp_path, z_um, message):
    path = tmp_path / "small.npz"
    _height_map(path, z_um)
    code, _, err = _fracto(capsys, "roughness", path, "--json")
    assert code == 2 and _one_error_line(err).startswith(f"error: {path}: {message}")


def test_a_bad_sigma_map_names_the_file(capsys, tmp_path):
    path = tmp_path / "map.npz"
    z_um = _noise()
    np.savez(path, z_um=z_um, sigma_um=np.full_like(z_um, -1.0), pixel_size_um=np.float64(0.5))
    code, _, err = _fracto(capsys, "roughness", path, "--json")
    assert code == 2 and _one_error_line(err).startswith(f"error: {path}: sigma_um must be finite and non-negative")


@pytest.mark.parametrize(
    ("field", "argv", "named"),
    [
        ("chain.s_filter_um", ["roughness", "synthetic"], "--s-filter-um"),
        ("chain.levelling_region", ["roughness", "synthetic"], "--levelling-region"),
        ("area.region", ["roughness", "synthetic", "--region", "0,0,1,1"], "--region"),
        ("region", ["roughness", "synthetic", "--roi", "zoom"], "synthetic"),
        ("spacing_um", ["profile", "synthetic", "--from", "0,0", "--to", "1,1", "-o", "p.csv"], "--spacing-um"),
        ("request_id", ["reconstruct", "manifest.json", "--request-id", "x" * 300], "--request-id"),
    ],
)
def test_request_fields_of_server_errors_are_named_as_flags(field, argv, named):
    from fractoscope.cli.common import in_command_line_terms
    from fractoscope.cli.main import build_parser

    args = build_parser().parse_args(argv)
    assert in_command_line_terms(field, f"{field}: is wrong", args) == f"{named}: is wrong"


def test_a_bad_image_of_a_manifest_is_named_by_its_file(capsys, tmp_path):
    """The server names rois[0].images[1].image; the command line names the manifest's file."""
    texture = np.random.default_rng(2).integers(0, 256, (64, 64))
    _grey_tiff(tmp_path / "l.tif", texture)
    (tmp_path / "r.tif").write_bytes(b"not an image")
    (tmp_path / "manifest.json").write_text(
        json.dumps(
            {
                "specimen": "s",
                "rois": [
                    {"id": "overview", "left": "l.tif", "right": "r.tif", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}
                ],
            }
        )
    )
    code, _, err = _fracto(capsys, "reconstruct", tmp_path / "manifest.json", "--data", tmp_path / "data")
    assert code == 2 and _one_error_line(err).startswith(f"error: {tmp_path / 'r.tif'}: not a TIFF, PNG or JPEG file")


def test_export_of_an_npz_to_x3p_carries_its_calibration(capsys, tmp_path):
    from fractoscope.formats.x3p import read_x3p

    _height_map(tmp_path / "map.npz", _noise(shape=(20, 30)))
    code, out, err = _fracto(
        capsys, "export", tmp_path / "map.npz", "-o", tmp_path / "map.x3p", "--data", tmp_path / "data", "--json"
    )
    assert code == 0, err
    surface = read_x3p(tmp_path / "map.x3p")
    assert surface.z_um.shape == (20, 30) and surface.step_x_um == pytest.approx(0.5)
    assert Calibration.from_dict(json.loads(surface.comment)["calibration"]) == CALIBRATION


def _grey_tiff(path, values) -> None:
    import tifffile

    tifffile.imwrite(path, np.asarray(values, np.uint8))


@pytest.mark.parametrize(
    "outputs, flag",
    [
        (["-o", "heights.txt"], "-o"),
        (["-o", ""], "-o"),
        (["-o", "."], "-o"),
        (["-o", "missing/heights.npz"], "-o"),
        (["-o", "first.npz"], "-o"),
        (["-o", "heights.npz", "--png", "heights.bmp"], "--png"),
        (["-o", "heights.npz", "--png", "first.tif"], "--png"),
    ],
)
def test_height_outputs_are_checked_before_any_matching(capsys, tmp_path, monkeypatch, outputs, flag):
    """A name the map would not be written under, a missing folder, or an input image to be
    overwritten (`--png first.tif` once replaced the SEM image with the picture)."""
    monkeypatch.chdir(tmp_path)
    texture = np.random.default_rng(2).integers(0, 256, (64, 64))
    _grey_tiff(tmp_path / "first.tif", texture)
    _grey_tiff(tmp_path / "second.tif", texture)
    (tmp_path / "first.npz").write_bytes((tmp_path / "first.tif").read_bytes())  # an input named like a map
    images = ["first.npz" if outputs[1] == "first.npz" else "first.tif", "second.tif"]
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    code, out, err = _fracto(capsys, "height", *images, "--tilt", "-5", "5", "--pixel-size-um", "0.1", *outputs)
    assert code == 2 and _one_error_line(err).startswith(f"error: {flag}: ")
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before


_PROFILE = ["profile", "s", "--from", "0,0", "--to", "1,1"]


@pytest.mark.parametrize(
    "argv, flag",
    [
        ([*_PROFILE, "-o", "p.txt"], "-o"),
        ([*_PROFILE, "-o", "."], "-o"),  # "." once gave [Errno 21]
        ([*_PROFILE, "-o", "p.csv", "--plot", "p.exe"], "--plot"),  # once matplotlib's traceback, after the CSV
        (["export", "map.npz", "-o", "missing/map.x3p"], "-o"),  # once made the folders
        (["export", "map.npz", "-o", "map.npz"], "-o"),
        (["report", "s", "-o", "r.pdf"], "-o"),
        (["report", "s", "-o", "r.html", "--pdf", "missing/r.pdf"], "--pdf"),
        (["mesh", "map.npz", "-o", "map.npz"], "-o"),
        (["tiles", "s", "-o", "map.npz/tiles"], "-o"),  # once [Errno 20]
    ],
)
def test_outputs_of_every_command_are_checked_before_any_work(capsys, tmp_path, monkeypatch, argv, flag):
    monkeypatch.chdir(tmp_path)
    _height_map(tmp_path / "map.npz", _noise())
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    code, _, err = _fracto(capsys, *argv, *(["--data", "data"] if argv[0] != "mesh" else []))
    assert code == 2 and _one_error_line(err).startswith(f"error: {flag}: ")
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before


@pytest.mark.parametrize(
    "constant, noise, named, message",
    [
        (1, False, "second.tif", "is one grey level (128) throughout"),
        (0, False, "first.tif", "is one grey level (128) throughout"),
        (None, True, "second.tif", "almost nothing of it could be matched"),
    ],
)
def test_a_pair_that_shares_nothing_is_refused_naming_the_image_at_fault(
    capsys, tmp_path, constant, noise, named, message
):
    """No pixel of a constant or a noise image matches a textured one: an empty map is not a
    measurement, so there is no output and the error names the image (a constant first image
    was once blamed on the second)."""
    from fractoscope.synthetic import self_affine_surface

    rng = np.random.default_rng(3)
    texture = self_affine_surface((128, 128), hurst=0.3, rms_um=1.0, seed=1, min_wavelength_px=3.0)
    images = [
        (texture - texture.min()) / np.ptp(texture) * 200 + 20,
        rng.integers(0, 256, texture.shape) if noise else texture,
    ]
    if constant is not None:
        images[constant] = np.full(texture.shape, 128)
    for name, values in zip(("first.tif", "second.tif"), images):
        _grey_tiff(tmp_path / name, values)
    code, _, err = _fracto(
        capsys,
        "height",
        tmp_path / "first.tif",
        tmp_path / "second.tif",
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "-o",
        tmp_path / "heights.npz",
    )
    assert code == 2 and _one_error_line(err).startswith(f"error: {tmp_path / named}: {message}")
    assert not (tmp_path / "heights.npz").exists()


@pytest.mark.parametrize(
    "stage_t_rad, pixel_width_m, named",
    [
        ("nan", "2.5e-08", "the stage tilt in its metadata"),
        ("100", "2.5e-08", "the stage tilt in its metadata"),
        ("0.0872665", "1e-300", "the pixel size in its metadata"),
    ],
)
def test_unusable_metadata_names_the_file_not_a_flag_the_user_never_gave(
    capsys, tmp_path, stage_t_rad, pixel_width_m, named
):
    import tifffile

    texture = np.random.default_rng(4).integers(40, 200, (64, 64)).astype(np.uint8)
    paths = []
    for name, stage_t in (("bad.tif", stage_t_rad), ("good.tif", "-0.0872665")):
        ini = (
            f"[Stage]\nStageT={stage_t}\n[Scan]\nPixelWidth={pixel_width_m}\n[Image]\nResolutionX=64\nResolutionY=64\n"
        )
        tifffile.imwrite(tmp_path / name, texture, extratags=[(34682, "s", 0, ini, True)])
        paths.append(tmp_path / name)
    code, _, err = _fracto(capsys, "height", *paths, "-o", tmp_path / "heights.npz")
    line = _one_error_line(err)
    assert (
        code == 2
        and line.startswith(f"error: {paths[0]}: {named}")
        and "--tilt" not in line
        and "--pixel-size-um" not in line
    )


@pytest.mark.parametrize("axis", ["1e300", "-400", "nan"])
def test_a_tilt_axis_no_angle_can_be_is_refused(capsys, tmp_path, axis):
    texture = np.random.default_rng(5).integers(40, 200, (64, 64))
    _grey_tiff(tmp_path / "first.tif", texture)
    _grey_tiff(tmp_path / "second.tif", texture)
    code, _, err = _fracto(
        capsys,
        "height",
        tmp_path / "first.tif",
        tmp_path / "second.tif",
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "--tilt-axis-deg",
        axis,
        "-o",
        tmp_path / "heights.npz",
    )
    assert code == 2 and _one_error_line(err).startswith("error: --tilt-axis-deg: must be an angle within ±360°")


@pytest.mark.parametrize(
    "source, extra, named",
    [
        ("missing.npz", [], "cannot read missing.npz"),
        ("manifest.json", [], "manifest.json: give a specimen id or an .npz height map"),
        ("map.npz", ["--roi", "zoom"], "--roi and --region are for specimens"),
        ("s", ["--pixel-size-um", "0.1"], "--pixel-size-um is for an npz height map"),
        ("no-such-specimen", [], "no specimen 'no-such-specimen'"),
    ],
)
def test_report_names_its_real_argument(capsys, tmp_path, monkeypatch, source, extra, named):
    """`fracto report` takes a specimen id or an npz height map; an error names what was given
    (once "specimen_id: 'h.npz' is not an id" for a file)."""
    monkeypatch.chdir(tmp_path)
    _height_map(tmp_path / "map.npz", _noise())
    (tmp_path / "manifest.json").write_text("{}")
    code, _, err = _fracto(capsys, "report", source, *extra, "-o", "r.html", "--data", "data")
    assert code in (2, 4) and _one_error_line(err).startswith(f"error: {named}")
    assert not (tmp_path / "r.html").exists()


def test_report_of_an_npz_height_map(capsys, tmp_path):
    """A height map file is reported as readily as a specimen: its calibration, as it records it."""
    _height_map(tmp_path / "map.npz", _noise())
    code, out, err = _fracto(capsys, "report", tmp_path / "map.npz", "-o", tmp_path / "map.html", "--json")
    assert code == 0, err
    assert json.loads(out)["outputs"] == [str(tmp_path / "map.html")]
    html = (tmp_path / "map.html").read_text()
    assert "Measurement report" in html and "No image files are kept with these heights" in html
    assert 'data-name="overview.tilt_sigma_deg[1]" data-value="0.04"' in html and "tilt_calibration" in html
