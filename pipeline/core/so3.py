"""Batched SO(3) maps: exp, log, hat, vee, projection, angles, means, quaternions.

Every function takes arrays with arbitrary leading batch dimensions, ``(..., 3)``
for rotation vectors and ``(..., 3, 3)`` for matrices, and contains no Python loop
over elements. The log map is accurate near 0 and near π.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hat",
    "vee",
    "exp",
    "log",
    "angle",
    "angle_between",
    "relative",
    "chordal_distance",
    "project_to_so3",
    "quat_from_matrix",
    "matrix_from_quat",
    "quat_multiply",
    "log_quat",
    "chordal_mean",
    "karcher_mean",
    "random_rotations",
    "is_rotation",
]


def _as_float(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype.kind not in "fiu":
        raise TypeError(f"dtype={x.dtype} is not supported. Try 'float64'.")
    return x.astype(np.float64, copy=False)


def _check_matrices(R: np.ndarray, name: str = "R") -> np.ndarray:
    R = _as_float(R)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"{name}.shape={R.shape} but expected (..., 3, 3)")
    return R


def _check_vectors(w: np.ndarray, name: str = "w") -> np.ndarray:
    w = _as_float(w)
    if w.shape[-1:] != (3,):
        raise ValueError(f"{name}.shape={w.shape} but expected (..., 3)")
    return w


def relative(R: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``R_j R_iᵀ`` (M, 3, 3) of the blocks ``R`` (N, 3, 3) on the edges (M, 2) ``(i, j)``."""
    R = _check_matrices(R)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return R[edges[:, 1]] @ np.swapaxes(R[edges[:, 0]], -1, -2)


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``[w]×``.

    Args:
        w: (..., 3) vectors.

    Returns:
        (..., 3, 3) matrices with ``hat(w) @ v == cross(w, v)``.
    """
    w = _check_vectors(w)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1] = -w[..., 2]
    W[..., 0, 2] = w[..., 1]
    W[..., 1, 0] = w[..., 2]
    W[..., 1, 2] = -w[..., 0]
    W[..., 2, 0] = -w[..., 1]
    W[..., 2, 1] = w[..., 0]
    return W


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`, taken from the antisymmetric part of ``W``.

    Args:
        W: (..., 3, 3) matrices.

    Returns:
        (..., 3) vectors.
    """
    W = _check_matrices(W, "W")
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


_EXP_CHUNK = 16384  # rows per block: keeps the temporaries in cache


