"""`make bench`: height accuracy per fracture surface type, side by side with the peers, and where
the error comes from.

For each reference surface (synthetic.reference_surface: self-affine, dimples, cleavage), 640²
at 0.1 µm/px, tilts ±5° and 0/10°, 2 % noise, as in the accuracy tests:

- peers: the default method (TGV_ZNCC), window correlation (WINDOW_ZNCC, the paper's), and
  OpenCV's StereoSGBM as 3D-SEM and pollen3d configure it (benchmarks.peers): valid share, RMS
  error as % of the height range, Sa error (Matching II's targets: self-affine ≤ 1.0 %, dimples
  ≤ 1.5 %, cleavage ≤ 2.0 % RMS; ≥ 98 %, 98 %, 95 % valid; Sa within 2 %);
- the default method on the same pair without noise, with the secondary-electron shading made a
  fixed property of the surface (as if it did not change with tilt), and with both ("ideal"
  images that differ only by parallax): how much of the error each causes;
- the window floor: the RMS difference between the truth and the truth averaged over one 15 px
  window, which a matcher that finds one disparity per window leaves.

Then two reference cases of their own: a low-magnification overview of ductile dimples
(synthetic.overview_dimple_surface, 288² and 512² at 0.4 µm/px; target ≤ 2 % RMS, Sa within 3 %)
and a -5/0/+5° dimple series with nominal tilts 10 % off, calibrated (target ≤ 1.5 % RMS).

Writes bench-results/accuracy.json and prints the tables.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from benchmarks import peers
from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo import matching, tilt_series
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_height_map, compute_series_height_map

SIZE_PX = 640
MARGIN_PX = 64
BORDER_PX = 16
TILTS_DEG = ((-5.0, 5.0), (0.0, 10.0))
WINDOW_PX = MatchingOptions().window_px
OVERVIEW_SIZES_PX = (288, 512)
SERIES_TILTS_DEG, SERIES_NOMINAL_DEG = (-5.0, 0.0, 5.0), (-5.0, 0.5, 5.5)


def _render(surface_um, tilt_deg, *, pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM, size_px=SIZE_PX, **render):
    return synthetic.render_stereo_pair(
        surface_um, pixel_size_um=pixel_size_um, tilt_deg=tilt_deg, output_shape=(size_px, size_px), seed=1, **render
    )


def _ours(pair, tilt_deg, method, *, pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM) -> synthetic.HeightErrors:
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    result = compute_height_map(
        first, second, tilt_deg=tilt_deg, pixel_size_um=pixel_size_um, options=MatchingOptions(method=method)
    )
    return synthetic.height_errors(result.z_um, pair.z_seen_um, border_px=BORDER_PX)


def _peer(pair, tilt_deg, match) -> synthetic.HeightErrors:
    """A peer's disparities of the (rectified) synthetic pair to heights by the pipeline's formula."""
    columns_px = np.arange(SIZE_PX, dtype=np.float64) - (SIZE_PX - 1) / 2.0
    x_px = np.broadcast_to(columns_px[None, :], pair.first.shape)
    truth_range_px = (
        np.ptp(pair.z_seen_um) / synthetic.REFERENCE_PIXEL_SIZE_UM * np.sin(np.radians(abs(tilt_deg[1] - tilt_deg[0])))
    )
    disparity = match(pair.first, pair.second, int(np.ceil(truth_range_px + 0.02 * SIZE_PX)) + 8)
    z_px, _ = tilt_series.heights_px(x_px, np.stack([np.zeros_like(disparity), disparity]), tilt_deg)
    return synthetic.height_errors(z_px * synthetic.REFERENCE_PIXEL_SIZE_UM, pair.z_seen_um, border_px=BORDER_PX)


def _window_floor_of_range(truth_um: np.ndarray) -> float:
    """RMS of the truth minus its average over one window, as a fraction of the height range."""
    truth = truth_um.astype(np.float32)
    averaged = cv2.boxFilter(truth, -1, (WINDOW_PX, WINDOW_PX), borderType=cv2.BORDER_REFLECT)
    inner = (slice(BORDER_PX, -BORDER_PX),) * 2
    return float(np.sqrt(np.mean((truth - averaged)[inner] ** 2)) / np.ptp(truth[inner]))


def _figures(errors: synthetic.HeightErrors) -> dict:
    return {
        "valid_percent": 100 * errors.valid_fraction,
        "rms_percent_of_range": 100 * errors.rms_of_range,
        "sa_error_percent": 100 * errors.sa_relative,
    }


def _surface_rows() -> list[dict]:
    rows = []
    for kind in synthetic.REFERENCE_SURFACES:
        surface = synthetic.reference_surface(kind, SIZE_PX + MARGIN_PX, seed=1)
        for tilt_deg in TILTS_DEG:
            pair = _render(surface, tilt_deg)
            no_noise, fixed = {"noise_fraction": 0.0}, {"shading_tilt_deg": float(np.mean(tilt_deg))}
            default = "tgv_zncc"
            rows.append(
                {
                    "surface": kind,
                    "tilt_deg": list(tilt_deg),
                    "tgv_zncc": _figures(_ours(pair, tilt_deg, default)),
                    "window_zncc": _figures(_ours(pair, tilt_deg, "window_zncc")),
                    "sgbm_3d_sem": _figures(_peer(pair, tilt_deg, peers.sgbm_3d_sem)),
                    "sgbm_pollen3d": _figures(_peer(pair, tilt_deg, peers.sgbm_pollen3d)),
                    "rms_percent_without_noise": 100
                    * _ours(_render(surface, tilt_deg, **no_noise), tilt_deg, default).rms_of_range,
                    "rms_percent_with_fixed_shading": 100
                    * _ours(_render(surface, tilt_deg, **fixed), tilt_deg, default).rms_of_range,
                    "rms_percent_ideal_images": 100
                    * _ours(_render(surface, tilt_deg, **no_noise, **fixed), tilt_deg, default).rms_of_range,
                    "window_floor_rms_percent": 100 * _window_floor_of_range(pair.z_seen_um),
                }
            )
    return rows


def _overview_rows() -> list[dict]:
    rows = []
    for size_px in OVERVIEW_SIZES_PX:
        surface = synthetic.overview_dimple_surface(size_px + MARGIN_PX, seed=1)
        pair = _render(surface, (-5.0, 5.0), pixel_size_um=synthetic.OVERVIEW_PIXEL_SIZE_UM, size_px=size_px)
        rows.append(
            {
                "size_px": size_px,
                "window_floor_rms_percent": 100 * _window_floor_of_range(pair.z_seen_um),
                **{
                    method: _figures(_ours(pair, (-5.0, 5.0), method, pixel_size_um=synthetic.OVERVIEW_PIXEL_SIZE_UM))
                    for method in matching.METHODS
                },
            }
        )
    return rows


def _series_rows() -> list[dict]:
    """A -5/0/+5° dimple series whose nominal tilts read both steps 10 % large, calibrated: RMS
    error after the frame's tilt (unobservable) is taken out, % of the height range."""
    surface = synthetic.reference_surface("dimples", SIZE_PX + MARGIN_PX, seed=5)
    images, truth = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=SERIES_TILTS_DEG, output_shape=(SIZE_PX, SIZE_PX), seed=5
    )
    views = [SemImage(image, None, 0.1, 0) for image in images]
    rows = []
    for method in matching.METHODS:
        result = compute_series_height_map(
            views, tilt_deg=SERIES_NOMINAL_DEG, options=MatchingOptions(calibrate_tilt=True, method=method)
        )
        known = np.isfinite(result.z_um)
        known[:BORDER_PX] = known[-BORDER_PX:] = known[:, :BORDER_PX] = known[:, -BORDER_PX:] = False
        rows_px, cols_px = np.nonzero(known)
        plane = np.column_stack([rows_px, cols_px, np.ones(known.sum())])
        error = result.z_um[known] - truth[known]
        error -= plane @ np.linalg.lstsq(plane, error, rcond=None)[0]
        rows.append(
            {
                "method": method.value,
                "tilt_deg": result.report["tilt_deg"],
                "tilt_sigma_deg": result.report["tilt_sigma_deg"],
                "rms_percent_of_range": float(100 * np.sqrt(np.mean(error**2)) / np.ptp(truth)),
            }
        )
    return rows


