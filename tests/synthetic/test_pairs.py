"""Synthetic two-view pairs: argument checks and shapes."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.synthetic.pairs import synthetic_pair, synthetic_pairs


def test_synthetic_pair_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="outlier_frac=1.5"):
        synthetic_pair(10, outlier_frac=1.5)


def test_synthetic_pairs_one_pair_per_edge() -> None:
    names, edges, pairs = synthetic_pairs(4, n_points=20)
    assert names == ["im0.png", "im1.png", "im2.png", "im3.png"]
    np.testing.assert_array_equal(edges, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    assert [p.x_i.shape for p in pairs] == [(20, 2)] * 6
    with pytest.raises(ValueError, match="n_cams=1"):
        synthetic_pairs(1)
