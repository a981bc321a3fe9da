"""Short cycles of a view graph (triangles and 4-cycles), found sparsely, and the rotation around each.

Pure functions on arrays: ``edges`` (M, 2) with ``i < j``, ``R_rel`` (M, 3, 3) with
``R_ij = R_j R_iᵀ`` (docs/CONVENTIONS.md). Nothing here forms an (N, N) matrix, so a
graph of thousands of cameras costs what its cycles cost:

- triangles ``i < j < k`` from the wedges ``i – j – k`` whose closing edge ``(i, k)``
  exists: ``Σ_j indeg(j)·outdeg(j)`` candidates, each looked up in the sorted edge keys;
- 4-cycles from pairs of wedges ``u – v – w`` with the same ends ``u < w``: each pair of
  centres ``v₁ ≠ v₂`` closes ``u – v₁ – w – v₂ – u``. A 4-cycle has two diagonals; it is
  kept from the one that holds its smallest camera, so each is listed once (with or
  without a chord). ``Σ_v deg(v)²/2`` wedges.

A cycle is walked ``x₀ → x₁ → … → x₀``; an edge ``(a, b)`` walked from ``b`` to ``a``
contributes ``R_abᵀ``. Exact rotations compose to the identity around every cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core import so3

__all__ = ["Cycles", "EdgeIndex", "find_triangles", "find_cycles", "cycle_angles", "cycle_variance", "edge_cycles",
           "expand_rows"]


@dataclass
class Cycles:
    """Short cycles of a graph.

    Attributes:
        edges: (C, 4) edge indices along the walk (triangles padded with -1 in the last column).
        forward: (C, 4) bool: the edge is walked from its ``i`` to its ``j`` (else backwards).
        length: (C,) 3 or 4.
    """

    edges: np.ndarray
    forward: np.ndarray
    length: np.ndarray

    def __len__(self) -> int:
        return int(len(self.length))

    def select(self, keep: np.ndarray) -> "Cycles":
        return Cycles(self.edges[keep], self.forward[keep], self.length[keep])


class EdgeIndex:
    """Edge index of camera pairs, by binary search on the sorted keys ``i·N + j`` (i < j).

    Args:
        edges: (M, 2) with i < j.
        n: number of cameras.
        active: (M,) bool edges to index (default all).
    """

    def __init__(self, edges: np.ndarray, n: int, active: np.ndarray | None = None) -> None:
        edges = np.asarray(edges, np.int64).reshape(-1, 2)
        idx = np.arange(len(edges)) if active is None else np.flatnonzero(active)
        keys = edges[idx, 0] * n + edges[idx, 1]
        order = np.argsort(keys, kind="stable")
        self.n, self.keys, self.ids = int(n), keys[order], idx[order]

    def lookup(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(K,) edge index of each pair ``{a, b}`` (either order), -1 where there is none."""
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        q = np.minimum(a, b) * self.n + np.maximum(a, b)
        pos = np.searchsorted(self.keys, q)
        pos_c = np.minimum(pos, max(len(self.keys) - 1, 0))
        found = (pos < len(self.keys)) & (self.keys[pos_c] == q) if len(self.keys) else np.zeros(q.shape, bool)
        return np.where(found, self.ids[pos_c] if len(self.keys) else -1, -1)


