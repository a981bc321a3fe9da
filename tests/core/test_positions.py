"""pipeline.core.names.positions: one dictionary pass gives what ``names.index`` for each name gave (the
definition here), on random orders and edge cases; a name that is not there is the ``missing`` given, or raises."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.names import positions


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


def test_a_name_not_there_is_the_missing_value_given():
    """The lists of our stages that hold only some of the cameras (a method's solved component, a peer's registered
    images): −1 where a camera is not there."""
    assert positions(["a", "b", "c"], ["c", "x", "a", "y"], missing=-1).tolist() == [2, -1, 0, -1]
    assert positions(["a"], [], missing=-1).dtype == np.int64 and positions([], ["a"], missing=-1).tolist() == [-1]
