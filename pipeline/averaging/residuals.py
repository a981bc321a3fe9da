"""The residuals ``r_ij = log(R_jᵀ R_ij R_i)`` of a view graph's edges (paper 1, eq. 7), by matrices or quaternions.

:func:`graph_residuals` is the one the iterative methods call tens of times per run: it works on quaternions held
as four contiguous rows (4, M), keeps each product's four components in preallocated rows and writes every
elementwise operation into them (``out=``), so that an evaluation on 20,000 edges allocates no (M,) temporaries
beyond its result (an IRLS run on a dense graph spent a third of its time here). Its arithmetic is that of
:func:`pipeline.core.so3.quat_multiply` and :func:`pipeline.core.so3.log_quat`, operation for operation: the same
residuals to the last bit. Re-exported by :mod:`~pipeline.averaging.kernel`. Pure functions on arrays, but for the
memo of a view graph's converted measurements, which :func:`held_measurements` lets one solve validate once.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["edge_residuals", "graph_residuals", "held_measurements"]

_FINGERPRINT_WEIGHTS: dict[int, np.ndarray] = {}
#: The view graphs held by :func:`held_measurements`, by ``id``: [holds, memo validated in this hold]. Kept here,
#: not on the graph, so that a copy of a held graph (a different object) is validated as any other graph is.
_HELD: dict[int, list] = {}


def edge_residuals(edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Residual rotation vectors ``r_ij = log(R_jᵀ R_ij R_i)`` (paper 1, eq. 7).

    Args:
        edges: (M, 2) camera indices ``(i, j)``.
        R_rel: (M, 3, 3) measured ``R_ij ≈ R_j R_iᵀ``.
        R: (N, 3, 3) current cam_from_world rotations.

    Returns:
        (M, 3) residuals in radians.
    """
    Ri = R[edges[:, 0]]
    Rj = R[edges[:, 1]]
    return so3.log(np.swapaxes(Rj, 1, 2) @ R_rel @ Ri)


def _fingerprint(a: np.ndarray) -> tuple[int, tuple[int, ...], float]:
    """Where ``a``'s data is, its shape, and its dot product with fixed random weights: any change of the values
    (in place too) changes the last but for a set of measure zero; 0.1 ms for 20,000 rotations."""
    flat = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
    w = _FINGERPRINT_WEIGHTS.get(flat.size)
    if w is None:
        w = _FINGERPRINT_WEIGHTS[flat.size] = np.random.default_rng(flat.size).standard_normal(flat.size)
        if len(_FINGERPRINT_WEIGHTS) > 8:  # a few graph sizes at a time
            del _FINGERPRINT_WEIGHTS[next(iter(_FINGERPRINT_WEIGHTS))]
    # einsum's own loop: no temporary (3× faster than sum(flat * w) on 680k rotations), and not BLAS, whose threads
    # wake slowly
    return a.__array_interface__["data"][0], a.shape, float(np.einsum("i,i->", flat, w))


@contextlib.contextmanager
def held_measurements(vg: ViewGraph) -> Iterator[ViewGraph]:
    """Within it, ``vg``'s measurements (``R_rel``, ``edges``) are taken as unchanged: the memo of
    :func:`graph_residuals` is validated (fingerprinted, converted anew if they changed) at the first evaluation
    only, not at each (an IRLS run on 20,000 edges evaluates its residuals about 50 times; the fingerprints cost
    10 ms of its 0.3 s). One solve holds its graph (:func:`pipeline.averaging.solve.average`); holds nest, and
    the next evaluation after the outermost ends validates again."""
    hold = _HELD.setdefault(id(vg), [0, False])
    hold[0] += 1
    try:
        yield vg
    finally:
        hold[0] -= 1
        if hold[0] == 0:
            del _HELD[id(vg)]