def _exp_block(w: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` (K, 9) with row-major ``exp([w]×)`` for ``w`` (K, 3)."""
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    t2 = x * x + y * y + z * z
    theta = np.sqrt(t2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    # a = sin(θ)/θ and b = (1 − cos θ)/θ² = 2 sin²(θ/2)/θ²: neither cancels. Below
    # 1e-4 rad their Taylor series (error < θ⁶/5040) replace the 0/0.
    a = np.sin(safe)
    a /= safe
    h = np.sin(0.5 * safe)
    h /= safe
    b = 2.0 * h * h
    if small.any():
        ts = t2[small]
        a[small] = 1.0 - ts / 6.0 * (1.0 - ts / 20.0)
        b[small] = 0.5 - ts / 24.0 * (1.0 - ts / 30.0)
    c = 1.0 - b * t2  # cos θ = 1 − 2 sin²(θ/2), accurate for every θ
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    out[:, 0] = bx * x + c
    out[:, 4] = by * y + c
    out[:, 8] = bz * z + c
    bxy, bxz, byz = bx * y, bx * z, by * z
    np.subtract(bxy, az, out=out[:, 1])
    np.add(bxy, az, out=out[:, 3])
    np.add(bxz, ay, out=out[:, 2])
    np.subtract(bxz, ay, out=out[:, 6])
    np.subtract(byz, ax, out=out[:, 5])
    np.add(byz, ax, out=out[:, 7])


def exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula ``exp([w]×)`` (paper 1, eq. 1).

    Computed as ``cos θ·I + (sin θ/θ)·[w]× + ((1 − cos θ)/θ²)·w wᵀ``, entry by
    entry and in cache-sized blocks (a loop over blocks of 16k rotations, not
    over rotations): batched 3×3 products and large temporaries are what make
    the naive numpy version slow (``benchmarks/so3.py``).

    Args:
        w: (..., 3) rotation vectors in radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    w = _check_vectors(w)
    flat = w.reshape(-1, 3)
    out = np.empty((flat.shape[0], 9))
    for s in range(0, flat.shape[0], _EXP_CHUNK):
        _exp_block(flat[s : s + _EXP_CHUNK], out[s : s + _EXP_CHUNK])
    return out.reshape(w.shape[:-1] + (3, 3))


def _angle_and_sin_axis(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = vee(R)  # sin(θ)·axis
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    s = np.linalg.norm(v, axis=-1)
    theta = np.arctan2(s, c)
    return theta, v, c


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``w`` with ``exp([w]×) = R`` and ``|w| <= π`` (paper 1, eq. 2).

    The angle comes from ``atan2(|sin θ|, cos θ)``, which is accurate for every θ.
    Below π/2 the axis comes from the antisymmetric part; above, from the
    symmetric part ``(R + Rᵀ)/2 − cos θ·I = (1 − cos θ)·a aᵀ``, with its sign
    taken from the antisymmetric part, so the map stays accurate near π.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors.
    """
    R = _check_matrices(R)
    theta, v, c = _angle_and_sin_axis(R)
    # Small and moderate angles: w = θ / sin θ · v.
    scale = 1.0 / np.sinc(theta / np.pi)
    w = scale[..., None] * v
    big = c < 0.0
    if np.any(big):
        Rb, vb, cb, tb = R[big], v[big], c[big], theta[big]
        S = 0.5 * (Rb + np.swapaxes(Rb, -1, -2))
        aat = (S - cb[:, None, None] * np.eye(3)) / (1.0 - cb)[:, None, None]
        k = np.argmax(np.diagonal(aat, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(aat, k[:, None, None], axis=-1)[..., 0]
        axis = col / np.sqrt(np.take_along_axis(col, k[:, None], axis=-1))
        sign = np.where(np.einsum("ni,ni->n", axis, vb) < 0.0, -1.0, 1.0)
        w[big] = (sign * tb)[:, None] * axis
    return w


def angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle of rotations, in radians, accurate for tiny angles.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (...,) angles in [0, π].
    """
    theta, _, _ = _angle_and_sin_axis(_check_matrices(R))
    return theta


def angle_between(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Geodesic distance ``|log(R1 R2ᵀ)|`` in radians (paper 1, eq. 4).

    Args:
        R1: (..., 3, 3) rotations.
        R2: (..., 3, 3) rotations, broadcastable against ``R1``.

    Returns:
        (...,) angles in radians.
    """
    R1 = _check_matrices(R1, "R1")
    R2 = _check_matrices(R2, "R2")
    return angle(R1 @ np.swapaxes(R2, -1, -2))


def chordal_distance(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Chordal distance ``‖R1 − R2‖_F``.

    Args:
        R1: (..., 3, 3) rotations.
        R2: (..., 3, 3) rotations.

    Returns:
        (...,) distances, in [0, 2√2].
    """
    R1 = _check_matrices(R1, "R1")
    R2 = _check_matrices(R2, "R2")
    return np.sqrt(np.sum((R1 - R2) ** 2, axis=(-2, -1)))


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation in Frobenius norm: SVD with the determinant fixed.

    Args:
        M: (..., 3, 3) matrices.

    Returns:
        (..., 3, 3) rotations ``U diag(1, 1, det(U Vᵀ)) Vᵀ``.
    """
    M = _check_matrices(M, "M")
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Whether each matrix is a rotation: ``‖RᵀR − I‖_max <= tol`` and ``det R > 0``.

    Args:
        R: (..., 3, 3) matrices.
        tol: tolerance on the entries of ``RᵀR − I``.

    Returns:
        (...,) booleans; false for any matrix with a NaN or inf.
    """
    R = _check_matrices(R)
    finite = np.all(np.isfinite(R), axis=(-2, -1))
    Rf = np.where(finite[..., None, None], R, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries overflow: not a rotation, no warning
        orth = np.max(np.abs(np.swapaxes(Rf, -1, -2) @ Rf - np.eye(3)), axis=(-2, -1)) <= tol
        return finite & orth & (np.linalg.det(Rf) > 0)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(w, x, y, z)``, scalar first, with ``w >= 0``.

    Uses the numerically best of the four Shepperd branches per element.

    Args:
        R: (..., 3, 3) rotations.

    Returns:
        (..., 4) quaternions (Hamilton convention, as COLMAP and Eigen).
    """
    R = _check_matrices(R)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack(
        [
            np.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 branches, 4)
    k = np.argmax(np.stack([tr, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions ``(w, x, y, z)``; normalizes the input.

    Args:
        q: (..., 4) quaternions, scalar first.

    Returns:
        (..., 3, 3) rotations.
    """
    q = _as_float(q)
    if q.shape[-1:] != (4,):
        raise ValueError(f"q.shape={q.shape} but expected (..., 4)")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(q)):
        raise ValueError("quaternions must be finite and non-zero")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def quat_multiply(p: np.ndarray, q: np.ndarray, axis: int = -1) -> np.ndarray:
    """Hamilton products ``p ⊗ q`` of quaternions ``(w, x, y, z)``: the quaternion of ``R(p) R(q)``.

    ``axis`` holds the 4 components (default last: (..., 4)). With ``axis=0`` on (4, M) arrays each component
    is a contiguous row, four times faster on 20,000 quaternions than (M, 4) (the averaging kernel's layout).
    """
    P = np.moveaxis(np.asarray(p, dtype=np.float64), axis, 0)
    Q = np.moveaxis(np.asarray(q, dtype=np.float64), axis, 0)
    pw, px, py, pz = P
    qw, qx, qy, qz = Q
    out = np.empty(np.broadcast_shapes(P.shape, Q.shape))
    out[0] = pw * qw - px * qx - py * qy - pz * qz
    out[1] = pw * qx + px * qw + py * qz - pz * qy
    out[2] = pw * qy - px * qz + py * qw + pz * qx
    out[3] = pw * qz + px * qy - py * qx + pz * qw
    return np.moveaxis(out, 0, axis)


def log_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of unit quaternions ``(w, x, y, z)`` (..., 4), ``|w| <= π``, the same as
    :func:`log` of their matrices.

    ``θ = 2 atan2(|v|, |w|)`` is accurate for every angle, and so is the axis ``v/|v|`` (no cancellation near
    π, unlike a matrix's antisymmetric part); below ``|v|`` = 1e-8 the factor ``2 atan2(|v|, |w|)/|v|`` is
    ``2/|w|`` to rounding (its relative error is ``|v|²/3``).
    """
    q = np.asarray(q, dtype=np.float64)
    w, v = q[..., 0], q[..., 1:]
    n = np.sqrt(np.einsum("...i,...i->...", v, v))
    aw = np.abs(w)
    tiny = n < 1e-8
    scale = np.where(tiny, 2.0 / np.where(tiny, aw, 1.0), 2.0 * np.arctan2(n, aw) / np.where(tiny, 1.0, n))
    return (np.where(w < 0, -scale, scale))[..., None] * v


def chordal_mean(R: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal (Frobenius) mean: the projection of the weighted sum onto SO(3).

    Args:
        R: (K, 3, 3) rotations.
        weights: (K,) non-negative weights, or None for equal weights.

    Returns:
        (3, 3) rotation.
    """
    R = _check_matrices(R)
    w = np.ones(R.shape[0]) if weights is None else np.asarray(weights, float)
    return project_to_so3(np.einsum("k,kab->ab", w, R))


def karcher_mean(
    R: np.ndarray,
    weights: np.ndarray | None = None,
    tol: float = 1e-12,
    max_iterations: int = 100,
) -> np.ndarray:
    """Geodesic (Karcher) mean ``argmin_S Σ w_k d(R_k, S)²``.

    Starts from the chordal mean and takes Riemannian gradient steps
    ``S ← exp(mean_k log(R_k Sᵀ)) S`` until the step is below ``tol`` radians.

    Args:
        R: (K, 3, 3) rotations.
        weights: (K,) non-negative weights, or None.
        tol: stopping tolerance on the step, in radians.
        max_iterations: iteration cap.

    Returns:
        (3, 3) rotation.
    """
    R = _check_matrices(R)
    w = np.ones(R.shape[0]) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    S = chordal_mean(R, w)
    for _ in range(max_iterations):
        step = np.einsum("k,ki->i", w, log(R @ S.T))
        S = exp(step) @ S
        if np.linalg.norm(step) < tol:
            break
    return S


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """Haar-uniform random rotations (from normalized Gaussian quaternions).

    Args:
        n: how many.
        rng: a numpy random generator.

    Returns:
        (n, 3, 3) rotations.
    """
    q = rng.standard_normal((n, 4))
    return matrix_from_quat(q)
