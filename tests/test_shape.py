"""Tests of medseg.shape: invariants, cliques, densities, potentials, persistence."""

from __future__ import annotations

import copy
import json
from math import comb

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from scipy.stats import gaussian_kde, multivariate_normal

from medseg.errors import (
    CohortError,
    ModelFileError,
    NotFittedError,
    ResourceLimitError,
)
from medseg.shape import (
    TripletPrior,
    clique_table_size,
    relative_distances,
    relative_distances_and_size,
    select_cliques,
    triangle_angles,
)

N_LANDMARKS = 9


def _training_shapes(n_shapes=25, seed=0, pose=True):
    """Noisy copies of one configuration, each in a random pose and size."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(N_LANDMARKS, 3)) * 10.0
    shapes = base + rng.normal(scale=0.4, size=(n_shapes, N_LANDMARKS, 3))
    if pose:
        rots = Rotation.random(n_shapes, random_state=seed).as_matrix()
        scales = rng.uniform(0.5, 2.0, size=n_shapes)
        shifts = rng.normal(scale=50.0, size=(n_shapes, 3))
        shapes = np.einsum("sij,snj->sni", rots, shapes) * scales[:, None, None]
        shapes = shapes + shifts[:, None, :]
    return base, shapes


@pytest.fixture(scope="module")
def fitted():
    base, shapes = _training_shapes()
    priors = {
        inv: TripletPrior(invariant=inv, random_state=0).fit(shapes)
        for inv in ("distance", "distance_size", "angle")
    }
    return base, shapes, priors


# ---------------------------------------------------------------- invariants


def test_relative_distances_of_a_345_triangle():
    tri = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    # d_ij = 3, d_jk = 4, d_ki = 5, perimeter 12
    np.testing.assert_allclose(relative_distances(tri), [3 / 12, 4 / 12])


def test_triangle_angles_of_a_right_triangle():
    tri = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    np.testing.assert_allclose(triangle_angles(tri), [np.pi / 2, np.arctan2(4.0, 3.0)])


def test_invariants_broadcast_over_leading_axes():
    pts = np.random.default_rng(1).normal(size=(4, 5, 3, 3))
    out = relative_distances(pts)
    assert out.shape == (4, 5, 2)
    np.testing.assert_allclose(out[2, 3], relative_distances(pts[2, 3]))
    assert triangle_angles(pts).shape == (4, 5, 2)


def test_invariants_are_finite_for_degenerate_triangles():
    coincident = np.zeros((3, 3))
    two_same = np.array([[0.0, 0, 0], [0, 0, 0], [1, 0, 0]])
    collinear = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    for tri in (coincident, two_same, collinear):
        assert np.all(np.isfinite(relative_distances(tri)))
        assert np.all(np.isfinite(triangle_angles(tri)))
    np.testing.assert_allclose(relative_distances(coincident), [0.0, 0.0])
    # collinear: d_ij = 1, d_jk = 1, d_ki = 2
    np.testing.assert_allclose(relative_distances(collinear), [0.25, 0.25])


def test_invariant_rejects_bad_shape():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        relative_distances(np.zeros((3, 2)))


# ---------------------------------------------------------------- cliques


def test_select_cliques_all_counts_every_triplet():
    pts = np.random.default_rng(0).normal(size=(7, 3))
    cl = select_cliques(pts, method="all")
    assert cl.shape == (comb(7, 3), 3)
    assert np.all(cl[:, 0] < cl[:, 1]) and np.all(cl[:, 1] < cl[:, 2])


@pytest.mark.parametrize("method", ["delaunay", "knn"])
def test_select_cliques_sparse_sets_are_sorted_unique_and_cover_all_landmarks(method):
    pts = np.random.default_rng(3).normal(size=(20, 3))
    cl = select_cliques(pts, method=method, k=4)
    assert cl.dtype == np.int64 and cl.ndim == 2 and cl.shape[1] == 3
    assert np.all(np.diff(cl, axis=1) > 0)
    assert len(np.unique(cl, axis=0)) == len(cl)
    assert np.array_equal(np.unique(cl, axis=0), cl)  # lexicographic order
    assert set(np.unique(cl)) == set(range(20))
    assert len(cl) < comb(20, 3)
    if method == "knn":
        assert len(cl) <= 20 * comb(4, 2)


def test_delaunay_cliques_of_a_tetrahedron_are_its_four_faces():
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    cl = select_cliques(tet, method="delaunay")
    np.testing.assert_array_equal(cl, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])


def test_delaunay_cliques_survive_a_flat_configuration():
    pts = np.c_[np.random.default_rng(0).normal(size=(10, 2)), np.zeros(10)]
    cl = select_cliques(pts, method="delaunay", random_state=0)
    assert len(cl) > 0 and np.all(np.diff(cl, axis=1) > 0)


def test_max_cliques_subsamples_reproducibly():
    pts = np.random.default_rng(0).normal(size=(10, 3))
    a = select_cliques(pts, method="all", max_cliques=15, random_state=4)
    b = select_cliques(pts, method="all", max_cliques=15, random_state=4)
    assert a.shape == (15, 3)
    np.testing.assert_array_equal(a, b)


def test_clique_table_size_reports_count_and_memory():
    cl = np.zeros((100, 3), dtype=int)
    size = clique_table_size(cl, 20)
    assert size.n_cliques == 100 and size.nbytes == 100 * 20**3 * 4
    assert "100 cliques" in str(size)


def test_select_cliques_rejects_bad_input():
    with pytest.raises(ValueError, match="mean_shape"):
        select_cliques(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="method"):
        select_cliques(np.random.default_rng(0).normal(size=(5, 3)), method="mesh")


# ---------------------------------------------------------------- invariance (hypothesis)

_similarity = st.tuples(
    st.integers(0, 2**31 - 1),  # rotation seed
    st.floats(0.05, 20.0),  # uniform scale
    st.tuples(*[st.floats(-500.0, 500.0)] * 3),  # translation, mm
    st.booleans(),  # reflect
)


def _apply(points, params):
    seed, scale, shift, reflect = params
    rot = Rotation.random(random_state=seed).as_matrix()
    if reflect:
        rot = rot @ np.diag([1.0, 1.0, -1.0])
    return scale * points @ rot.T + np.asarray(shift)


@settings(max_examples=40, deadline=None)
@given(params=_similarity, which=st.integers(0, 24), noise_seed=st.integers(0, 1000))
def test_clique_potentials_are_similarity_invariant(fitted, params, which, noise_seed):
    _, shapes, priors = fitted
    # any configuration, not only a plausible one
    x = shapes[which] + np.random.default_rng(noise_seed).normal(scale=3.0, size=shapes[0].shape)
    rigid = (params[0], 1.0, params[2], params[3])
    for name, prior in priors.items():
        h0 = prior.clique_potentials(x)
        # relative distances with size are invariant to rigid motions, not to scaling
        h1 = prior.clique_potentials(_apply(x, rigid if name == "distance_size" else params))
        np.testing.assert_allclose(h1, h0, rtol=1e-6, atol=1e-6 * np.abs(h0).max())


def test_relative_distances_and_size_of_a_345_triangle():
    tri = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    np.testing.assert_allclose(relative_distances_and_size(tri), [0.25, 4 / 12, np.log(12.0)])
    # scaling moves only the size coordinate, by log(scale)
    np.testing.assert_allclose(
        relative_distances_and_size(2.5 * tri), [0.25, 4 / 12, np.log(12.0) + np.log(2.5)]
    )


def test_size_aware_prior_rejects_a_shape_of_the_wrong_size():
    # the paper's similarity invariant accepts a shape three times too large; with the
    # size term, the prior knows the training population's size range (0.9-1.1 here)
    rng = np.random.default_rng(3)
    base = rng.normal(size=(N_LANDMARKS, 3)) * 10.0
    rots = Rotation.random(30, random_state=3).as_matrix()
    noisy = base + rng.normal(scale=0.4, size=(30, N_LANDMARKS, 3))
    shapes = np.einsum("sij,snj->sni", rots, noisy) * rng.uniform(0.9, 1.1, (30, 1, 1))
    paper = TripletPrior(invariant="distance", random_state=0).fit(shapes)
    sized = TripletPrior(invariant="distance_size", random_state=0).fit(shapes)
    np.testing.assert_allclose(paper.score_samples(3.0 * base), paper.score_samples(base))
    assert sized.score_samples(base) > sized.score_samples(3.0 * base) + 100.0
    assert sized.score_samples(base) > sized.score_samples(base + rng.normal(size=base.shape) * 4)


def test_potentials_would_detect_a_non_similarity_change(fitted):
    # the invariance test above is not vacuous: an anisotropic stretch changes the potentials
    _, shapes, priors = fitted
    x = shapes[0]
    stretched = x * np.array([1.0, 1.0, 1.3])
    assert not np.allclose(
        priors["distance"].clique_potentials(x), priors["distance"].clique_potentials(stretched)
    )


# ---------------------------------------------------------------- densities and potentials


def test_prior_prefers_training_like_shapes_to_distorted_ones(fitted):
    base, shapes, priors = fitted
    rng = np.random.default_rng(5)
    distorted = base + rng.normal(scale=4.0, size=base.shape)
    for prior in priors.values():
        assert prior.score_samples(base) > prior.score_samples(distorted)


@pytest.mark.parametrize(
    ("invariant", "function"),
    [("distance", relative_distances), ("distance_size", relative_distances_and_size)],
)
def test_gaussian_density_matches_scipy(invariant, function):
    _, shapes = _training_shapes(n_shapes=30, seed=2)
    prior = TripletPrior(
        cliques="all", density="gaussian", invariant=invariant, reg_covar=1e-9
    ).fit(shapes)
    samples = function(shapes[:, prior.cliques_[4]])
    dim = samples.shape[1]
    ref = multivariate_normal(samples.mean(0), np.cov(samples.T, bias=True) + 1e-9 * np.eye(dim))
    x = shapes[3] + 0.5
    np.testing.assert_allclose(
        prior.clique_potentials(x)[4], -ref.logpdf(function(x[prior.cliques_[4]])), rtol=1e-6
    )


def test_parzen_density_matches_scipy_gaussian_kde():
    _, shapes = _training_shapes(n_shapes=30, seed=2)
    prior = TripletPrior(cliques="all", density="parzen", reg_covar=1e-12).fit(shapes)
    c = prior.cliques_[7]
    kde = gaussian_kde(relative_distances(shapes[:, c]).T, bw_method="scott")
    x = shapes[1] * 1.1
    np.testing.assert_allclose(
        prior.clique_potentials(x)[7], -kde.logpdf(relative_distances(x[c])[:, None])[0],
        rtol=1e-6,
    )  # fmt: skip


def test_gmm_bic_picks_two_components_for_a_bimodal_clique():
    rng = np.random.default_rng(0)
    base = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [5, 5, 8]])
    shapes = np.repeat(base[None], 60, axis=0) + rng.normal(scale=0.05, size=(60, 4, 3))
    shapes[::2, 2] = [0.0, 20.0, 0.0]  # landmark 2 has two distinct positions
    shapes[::2, 2] += rng.normal(scale=0.05, size=(30, 3))
    prior = TripletPrior(cliques=np.array([[0, 1, 2]]), max_components=3, random_state=0)
    prior.fit(shapes)
    assert prior.n_components_[0] == 2
    one = TripletPrior(cliques=np.array([[0, 1, 2]]), density="gaussian").fit(shapes)
    # the mixture explains both modes better than one Gaussian
    assert prior.score_samples(shapes).mean() > one.score_samples(shapes).mean()


def test_identical_training_shapes_still_give_finite_potentials():
    base, _ = _training_shapes()
    shapes = np.repeat(base[None], 5, axis=0)
    for density in ("gmm", "gaussian", "parzen"):
        prior = TripletPrior(density=density, random_state=0).fit(shapes)
        far = np.random.default_rng(0).normal(size=base.shape) * 100
        assert np.all(np.isfinite(prior.clique_potentials(far)))
        assert np.all(np.isfinite(prior.clique_potentials(np.zeros_like(base))))


@pytest.mark.parametrize(
    ("density", "invariant"),
    [("gmm", "distance"), ("parzen", "distance"), ("gmm", "distance_size")],
)
def test_potential_tables_agree_with_clique_potentials(fitted, density, invariant):
    base, shapes, _ = fitted
    prior = TripletPrior(density=density, invariant=invariant, random_state=0).fit(shapes)
    rng = np.random.default_rng(1)
    n_cand = 6
    cand = base[:, None, :] + rng.normal(scale=2.0, size=(N_LANDMARKS, n_cand, 3))
    cand[:, 0] = 0.0  # coincident candidates for every landmark: degenerate triples
    tables = prior.potential_tables(cand)
    assert tables.shape == (len(prior.cliques_), n_cand, n_cand, n_cand)
    assert tables.dtype == np.float32
    assert np.all(np.isfinite(tables))
    for _ in range(5):
        labels = rng.integers(0, n_cand, size=N_LANDMARKS)
        x = cand[np.arange(N_LANDMARKS), labels]
        h = prior.clique_potentials(x)
        cl = prior.cliques_
        got = tables[np.arange(len(cl)), labels[cl[:, 0]], labels[cl[:, 1]], labels[cl[:, 2]]]
        np.testing.assert_allclose(got, h, rtol=1e-5, atol=1e-4)
    # chunking does not change the result
    np.testing.assert_array_equal(prior.potential_tables(cand, chunk_size=1), tables)
    np.testing.assert_array_equal(prior.potential_tables(cand, max_bytes=1), tables)


def test_potential_tables_refuse_oversized_tables(fitted):
    base, _, priors = fitted
    cand = np.repeat(base[:, None, :], 10, axis=1)
    with pytest.raises(ResourceLimitError, match="MiB"):
        priors["distance"].potential_tables(cand, max_table_bytes=1000)


def test_alpha_scales_potentials(fitted):
    _, shapes, priors = fitted
    p2 = copy.deepcopy(priors["distance"]).set_params(alpha=2.5)
    np.testing.assert_allclose(
        p2.clique_potentials(shapes[0]), 2.5 * priors["distance"].clique_potentials(shapes[0])
    )


def test_same_seed_gives_the_same_prior():
    _, shapes = _training_shapes(n_shapes=12, seed=4)
    a = TripletPrior(max_components=2, random_state=3).fit(shapes)
    b = TripletPrior(max_components=2, random_state=3).fit(shapes)
    np.testing.assert_array_equal(a.means_, b.means_)
    np.testing.assert_array_equal(a.cliques_, b.cliques_)


def test_mean_shape_is_similar_to_the_underlying_configuration(fitted):
    base, _, priors = fitted
    from medseg.geometry import similarity_fit

    mean = priors["distance"].mean_shape_
    tf = similarity_fit(base, mean)
    assert np.abs(tf(base) - mean).max() < 0.1 * tf.scale * np.ptp(base)


# ---------------------------------------------------------------- bad input


def test_too_few_training_shapes_is_a_cohort_error():
    _, shapes = _training_shapes(n_shapes=2)
    with pytest.raises(CohortError, match="at least 3 training shapes"):
        TripletPrior().fit(shapes)


def test_unfitted_prior_raises():
    with pytest.raises(NotFittedError, match="fit"):
        TripletPrior().clique_potentials(np.zeros((5, 3)))


@pytest.mark.parametrize(
    ("param", "value"),
    [("density", "kde"), ("alpha", -1.0), ("max_components", 0), ("cliques", "mesh")],
)
def test_bad_parameters_name_the_parameter(param, value):
    _, shapes = _training_shapes(n_shapes=5)
    with pytest.raises(ValueError, match=f"`{param}`"):
        TripletPrior(**{param: value}).fit(shapes)


def test_wrong_number_of_landmarks_is_rejected(fitted):
    _, _, priors = fitted
    with pytest.raises(ValueError, match=f"{N_LANDMARKS} landmarks"):
        priors["distance"].clique_potentials(np.zeros((N_LANDMARKS + 1, 3)))


# ---------------------------------------------------------------- persistence


@pytest.mark.parametrize("invariant", ["distance", "distance_size", "angle"])
def test_save_load_round_trip(fitted, tmp_path, invariant):
    base, shapes, priors = fitted
    prior = priors[invariant]
    path = prior.save(tmp_path / "prior.npz")
    loaded = TripletPrior.load(path)
    assert loaded.get_params() == {**prior.get_params(), "random_state": None}
    np.testing.assert_array_equal(loaded.cliques_, prior.cliques_)
    np.testing.assert_array_equal(
        loaded.clique_potentials(shapes[:3]), prior.clique_potentials(shapes[:3])
    )
    with np.load(path, allow_pickle=False) as npz:  # readable with pickle disabled
        header = json.loads(str(npz["header"]))
    assert header["format_version"] == TripletPrior.FORMAT_VERSION
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind


def test_load_rejects_corrupt_and_foreign_files(fitted, tmp_path):
    _, _, priors = fitted
    path = priors["distance"].save(tmp_path / "prior.npz")
    raw = path.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ModelFileError, match="truncated.npz"):
        TripletPrior.load(tmp_path / "truncated.npz")

    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays.pop("header")))
    header["format_version"] = 99
    np.savez(tmp_path / "future.npz", header=np.array(json.dumps(header)), **arrays)
    with pytest.raises(ModelFileError, match="version 99"):
        TripletPrior.load(tmp_path / "future.npz")

    header["format_version"] = TripletPrior.FORMAT_VERSION
    arrays["cliques"] = arrays["cliques"] + 100
    np.savez(tmp_path / "bad.npz", header=np.array(json.dumps(header)), **arrays)
    with pytest.raises(ModelFileError, match="corrupt"):
        TripletPrior.load(tmp_path / "bad.npz")
