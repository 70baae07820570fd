"""Dense matching on several cores: strips matched at once on threads give exactly the answer
that one thread gives, on a pair whose disparity is known."""

import functools
import itertools
import threading

import numpy as np
import pytest

from fractoscope.stereo import correlation, matching
from fractoscope.synthetic import self_affine_surface

SHAPE = (480, 192)
STRIP_PIXELS = SHAPE[1] * 150  # four strips of this pair


def _pair():
    """A textured left image, the right one it matches under a ramp of -4 to 4 px along rows (left
    pixel (r, c) seen at right (r, c + d)), and the ramp, (rows, cols) float32 each."""
    texture = self_affine_surface(SHAPE, hurst=0.3, rms_um=1.0, seed=4, min_wavelength_px=3.0)
    left = ((texture - texture.min()) / np.ptp(texture) * 200 + 20).astype(np.float32)
    ramp = np.linspace(-4, 4, SHAPE[1], dtype=np.float32)[None, :].repeat(SHAPE[0], axis=0)
    return left, correlation.warp_along_rows(left, -ramp), ramp


def _record_threads(monkeypatch, method, strip_method, workers):
    """The names of the threads that match strips by `method` (with `strip_method`) from now on
    (a set that fills). The first `workers` strips wait for each other: matched at once, each on
    a thread of its own, or the test fails after 60 s, never passing or failing by how the
    threads happened to be scheduled."""
    threads, started = set(), itertools.count()
    together = threading.Barrier(workers, timeout=60)

    def recorded(task):
        threads.add(threading.current_thread().name)
        if next(started) < workers:
            together.wait()
        return strip_method(task)

    monkeypatch.setitem(matching.METHODS, method, recorded)
    return threads


@pytest.mark.parametrize("method", ["tgv_zncc", "window_zncc"])
def test_two_workers_give_exactly_what_one_gives(method, monkeypatch):
    left, right, ramp = _pair()
    strip_method = matching.METHODS[method]
    results = {}
    for workers in (1, 2):
        threads = _record_threads(monkeypatch, method, strip_method, workers)
        results[workers] = matching.match_disparity(
            left,
            right,
            max_disparity_px=12,
            method=method,
            strip_pixels=STRIP_PIXELS,
            strip_matcher=functools.partial(matching.match_strips, workers=workers),
        )
        assert len(threads) == workers
    one, two = results[1], results[2]
    for field in ("disparity_px", "confidence", "sigma_px"):
        assert np.array_equal(getattr(one, field), getattr(two, field), equal_nan=True), field
    inner = (slice(None), slice(40, -40))
    assert np.isfinite(one.disparity_px[inner]).mean() > 0.95
    assert np.nanmedian(np.abs(one.disparity_px[inner] - ramp[inner])) < 0.1


def test_by_default_a_strip_is_matched_per_two_cpus_the_process_may_use(monkeypatch):
    left, right, _ = _pair()
    method = "window_zncc"
    threads = _record_threads(monkeypatch, method, matching.METHODS[method], 2)
    monkeypatch.setattr(matching.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    matching.match_disparity(left, right, max_disparity_px=12, method="window_zncc", strip_pixels=STRIP_PIXELS)
    assert len(threads) == 2


def test_strips_are_matched_by_at_least_one_worker():
    left, right, _ = _pair()
    with pytest.raises(ValueError, match="workers"):
        matching.match_disparity(
            left, right, max_disparity_px=12, strip_matcher=functools.partial(matching.match_strips, workers=0)
        )
