"""pipeline.geometry.ba_stage: the per-pair "same K" test done for all pairs at once (same_intrinsics) and the tasks
built from it (pair_tasks) equal the per-pair ``np.allclose`` loop they replace (the definition here)."""

from __future__ import annotations

import types

import numpy as np
import pytest

from pipeline.geometry.ba_focal import focal_columns
from pipeline.geometry.ba_stage import pair_tasks, same_intrinsics


def _reference_tasks(data, K, t_in, mode, known):
    tasks = []
    for k in range(data.vg.n_edges):
        xi, xj = data.correspondences(k)
        i, j = data.vg.edges[k]
        A = focal_columns(mode if np.allclose(K[i], K[j]) or mode != "shared" else "per_camera", bool(known[i]),
                          bool(known[j]))
        tasks.append((np.asarray(xi, np.float64), np.asarray(xj, np.float64), K[i], K[j], data.vg.R_rel[k], t_in[k],
                      A))
    return tasks


def _intrinsics(rng, n):
    """Cameras sharing a K, some a hair apart (inside allclose's tolerance), some apart, one with a NaN."""
    K = np.tile(np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]]), (n, 1, 1))
    kind = rng.integers(0, 4, n)
    K[kind == 1, 0, 0] *= 1 + 1e-9
    K[kind == 2, 0, 0] *= 1 + 1e-3
    K[kind == 2, 1, 2] += 5.0
    if n > 3:
        K[3, 0, 2] = np.nan
    return K


def _data(rng, n, edges):
    M = len(edges)
    off = np.r_[0, np.cumsum(rng.integers(0, 20, M))]
    x1, x2 = rng.random((off[-1], 2)).astype(np.float32), rng.random((off[-1], 2))
    vg = types.SimpleNamespace(edges=edges, n_edges=M, R_rel=rng.standard_normal((M, 3, 3)))
    return types.SimpleNamespace(vg=vg, correspondences=lambda k: (x1[off[k]:off[k + 1]], x2[off[k]:off[k + 1]]))


def _same_tasks(a, b):
    assert len(a) == len(b)
    for p, q in zip(a, b):
        assert len(p) == len(q) == 7
        for x, y in zip(p, q):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y, equal_nan=True)


@pytest.mark.parametrize("seed", range(6))
def test_random_pairs(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    E = np.stack(np.triu_indices(n, 1), 1)
    E = E[rng.random(len(E)) < rng.uniform(0.1, 1.0)]
    K = _intrinsics(rng, n)
    want = np.array([np.allclose(K[i], K[j]) for i, j in E], bool)
    assert np.array_equal(same_intrinsics(K, E), want)
    data, t_in, known = _data(rng, n, E), rng.standard_normal((len(E), 3)), rng.random(n) < 0.4
    for mode in ("none", "shared", "per_camera"):
        _same_tasks(pair_tasks(data, K, t_in, mode, known), _reference_tasks(data, K, t_in, mode, known))


def test_edge_cases():
    rng = np.random.default_rng(9)
    K = _intrinsics(rng, 5)
    K[1] = K[0] * (1 + 1e-9)  # within tolerance of camera 0
    K[2] = K[0]
    K[2, 0, 0] += 1.0  # not
    empty = np.zeros((0, 2), np.int64)
    assert same_intrinsics(K, empty).shape == (0,)
    E = np.array([[0, 1], [0, 2], [0, 1], [3, 4], [3, 3]])  # one pair twice; NaN K; a camera with itself
    assert same_intrinsics(K, E).tolist() == [np.allclose(K[i], K[j]) for i, j in E] == [True, False, True, False,
                                                                                         False]
    assert same_intrinsics(K, E[:1]).tolist() == [True]
    for edges in (empty, E[:1], E):
        data, t_in, known = _data(rng, 5, edges), rng.standard_normal((len(edges), 3)), np.array([1, 0, 0, 1, 0], bool)
        _same_tasks(pair_tasks(data, K, t_in, "shared", known), _reference_tasks(data, K, t_in, "shared", known))
