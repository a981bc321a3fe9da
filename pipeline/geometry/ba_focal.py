"""The focal lengths as unknowns of the two-view BA, marginalized into ``H`` with the translation.

When a camera's intrinsics are not known (estimated from the view graph, or an
EXIF prior), the BA of a pair can refine its focal length(s) (``BAConfig.refine_focal``):

* **Parameters.** ``φ`` = log focal scale, ``K(φ) = diag(e^φ, e^φ, 1) K₀`` (fx, fy
  and the skew scale together; the principal point stays), so ``φ`` is unitless and
  ``dφ = df/f``. A (2, m) 0/1 matrix ``A`` says which camera each of the m columns
  scales: ``shared`` is ``[[1], [1]]`` (one focal for both), ``per_camera``
  ``[[1, 0], [0, 1]]``; a pair with one known camera has one column on the other.
* **Jacobian.** Image i: ``∂r_i/∂φ = K_i[:2, :2](a, b) = x̂_i − c_i``; image j:
  ``∂r_j/∂φ = x̂_j − c_j`` (``x̂`` the predicted pixel). The image-i rows, which had
  no camera dependence, now have one.
* **Elimination.** Each point's 4×3 Jacobian depends on K only through its value
  and keeps its one-dimensional left null space ``n_k``, so the point Schur term is
  ``Jc_kᵀ n_k n_kᵀ Jc_k`` with ``Jc_k`` the 4×(5+m) camera Jacobian: the reduced
  system is (5+m)×(5+m), and
  :func:`pipeline.geometry.ba_hessian.marginalize_translation` eliminates the
  translation and the focal(s) together, so ``H`` stays the rotation's marginal
  precision (NEES ≈ 3 on synthetic pairs with an unknown focal: tests and
  ``benchmarks/intrinsics.py``). σ²'s degrees of freedom lose m.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

__all__ = ["FOCAL_MODES", "focal_columns", "scale_K", "FocalUnknowns"]

FOCAL_MODES = ("none", "shared", "per_camera")
MAX_LOG_SCALE = 1.0  # a step beyond e^±1 of the start focal is refused (LM damps it)


def focal_columns(mode: Literal["none", "shared", "per_camera"], known_i: bool = False, known_j: bool = False
                  ) -> np.ndarray:
    """The (2, m) matrix ``A`` of a pair: which camera (rows i, j) each focal unknown scales.

    Known cameras get no column; ``shared`` with one camera known refines the other's alone.
    """
    if mode not in FOCAL_MODES:
        raise ValueError(f"refine_focal={mode!r} but expected one of {FOCAL_MODES}")
    free = [not known_i, not known_j]
    if mode == "none" or not any(free):
        return np.zeros((2, 0))
    if mode == "shared" and all(free):
        return np.ones((2, 1))
    return np.eye(2)[:, [k for k in range(2) if free[k]]]


def scale_K(K: np.ndarray, phi: float) -> np.ndarray:
    """``diag(e^φ, e^φ, 1) K``: focal lengths (and skew) scaled, principal point kept."""
    out = np.array(K, dtype=np.float64)
    out[:2, :2] *= math.exp(phi)
    return out


class FocalUnknowns:
    """The focal unknowns of one pair during the BA: their columns, start K's and current values.

    Args:
        A: (2, m) from :func:`focal_columns`.
        K_i, K_j: (3, 3) start intrinsics (φ = 0).
    """

    def __init__(self, A: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> None:
        self.A = np.asarray(A, dtype=np.float64).reshape(2, -1)
        self.m = self.A.shape[1]
        self.K0 = (np.asarray(K_i, np.float64), np.asarray(K_j, np.float64))
        self.phi = np.zeros(self.m)
        self.K_i, self.K_j = self.K0

    def Ks(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(K_i, K_j)`` at log scales ``phi`` (m,)."""
        s = self.A @ phi
        return scale_K(self.K0[0], float(s[0])), scale_K(self.K0[1], float(s[1]))

    def admissible(self, phi: np.ndarray) -> bool:
        return bool(np.all(np.abs(phi) <= MAX_LOG_SCALE))

    def accept(self, phi: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> None:
        self.phi, self.K_i, self.K_j = phi, K_i, K_j

    def jacobian(self, P: np.ndarray, K_i: np.ndarray, K_j: np.ndarray, aux: tuple) -> np.ndarray:
        """(4, m, n) derivatives of the residuals (image i x, y; image j x, y) with respect to φ.

        ``aux`` is :func:`pipeline.geometry.ba_model.project`'s third output at ``K_i``,
        ``K_j`` (its ``uv`` holds the predicted pixels of image j).
        """
        gi = K_i[:2, :2] @ P[:2]  # x̂_i − c_i
        gj = aux[2] - K_j[:2, 2, None]  # x̂_j − c_j
        return np.concatenate([gi[:, None, :] * self.A[0][None, :, None], gj[:, None, :] * self.A[1][None, :, None]])

    @staticmethod
    def reduced(nv: np.ndarray, Jf: np.ndarray) -> np.ndarray:
        """(m, n) rows of the reduced Jacobian: ``n_kᵀ Jf_k`` (all four residual rows)."""
        return (nv[:, None, :] * Jf).sum(axis=0)
