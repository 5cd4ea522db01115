"""Batched Cholesky with the jitter ladder: per-matrix NumPy as the reference."""

import warnings

import numpy as np
import pytest

from mdcore import _linalg as linalg
from mdcore._exceptions import NumericalWarning
from mdcore._linalg import JitterLog, cholesky, solve_lower_inplace


def batch(rng, n=7, size=40, bad=(3, 17, 18, 39)):
    A = rng.normal(size=(size, n, n))
    K = A @ np.swapaxes(A, 1, 2) + n * np.eye(n)
    for i in bad:                                    # indefinite: never factorises
        K[i] = np.diag(np.r_[np.ones(n - 1), -5.0])
    return K


def test_failures_are_found_and_the_rest_equal_numpy(rng):
    K = batch(rng)
    log = JitterLog()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumericalWarning)
        L, ok = cholesky(K, log)
    assert ok.tolist() == [i not in (3, 17, 18, 39) for i in range(40)]
    for i in range(40):
        if ok[i]:
            np.testing.assert_array_equal(L[i], np.linalg.cholesky(K[i]))   # bit for bit
        else:
            assert np.all(np.isnan(L[i]))
    assert log.failed == 4 and log.jittered == 0
    with pytest.warns(NumericalWarning, match="4 covariance matrix\\(es\\) stayed non-positive"):
        log.warn("test")


def test_jitter_ladder_rescues_a_singular_matrix(rng):
    x = np.linspace(0, 1, 6)
    K = np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / 100.0)[None]     # rank-deficient
    log = JitterLog()
    L, ok = cholesky(K, log)
    assert ok[0] and log.jittered == 1 and log.max_jitter in linalg.JITTER_LADDER
    jittered = K[0] + log.max_jitter * np.mean(np.diag(K[0])) * np.eye(6)
    np.testing.assert_allclose(L[0] @ L[0].T, jittered, rtol=1e-10, atol=1e-12)


def test_solve_lower_inplace_against_numpy(rng):
    L = np.tril(rng.normal(size=(5, 6, 6))) + 4 * np.eye(6)
    B = rng.normal(size=(5, 6, 3))
    want = np.linalg.solve(L, B)
    np.testing.assert_allclose(solve_lower_inplace(L, B.copy()), want, rtol=1e-10)


def test_chunks_cover_the_batch_once():
    pieces = linalg.chunks((7, 5), bytes_per_item=linalg.CHUNK_BYTES / 4)
    covered = np.concatenate([np.arange(35)[s] for s, _, _ in pieces])
    np.testing.assert_array_equal(covered, np.arange(35))
    assert all(n <= 4 for _, _, n in pieces)
