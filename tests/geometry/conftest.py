"""Shared fixtures of the geometry tests."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.synthetic.pairs import SyntheticPair, synthetic_pair


@pytest.fixture(scope="session")
def pair200() -> SyntheticPair:
    return synthetic_pair(200, sigma_px=1.0, outlier_frac=0.0, seed=3)


def skewed_K(f: float, cx: float, cy: float, aspect: float = 1.02, skew: float = 0.7) -> np.ndarray:
    return np.array([[f, skew, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="session")
def make_skewed_K():
    return skewed_K
