"""The BEV polish's exact Jacobian: it equals finite differences, and the polish finds what it
found with them, in a fraction of the residual evaluations (issue 45: bev spent minutes in a dense
finite-difference Jacobian)."""

from __future__ import annotations

import numpy as np
import pytest

from omnigen.detector.bev import homography as bev
from omnigen.detector.bev.synthetic import synthetic_frame


@pytest.mark.parametrize("handedness", [1.0, -1.0])
@pytest.mark.parametrize("with_prior", [False, True])
def test_the_jacobian_is_the_residuals_derivative(handedness, with_prior):
    rng = np.random.default_rng(3)
    n = 5
    pts = rng.normal(0, 0.5, (n, 4, 2))
    theta = np.concatenate([[0.05, -0.1, 0.2, 0.3], rng.normal(0, 0.5, 5 * n)])
    prior = np.full(n, 2.0)

    def residuals(t):
        g, inst = t[:4], t[4:].reshape(n, 5)
        res = [(bev._unwarp(g, bev._rectangles(inst, handedness)) - pts).ravel()]
        if with_prior:
            res.append(0.01 * (inst[:, 3] - inst[:, 4] - np.log(prior)))
        return np.concatenate(res)

    step = 1e-6
    numeric = np.stack([(residuals(theta + e) - residuals(theta - e)) / (2 * step)
                        for e in np.eye(len(theta)) * step], axis=1)
    exact = bev._reprojection_jacobian(theta[:4], theta[4:].reshape(n, 5), handedness, with_prior)
    assert exact.shape == numeric.shape
    np.testing.assert_allclose(exact, numeric, atol=1e-6 * np.abs(numeric).max())


@pytest.mark.parametrize("n", [3, 12, 45])  # dense steps, and sparse ones above SPARSE_FROM
def test_the_polish_finds_what_finite_differences_found(n):
    rng = np.random.default_rng(n)
    f = synthetic_frame(rng, n=n)
    seen = f.pixels + rng.normal(0, 2.0, f.pixels.shape)
    exact = bev.rectify(seen, f.classes)
    numeric = bev.rectify(seen, f.classes, jacobian="2-point")
    np.testing.assert_allclose(exact.homography, numeric.homography, atol=1e-6)


def test_an_unknown_jacobian_is_refused():
    f = synthetic_frame(np.random.default_rng(0), n=3)
    with pytest.raises(ValueError, match="jacobian"):
        bev.rectify(f.pixels, f.classes, jacobian="3-point")