def _graph_memo(vg: ViewGraph) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``vg``'s relative quaternions (4, M) and edge ends (M,), (M,), contiguous, kept on the view graph while its
    measurements are unchanged (an IRLS run evaluates its residuals tens of times; they are converted once)."""
    memo = vg.__dict__.get("_residual_memo")
    hold = _HELD.get(id(vg))
    if hold is not None and hold[1] and memo is not None:  # validated earlier in this hold
        return memo[1]
    fp = (_fingerprint(vg.R_rel), _fingerprint(vg.edges))
    if memo is None or memo[0] != fp:  # NaN never equals itself: a graph with NaN is converted anew
        e = np.asarray(vg.edges, dtype=np.int64)
        memo = (fp, (np.ascontiguousarray(so3.quat_from_matrix(vg.R_rel).T), np.ascontiguousarray(e[:, 0]),
                     np.ascontiguousarray(e[:, 1])))
        vg.__dict__["_residual_memo"] = memo
    if hold is not None:
        hold[1] = True
    return memo[1]


#: The Hamilton product ``p ⊗ q`` row by row: component k is ``Σ sign · p[a] · q[b]`` over these terms, in this
#: order (that of :func:`pipeline.core.so3.quat_multiply`, whose rounding it therefore reproduces).
_PRODUCT = (((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
            ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
            ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
            ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)))
#: Where ``p`` is a conjugate ``(w, −v)``, the term signs of its vector part flip: ``x − (−a)b`` is ``x + ab``
#: exactly in floating point, so the product needs no negated copy of ``p``.
_CONJ_PRODUCT = tuple(tuple((a, b, s if a == 0 else -s) for a, b, s in row) for row in _PRODUCT)


def _product_rows(p: np.ndarray, q: np.ndarray, terms: tuple, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """``p ⊗ q`` of (4, M) rows into ``out`` (4, M), each operation written in place (``tmp``: (M,) scratch)."""
    for k, row in enumerate(terms):
        (a, b, _), rest = row[0], row[1:]
        np.multiply(p[a], q[b], out=out[k])
        for a, b, sign in rest:
            np.multiply(p[a], q[b], out=tmp)
            (np.add if sign > 0 else np.subtract)(out[k], tmp, out=out[k])
    return out


def _log_rows(t: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """:func:`pipeline.core.so3.log_quat` of unit quaternions in rows (4, M), as (M, 3); ``tmp`` (M,) scratch.

    The (M, 3) result is Fortran-ordered, as that of ``log_quat`` on the transposed rows is: the sums over its
    rows downstream (``einsum``) then round as they did."""
    w, x, y, z = t
    n = np.multiply(x, x)
    n += np.multiply(y, y, out=tmp)
    n += np.multiply(z, z, out=tmp)
    np.sqrt(n, out=n)
    aw = np.abs(w, out=tmp)
    scale = np.arctan2(n, aw)
    scale *= 2.0
    tiny = n < 1e-8
    if tiny.any():  # 2 atan2(|v|, |w|)/|v| is 2/|w| to rounding there (and |v| may be 0)
        n[tiny] = 1.0
        scale /= n
        scale[tiny] = 2.0 / aw[tiny]
    else:
        scale /= n
    np.negative(scale, out=scale, where=w < 0)
    r = np.empty((3, t.shape[1]))  # returned as its (M, 3) transpose, Fortran-ordered as log_quat's product is
    for k in range(3):
        np.multiply(scale, t[k + 1], out=r[k])
    return r.T


def graph_residuals(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    """:func:`edge_residuals` of ``vg``'s edges at the rotations ``R`` (N, 3, 3), by quaternions: ``r_ij`` is the
    log of ``q_jᶜ ⊗ q_ij ⊗ q_i`` (:func:`pipeline.core.so3.log_quat`). The same residuals to 2e-15 rad, accurate
    near π as :func:`pipeline.core.so3.log` is, and 5× faster on 20,000 edges (no (M, 3, 3) gathers or products),
    and without temporaries twice as fast again as the same arithmetic by :func:`pipeline.core.so3.quat_multiply`."""
    q_rel, e0, e1 = _graph_memo(vg)
    q = np.ascontiguousarray(so3.quat_from_matrix(R).T)
    tmp = np.empty(q_rel.shape[1])
    qj = q.take(e1, axis=1)
    p = _product_rows(qj, q_rel, _CONJ_PRODUCT, np.empty_like(q_rel), tmp)
    return _log_rows(_product_rows(p, q.take(e0, axis=1), _PRODUCT, qj, tmp), tmp)  # qj's rows are free again