def _csr(src: np.ndarray, dst: np.ndarray, eid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Adjacency lists sorted by (src, dst): row pointers (n+1,), neighbours and edge ids."""
    order = np.lexsort((dst, src))
    ptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n))])
    return ptr, dst[order], eid[order]


def expand_rows(ptr: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each entry of ``rows``, every position of its CSR row (``ptr`` (n+1,) row pointers): (owner index
    into ``rows``, position)."""
    counts = ptr[rows + 1] - ptr[rows]
    owner = np.repeat(np.arange(len(rows)), counts)
    start = np.repeat(ptr[rows] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return owner, start + np.arange(int(counts.sum()))


def find_triangles(edges: np.ndarray, n: int, active: np.ndarray | None = None) -> Cycles:
    """Every triangle ``i < j < k`` of the active edges, walked ``i → j → k → i`` (edges ij, jk, ik).

    Args:
        edges: (M, 2) with i < j; n: number of cameras; active: (M,) bool (default all).
    Returns:
        :class:`Cycles` of length 3 (edge indices into the full ``edges``).
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    act = np.flatnonzero(np.ones(len(edges), bool) if active is None else np.asarray(active, bool))
    i, j = edges[act, 0], edges[act, 1]
    ptr, nbr, eid = _csr(i, j, act, n)  # the cameras above each camera
    owner, pos = expand_rows(ptr, j)  # wedge i – j – k with k > j
    e_ij, e_jk, k = act[owner], eid[pos], nbr[pos]
    e_ik = EdgeIndex(edges, n, None if active is None else active).lookup(i[owner], k)
    ok = e_ik >= 0
    E = np.stack([e_ij[ok], e_jk[ok], e_ik[ok], np.full(int(ok.sum()), -1)], 1)
    F = np.tile([True, True, False, True], (len(E), 1))
    return Cycles(E.reshape(-1, 4), F.reshape(-1, 4), np.full(len(E), 3))


def _cap(size: np.ndarray, budget: int) -> int:
    """The largest number c of centres per diagonal with ``Σ C(min(s, c), 2) ≤ budget`` (at least 2)."""
    lo, hi = 2, max(int(size.max()), 2)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        m = np.minimum(size, mid)
        lo, hi = (mid, hi) if int(np.sum(m * (m - 1) // 2)) <= budget else (lo, mid - 1)
    return lo


def find_cycles(edges: np.ndarray, n: int, active: np.ndarray | None = None, max_len: int = 4,
                max_four_cycles: int = 2_000_000) -> Cycles:
    """Triangles and, with ``max_len`` ≥ 4, 4-cycles of the active edges, each once (module docstring).

    The number of 4-cycles grows with the cube of the degree (a ring of 3000 cameras each paired with
    its 40 nearest has 14 million); beyond ``max_four_cycles`` each diagonal keeps its first few
    centres (the same number for every diagonal), so the count stays within the budget.

    Args:
        edges: (M, 2) with i < j; n: number of cameras; active: (M,) bool (default all).
        max_len: 3 (triangles only) or 4.
        max_four_cycles: the budget of 4-cycles (module docstring).
    Returns:
        :class:`Cycles`: the triangles first, then the 4-cycles ``u → v₁ → w → v₂ → u``.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    tri = find_triangles(edges, n, active)
    if max_len < 4:
        return tri
    act = np.flatnonzero(np.ones(len(edges), bool) if active is None else np.asarray(active, bool))
    a, b = edges[act, 0], edges[act, 1]
    ptr, nbr, eid = _csr(np.r_[a, b], np.r_[b, a], np.r_[act, act], n)  # every neighbour, sorted
    # wedges u – v – w, u < w: each neighbour of v paired with the later ones in v's sorted list
    centre = np.repeat(np.arange(n), np.diff(ptr))
    later = ptr[centre + 1] - np.arange(len(nbr)) - 1
    owner = np.repeat(np.arange(len(nbr)), later)
    second = owner + 1 + (np.arange(len(owner)) - np.repeat(np.cumsum(later) - later, later))
    v, u, w, e_vu, e_vw = centre[owner], nbr[owner], nbr[second], eid[owner], eid[second]
    # pairs of wedges with the same ends (u, w)
    key = u * n + w
    order = np.argsort(key, kind="stable")
    key, v, u, w, e_vu, e_vw = key[order], v[order], u[order], w[order], e_vu[order], e_vw[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    size = np.diff(np.r_[starts, len(key)])
    if len(size) and int(np.sum(size * (size - 1) // 2)) > max_four_cycles:
        first = np.arange(len(key)) - np.repeat(starts, size) < _cap(size, max_four_cycles)
        key, v, u, w, e_vu, e_vw = key[first], v[first], u[first], w[first], e_vu[first], e_vw[first]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        size = np.diff(np.r_[starts, len(key)])
    grp_end = np.repeat(starts + size, size)
    later = grp_end - np.arange(len(key)) - 1
    p = np.repeat(np.arange(len(key)), later)
    q = p + 1 + (np.arange(len(p)) - np.repeat(np.cumsum(later) - later, later))
    keep = (u[p] < v[p]) & (u[p] < v[q])  # the diagonal (u, w) holds the smallest camera
    p, q = p[keep], q[keep]
    # walk u → v₁ → w → v₂ → u
    E4 = np.stack([e_vu[p], e_vw[p], e_vw[q], e_vu[q]], 1)
    F4 = np.stack([u[p] < v[p], v[p] < w[p], w[p] < v[q], v[q] < u[p]], 1)
    return Cycles(np.concatenate([tri.edges, E4]), np.concatenate([tri.forward, F4]),
                  np.concatenate([tri.length, np.full(len(E4), 4)]))


def cycle_angles(R_rel: np.ndarray, cyc: Cycles) -> np.ndarray:
    """(C,) angle (deg) of the rotation composed around each cycle (0 for exact rotations)."""
    C = len(cyc)
    if C == 0:
        return np.zeros(0)
    P = np.broadcast_to(np.eye(3), (C, 3, 3)).copy()
    for s in range(cyc.edges.shape[1]):  # 4 steps, each vectorized over the cycles
        e = cyc.edges[:, s]
        has = e >= 0
        Rs = R_rel[np.maximum(e, 0)]
        Rs = np.where(cyc.forward[:, s, None, None], Rs, np.swapaxes(Rs, 1, 2))
        P[has] = Rs[has] @ P[has]
    return np.degrees(so3.angle(P))


def cycle_variance(var: np.ndarray, cyc: Cycles) -> np.ndarray:
    """(C,) sum of the per-edge variances ``var`` (M,) around each cycle."""
    return np.where(cyc.edges >= 0, var[np.maximum(cyc.edges, 0)], 0.0).sum(1)


def edge_cycles(cyc: Cycles, n_edges: int) -> tuple[np.ndarray, np.ndarray]:
    """The cycles through each edge: row pointers (M+1,) and cycle indices (CSR)."""
    flat = cyc.edges.ravel()
    owner = np.repeat(np.arange(len(cyc)), cyc.edges.shape[1])
    ok = flat >= 0
    flat, owner = flat[ok], owner[ok]
    order = np.argsort(flat, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n_edges))])
    return ptr, owner[order]
