"""The surface texture chain through the API: GetRoughness and GetProfile over gRPC and the HTTP
JSON endpoints, on a specimen stored with a known form, a known roughness and a known sigma map
(no matching in between, so the truths are exact)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import grpc
import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.http.server import start_http_server
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.model import RoiEntry, write_description, write_roi_arrays
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey, TileRecord
from fractoscope.store.folder import SpecimenStore
from fractoscope.v1 import tiles_pb2

PIXEL_UM = 0.25
SIZE_PX = 640
SPHERE_RADIUS_UM = 400.0
SIGMA_UM = 0.02
TILT_REL = 0.01


def _texture() -> np.ndarray:
    return synthetic.self_affine_surface((SIZE_PX, SIZE_PX), hurst=0.8, rms_um=0.5, seed=21, max_wavelength_px=40)


def _centred_sa(z: np.ndarray) -> float:
    return float(np.mean(np.abs(z - z.mean())))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(client, HTTP base URL, texture) for a one-ROI specimen "dome": a sphere of 400 µm radius
    carrying the texture, with a sigma map of 0.02 µm and a 1 % tilt uncertainty."""
    data = tmp_path_factory.mktemp("chain") / "data"
    texture = _texture()
    rows, cols = np.indices(texture.shape) * PIXEL_UM
    centre = SIZE_PX * PIXEL_UM / 2
    dome = np.sqrt(SPHERE_RADIUS_UM**2 - (cols - centre) ** 2 - (rows - centre) ** 2)
    z_um = (dome + texture).astype(np.float32)
    roi = PlacedRoi(
        "overview",
        100.0,
        PIXEL_UM,
        (0.0, 0.0),
        z_um,
        np.zeros(z_um.shape, np.uint8),
        np.full(z_um.shape, SIGMA_UM, np.float32),
    )
    entry = RoiEntry(roi.id, "", 100.0, PIXEL_UM, roi.origin_um, z_um.shape, tilt_rel_uncertainty=TILT_REL)
    root = TileKey(0, 0, 0)
    store = SpecimenStore(data)
    with store.writing("dome") as staging:
        (staging / root.uri).parent.mkdir(parents=True)
        (staging / root.uri).write_bytes(b"glTF")
        (staging / "tileset.json").write_text("{}")
        write_roi_arrays(staging, roi)
        write_description(
            staging,
            specimen_id="dome",
            request_id="",
            rois=[entry],
            layout=QuadtreeLayout((0.0, 0.0), SIZE_PX * PIXEL_UM),
            tiles={root: TileRecord(root, roi.id, 100.0, OPTICAL, 0.0, 0.0, 1.0)},
        )
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=data))
    server.start()
    http = start_http_server(SpecimenStore(data))
    with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=300) as client:
        yield client, f"http://127.0.0.1:{http.server_port}/api/specimens/dome", texture
    http.shutdown()
    server.stop(grace=None)


def test_a_known_form_with_roughness_gives_the_roughness_sa_back(served):
    client, _, texture = served
    sphere = client.roughness("dome", form="sphere")
    assert sphere["Sa"] == pytest.approx(_centred_sa(texture), rel=0.01)
    assert (
        sphere["chain"]["form"] == "sphere"
        and sphere["chain"]["s_filter_um"] == 0
        and sphere["chain"]["l_filter_um"] == 0
    )
    assert client.roughness("dome")["Sa"] > 3 * sphere["Sa"]  # a plane leaves the dome in


def test_uncertainties_come_from_the_sigma_map_and_the_tilt(served):
    client, _, _ = served
    values = client.roughness("dome", form="sphere")
    assert values["tilt_rel_uncertainty"] == pytest.approx(TILT_REL)
    sa = values["uncertainty"]["Sa"]
    assert sa["u_tilt"] == pytest.approx(TILT_REL * values["Sa"], rel=1e-6)
    assert 0 < sa["u_noise"] < sa["u_tilt"] and sa["u_total"] == pytest.approx(np.hypot(sa["u_tilt"], sa["u_noise"]))
    # Noise adds its variance: Sq² = Sq_true² + sigma², so the bias of Sq is about sigma² / (2 Sq).
    assert values["noise_bias"]["Sq"] == pytest.approx(SIGMA_UM**2 / (2 * values["Sq"]), rel=0.02)
    assert values["uncertainty"]["Sal"]["u_noise"] is None  # no first-order derivative
    assert values["units"]["Vmc"] == "µm³/µm²" and set(values["units"]) >= {"Sal", "Str", "Std", "Sk", "Spd", "Spc"}


def test_hurst_exponents_by_both_methods_along_and_across_a_direction(served):
    client, _, _ = served
    values = client.roughness("dome", form="sphere", direction_deg=30.0, window_px=2.0)
    fits = {(fit["method"], fit["side"]): fit for fit in values["hurst"]}
    assert set(fits) == {("hhc", "along"), ("hhc", "across"), ("psd", "along"), ("psd", "across")}
    assert fits["hhc", "along"]["direction_deg"] == 30.0 and fits["hhc", "across"]["direction_deg"] == 120.0
    # Lags from 4 windows of 2 px to a tenth of the field.
    assert fits["hhc", "along"]["fit_min_um"] == pytest.approx(4 * 2 * PIXEL_UM, rel=0.15)
    assert fits["hhc", "along"]["fit_max_um"] <= 0.1 * SIZE_PX * PIXEL_UM * 1.001
    assert values["hurst_exponent"] == fits["hhc", "along"]["hurst"]
    assert all(0 < fit["hurst_stderr"] < 0.2 for fit in fits.values())
    assert len(values["psd"]["q_per_um"]) == len(values["psd"]["c_um4"]) > 10
    assert values["chain"]["window_px"] == 2.0 and values["chain"]["min_windows"] == 4.0 and values["hurst_note"] == ""