PEERS = ("tgv_zncc", "window_zncc", "sgbm_3d_sem", "sgbm_pollen3d")


def _print(rows, overview, series, out) -> None:
    print(
        f"{'surface':<12}{'tilts':>7}"
        + "".join(f"{name:>26}" for name in PEERS)
        + f"{'no noise':>10}{'fixed shading':>15}{'ideal':>7}{'floor':>7}"
    )
    for row in rows:
        cells = "".join(
            f"{row[n]['rms_percent_of_range']:>8.2f} % {row[n]['valid_percent']:>5.1f} % "
            f"{row[n]['sa_error_percent']:>+5.1f} %"
            for n in PEERS
        )
        print(
            f"{row['surface']:<12}{'/'.join(f'{t:g}' for t in row['tilt_deg']):>7}{cells}"
            f"{row['rms_percent_without_noise']:>10.2f}{row['rms_percent_with_fixed_shading']:>15.2f}"
            f"{row['rms_percent_ideal_images']:>7.2f}{row['window_floor_rms_percent']:>7.2f}"
        )
    print(
        "Each peer: RMS error (% of range), valid share, Sa error; the last four columns are the default method's; "
        f"floor: the truth minus its {WINDOW_PX}² window average."
    )
    for row in overview:
        print(
            f"overview {row['size_px']}² at {synthetic.OVERVIEW_PIXEL_SIZE_UM} µm/px (floor "
            f"{row['window_floor_rms_percent']:.2f} %): "
            + ", ".join(
                f"{m} {row[m]['rms_percent_of_range']:.2f} % RMS, Sa {row[m]['sa_error_percent']:+.1f} %"
                for m in matching.METHODS
            )
        )
    for row in series:
        print(
            f"calibrated dimple series {row['method']}: tilts {np.round(row['tilt_deg'], 3).tolist()}, RMS "
            f"{row['rms_percent_of_range']:.2f} %"
        )
    print(f"Written to {out / 'accuracy.json'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    args = parser.parse_args()
    rows, overview, series = _surface_rows(), _overview_rows(), _series_rows()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "accuracy.json").write_text(
        json.dumps({"window_px": WINDOW_PX, "rows": rows, "overview": overview, "series": series}, indent=1)
    )
    _print(rows, overview, series, out)


if __name__ == "__main__":
    main()
