"""Memory estimates against the real allocations, the configurable limit, and the refusals.

The estimates are compared with the peak ``tracemalloc`` measures while the real function
runs (numpy, scipy.ndimage and scipy.fft allocate through the traced allocator), on small
generated inputs.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import SimpleITK as sitk

from medseg.datasets import make_phantom_cohort
from medseg.detection import FeatureSettings, compute_features, detection_bytes, feature_map_bytes
from medseg.errors import ResourceLimitError
from medseg.memory import (
    DEFAULT_FRACTION,
    ENV_VAR,
    check_memory,
    memory_limit_bytes,
    orientation_table_bytes,
    physical_memory_bytes,
    potential_table_bytes,
    solver_bytes,
    triplet_mrf_bytes,
)
from medseg.mrf import MRF, solve
from medseg.segmenter import ShapePriorSegmenter, segment_bytes
from medseg.shape import OrientationPrior, TripletPrior

# an estimate within this factor of the measured peak, either way
FACTOR = 1.3


def _peak(fn, *args, **kwargs):
    tracemalloc.start()
    try:
        out = fn(*args, **kwargs)
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _within(estimate: float, measured: float, factor: float = FACTOR) -> bool:
    return measured / factor <= estimate <= measured * factor


@pytest.fixture(autouse=True)
def _no_limit_from_the_environment(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


# ----------------------------------------------------------------------------- estimates


@pytest.mark.parametrize(
    ("shape", "spacing_zyx", "kinds"),
    [
        ((24, 32, 40), (2.0, 1.0, 1.0), None),  # the default features, anisotropic
        ((36, 20, 28), (1.0, 1.2, 0.8), ("shell",)),
        ((20, 30, 24), (1.0, 1.0, 1.0), ("hessian", "log")),
        ((20, 24, 30), (1.5, 1.0, 1.0), ("intensity", "gradient", "std")),
    ],
)
def test_feature_estimate_matches_the_measured_peak(shape, spacing_zyx, kinds):
    rng = np.random.default_rng(0)
    image = sitk.GetImageFromArray(rng.random(shape).astype(np.float32))
    image.SetSpacing(spacing_zyx[::-1])
    settings = FeatureSettings() if kinds is None else FeatureSettings(kinds=kinds)
    feats, measured = _peak(compute_features, image, settings)
    assert feats.shape == shape + (settings.n_features,)
    estimate = feature_map_bytes(shape, spacing=spacing_zyx, settings=settings)
    assert _within(estimate, measured), (estimate, measured)
    # the feature maps alone are far from the peak: the working set is what the estimate adds
    assert estimate > 1.3 * feats.nbytes


@pytest.fixture(scope="module")
def prior_and_candidates():
    rng = np.random.default_rng(3)
    base = rng.normal(size=(16, 3)) * 10
    shapes = base + rng.normal(scale=0.5, size=(12, 16, 3))
    prior = TripletPrior(cliques="knn", density="gaussian", random_state=0).fit(shapes)
    candidates = base[:, None] + rng.normal(scale=2.0, size=(16, 18, 3))
    return prior, candidates


def test_potential_table_estimate_matches_the_measured_peak(prior_and_candidates):
    prior, cand = prior_and_candidates
    n_cliques, n_lab = len(prior.cliques_), cand.shape[1]
    for chunk_bytes in (256 * 2**20, 4 * 2**20):
        tables, measured = _peak(prior.potential_tables, cand, max_bytes=chunk_bytes)
        estimate = potential_table_bytes(n_cliques, n_lab, chunk_bytes=chunk_bytes)
        assert _within(estimate, measured), (chunk_bytes, estimate, measured)
    assert tables.nbytes == 4 * n_cliques * n_lab**3


def test_orientation_table_estimate_matches_the_measured_peak(prior_and_candidates):
    prior, cand = prior_and_candidates
    rng = np.random.default_rng(1)
    shapes = cand[:, :12].transpose(1, 0, 2)  # any (S, N, 3) configurations will do
    orientation = OrientationPrior().fit(
        shapes, rng.normal(size=shapes.shape), cliques=prior.cliques_
    )
    directions = rng.normal(size=cand.shape)
    n_cliques, n_lab = len(prior.cliques_), cand.shape[1]
    for chunk_size in (4, 16):
        tables, measured = _peak(orientation.tables, cand, directions, chunk_size=chunk_size)
        estimate = orientation_table_bytes(n_cliques, n_lab, chunk_size=chunk_size)
        assert _within(estimate, measured), (chunk_size, estimate, measured)
    assert tables.nbytes == 4 * n_cliques * n_lab**3


@pytest.mark.parametrize("method", ["mplp", "srmp", "subgradient"])
def test_solver_estimate_matches_the_measured_peak(prior_and_candidates, method):
    prior, cand = prior_and_candidates
    n, n_lab = cand.shape[:2]
    tables = prior.potential_tables(cand)
    unaries = np.random.default_rng(0).random((n, n_lab))
    mrf = MRF.from_triplets(unaries, prior.cliques_, tables)
    result, measured = _peak(solve, mrf, method=method, max_iter=5)
    assert result.lower_bound <= result.energy + 1e-6
    estimate = solver_bytes(n, len(prior.cliques_), n_lab, method=method)
    assert _within(estimate, measured, factor=1.5), (estimate, measured)


# ----------------------------------------------------------------------------- the limit


def test_limit_comes_from_the_keyword_then_the_environment_then_the_machine(monkeypatch):
    total = physical_memory_bytes()
    assert total is not None and total > 2**28  # Linux: os.sysconf knows it
    assert memory_limit_bytes() == int(DEFAULT_FRACTION * total)
    monkeypatch.setenv(ENV_VAR, "0.25")
    assert memory_limit_bytes() == 2**28
    assert memory_limit_bytes(2) == 2 * 2**30  # the keyword wins
    for bad in ("lots", "-1", "0", "nan"):
        monkeypatch.setenv(ENV_VAR, bad)
        with pytest.raises(ResourceLimitError, match=f"{ENV_VAR}='{bad}'"):
            memory_limit_bytes()
    with pytest.raises(ResourceLimitError, match="memory_limit_gb"):
        memory_limit_bytes(-3)


def test_check_memory_message_gives_estimate_limit_source_and_hint(monkeypatch):
    check_memory(2**20, what="a thing", hint="use less", limit=2**21)  # fits: no error
    with pytest.raises(ResourceLimitError) as info:
        check_memory(3 * 2**30, what="a thing", hint="use fewer things", limit=2**30)
    msg = str(info.value)
    assert "a thing would need about 3.00 GiB" in msg
    assert "limit of 1.00 GiB (set by the caller)" in msg
    assert "To lower it: use fewer things." in msg and ENV_VAR in msg
    monkeypatch.setenv(ENV_VAR, "0.5")
    with pytest.raises(ResourceLimitError, match=rf"512.0 MiB \(from {ENV_VAR}=0.5\)"):
        check_memory(2**30, what="a thing", hint="less")


# ----------------------------------------------------------------------------- refusals


def test_potential_tables_refusal_names_a_candidate_count_that_fits(
    prior_and_candidates, monkeypatch
):
    prior, cand = prior_and_candidates
    n_cliques = len(prior.cliques_)
    limit = potential_table_bytes(n_cliques, 12)  # room for 12 candidates, not 18
    monkeypatch.setenv(ENV_VAR, repr(limit / 2**30))
    with pytest.raises(ResourceLimitError, match=ENV_VAR) as info:
        prior.potential_tables(cand)
    msg = str(info.value)
    suggested = int(msg.split("use at most ")[1].split(" candidates")[0])
    assert suggested == 12
    assert prior.potential_tables(cand[:, :suggested]).shape == (n_cliques,) + (12,) * 3
    # the other lever: a prior with the suggested number of cliques fits under the same limit
    fewer = int(msg.split("or at most ")[1].split(" cliques")[0])
    assert 1 <= fewer < n_cliques and f"now {n_cliques}" in msg
    sparse = TripletPrior(cliques="knn", density="gaussian", max_cliques=fewer, random_state=0)
    sparse.fit(np.stack([prior.mean_shape_] * 3) + np.random.default_rng(0).normal(size=(3, 16, 3)))
    assert sparse.potential_tables(cand).shape == (fewer,) + (18,) * 3
    # an explicit limit takes precedence over the environment
    assert prior.potential_tables(cand, max_table_bytes=2**30).shape[1] == 18


SMALL = dict(n_landmarks=10, size=40)


@pytest.fixture(scope="module")
def fitted():
    cohort = make_phantom_cohort(7, random_state=2, **SMALL)
    model = ShapePriorSegmenter(
        n_estimators=4, n_candidates=10, max_iter=50, augment_poses=0, random_state=0
    )  # memory at segmentation does not depend on the training copies
    return model.fit(cohort[:6]), cohort[6].load_image()


def test_segment_estimate_matches_the_measured_peak(fitted):
    model, image = fitted
    model.n_candidates = 24  # large enough for the MRF to set the peak, not the features
    try:
        seg, measured = _peak(model.segment, image)
    finally:
        model.n_candidates = 10
    n, n_lab = seg.candidates.positions.shape[:2]
    shape, spacing = image.GetSize()[::-1], image.GetSpacing()[::-1]
    estimate = max(
        detection_bytes(shape, spacing=spacing, settings=model.detector_.features, n_landmarks=n),
        triplet_mrf_bytes(
            n, len(model.prior_.cliques_), n_lab, method=model.mrf_method, orientation=True
        ),
    )
    assert _within(estimate, measured), (estimate, measured)
    # the one composed estimate (what medseg-segment --jobs sizes its workers by) is this one
    model.n_candidates = n_lab
    try:
        assert segment_bytes(model, image.GetSize(), image.GetSpacing()) == estimate
    finally:
        model.n_candidates = 10


def test_segment_refuses_before_the_work_and_says_what_to_lower(fitted, monkeypatch):
    model, image = fitted
    shape, spacing = image.GetSize()[::-1], image.GetSpacing()[::-1]
    n = model.detector_.n_landmarks_
    detect = detection_bytes(
        shape, spacing=spacing, settings=model.detector_.features, n_landmarks=n
    )
    # below the detector's need: refused before any feature is computed
    model.memory_limit_gb = 0.5 * detect / 2**30
    with pytest.raises(ResourceLimitError, match="landmark detection on a 40x40x40 image"):
        model.segment(image)
    # enough for detection, not for 40 candidates per landmark in the MRF
    model.memory_limit_gb = 1.1 * detect / 2**30
    model.n_candidates = 40
    try:
        with pytest.raises(ResourceLimitError, match="the shape-prior MRF") as info:
            model.segment(image)
        msg = str(info.value)
        fits = int(msg.split("n_candidates=")[1].split(" fits")[0])
        assert 1 <= fits < 40
        model.n_candidates = fits  # the advice works under the same limit
        seg = model.segment(image)
        assert seg.candidates.positions.shape[1] == fits
    finally:
        model.n_candidates, model.memory_limit_gb = 10, None
    # the environment variable reaches the segmenter too (what a medseg-segment user sets)
    monkeypatch.setenv(ENV_VAR, repr(0.5 * detect / 2**30))
    with pytest.raises(ResourceLimitError, match=f"from {ENV_VAR}"):
        model.segment(image)


def test_fit_refuses_before_training_the_detectors():
    cohort = make_phantom_cohort(5, random_state=4, n_landmarks=8, size=32)
    model = ShapePriorSegmenter(n_estimators=2, random_state=0, memory_limit_gb=0.001)
    with pytest.raises(ResourceLimitError, match="training feature maps of the largest image"):
        model.fit(cohort)
    assert not hasattr(model, "detector_")
    # features fit, but 200 candidates per landmark would not at segmentation time
    big = ShapePriorSegmenter(n_candidates=200, random_state=0, memory_limit_gb=0.1)
    with pytest.raises(ResourceLimitError, match="shape-prior MRF .* x 200\\^3"):
        big.fit(cohort)
    assert not hasattr(big, "detector_")