def test_a_field_too_small_for_four_windows_is_fitted_from_two_and_says_so(served):
    client, _, _ = served
    values = client.roughness(
        "dome", form="sphere"
    )  # the default matching window, 15 px: 4 windows exceed a tenth of 640 px
    assert {fit["fit_min_windows"] for fit in values["hurst"]} == {2.0}
    assert "too small" in values["hurst_note"]


def test_filters_are_applied_and_named(served):
    client, _, texture = served
    values = client.roughness("dome", form="sphere", s_filter_um=1.0, l_filter_um=10.0)
    assert (values["chain"]["s_filter_um"], values["chain"]["l_filter_um"]) == (1.0, 10.0)
    assert values["Sa"] < 0.8 * _centred_sa(texture)  # the texture's long waves are gone
    levelled = client.roughness("dome", form="plane", levelling_region_um=(0.0, 0.0, 40.0, 40.0))
    assert levelled["chain"]["levelling_region_um"] == [0.0, 0.0, 40.0, 40.0]


def test_profiles_name_their_chain_and_default_to_iso_21920_3(served):
    client, base, _ = served
    line = [(10.0, 80.0), (150.0, 80.0)]
    default = client.profile("dome", line)
    assert (
        default.chain["form"] == "plane"
        and default.chain["l_filter_um"] == 25.0
        and default.chain["s_filter_um"] == 0.8
    )
    assert default.chain["cutoffs_from_iso_table"] is False  # 140 µm: below the table's 400 µm
    assert default.roughness_um.shape == default.z_um.shape
    arc = client.profile("dome", line, form="sphere", s_filter_um=0, l_filter_um=0)
    assert (arc.chain["form"], arc.chain["s_filter_um"], arc.chain["l_filter_um"]) == ("sphere", 0.0, 0.0)
    assert arc.parameters["Rq"] > default.parameters["Rq"] and {"Rk", "RSm", "Rdq"} <= set(arc.parameters)
    with urllib.request.urlopen(f"{base}/profile?from=10,80&to=150,80&form=poly2&l_filter_um=50") as response:
        answer = json.loads(response.read())
    assert answer["chain"]["form"] == "poly2" and answer["chain"]["l_filter_um"] == 50.0
    assert len(answer["roughness_um"]) == len(answer["z_um"])


def test_grpc_errors_name_the_chain_field(served):
    client, _, _ = served
    for options, field in (
        ({"s_filter_um": -1.0}, "chain.s_filter_um"),
        ({"s_filter_um": 5.0, "l_filter_um": 2.0}, "chain.s_filter_um"),
        ({"window_px": 0.0}, "chain.window_px"),
        ({"levelling_region_um": (500.0, 500.0, 600.0, 600.0)}, "chain.levelling_region"),
    ):
        with pytest.raises(ClientError) as raised:
            client.roughness("dome", **options)
        assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT and raised.value.field == field, options
    request = tiles_pb2.GetRoughnessRequest(specimen_id="dome", roi="overview", chain=tiles_pb2.SurfaceChain(form=99))
    with pytest.raises(grpc.RpcError) as unknown:
        client._tiles.GetRoughness(request)
    assert unknown.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "chain.form" in unknown.value.details()


def test_http_roughness_takes_the_chain_and_answers_as_the_cli(served):
    client, base, texture = served
    with urllib.request.urlopen(f"{base}/roughness?form=sphere&direction_deg=45&robust_form=true") as response:
        answer = json.loads(response.read())
    assert answer["Sa"] == pytest.approx(_centred_sa(texture), rel=0.01)
    assert (
        answer["chain"]["form"] == "sphere"
        and answer["chain"]["robust_form"] is True
        and answer["chain"]["direction_deg"] == 45.0
    )
    assert set(answer) == set(client.roughness("dome", form="sphere"))


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("form=poly9", "form"),
        ("s_filter_um=abc", "s_filter_um"),
        ("s_filter_um=5&l_filter_um=2", "s_filter_um"),
        ("l_filter_um=-3", "l_filter_um"),
        ("levelling_region=1,2", "levelling_region"),
        ("direction_deg=nan", "direction_deg"),
        ("window_px=0.5", "window_px"),
        ("min_windows=0", "min_windows"),
        ("robust_form=maybe", "robust_form"),
    ],
)
def test_http_names_a_bad_chain_parameter(served, query, field):
    _, base, _ = served
    with pytest.raises(urllib.error.HTTPError) as bad:
        urllib.request.urlopen(f"{base}/roughness?{query}")
    answer = json.loads(bad.value.read())
    assert bad.value.code == 400 and answer["field"] == field, answer
