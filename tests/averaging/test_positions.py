"""pipeline.averaging.stage.positions: one dictionary pass gives what ``names.index`` for each name gave (the
definition here), on random orders and edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.averaging.stage import positions


def _reference(names, subset):
    return np.array([names.index(n) for n in subset])


@pytest.mark.parametrize("seed", range(10))
def test_random_subsets(seed):
    rng = np.random.default_rng(seed)
    names = [f"img{k:04d}.jpg" for k in rng.permutation(int(rng.integers(1, 300)))]
    subset = [names[k] for k in rng.choice(len(names), int(rng.integers(1, len(names) + 1)), replace=bool(seed % 2))]
    got, want = positions(names, subset), _reference(names, subset)
    assert got.dtype == want.dtype == np.int64 and np.array_equal(got, want)


def test_edge_cases():
    assert positions(["a"], ["a"]).tolist() == _reference(["a"], ["a"]).tolist() == [0]
    assert positions(["a", "b", "c"], ["c", "c", "a"]).tolist() == _reference(["a", "b", "c"], ["c", "c", "a"]).tolist()
    assert positions([], []).shape == (0,) and positions(["a"], []).dtype == np.int64  # the old one gave float64 here
    with pytest.raises(ValueError, match="'x' is not in list"):
        positions(["a", "b"], ["x"])
