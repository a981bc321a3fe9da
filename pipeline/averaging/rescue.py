"""Cameras that the robust averaging left in a wrong basin, found and moved to the rotation their own edges agree on.

On a dense graph of internet photos (1DSfM's kind) a few cameras are matched mostly wrong: 80–95% of their
edges are outliers. Their few right edges still agree with one another (each edge ``(k, j)`` proposes
``R_k = R̃_kjᵀ R_j`` from the neighbour's current rotation, and the right ones propose the same rotation to the
noise), while the outliers' proposals are scattered. An ℓ1 start is a median, which such a camera's outliers
outvote, and the IRLS that follows keeps the camera where the start put it: on the synthetic dense graphs of
:func:`pipeline.synthetic.protocols.dense_graph` 0–8 cameras ended 55–160° off, each with 6–20 edges that
proposed its true rotation to within 0.3–1.8° and *one or two* edges that agreed with where it was.

:func:`rescue_cameras` finds those cameras (fewer than ``max_share`` of their edges within the agreement radius
``tol`` of their current rotation), takes the densest cluster of their edges' proposals (the proposal with the
most others within ``tol``), and moves a camera there when that cluster has at least ``min_support`` proposals
and more than twice the current support. By chance alone such a cluster is rare: a Haar-random rotation falls
within 5° of a given one with probability ≈ (θ − sin θ)/π ≈ 3.5e-5, so among 200 random proposals about 0.7
pairs agree and a cluster of 4 has odds of about 1e-5 (at a 10° radius, 6e-3); the likelihood test below
refuses a move that does not fit. A correlated wrong cluster (repeated structure: a block of edges wrong by one
rotation) is not moved to unless it outnumbers the camera's current support twice over, and a camera whose
proposals form two rival clusters (the second more than half the first: a symmetric building's two sides, seen on
a synthetic one where 7 mirrored pairs outvoted 6 right ones) is left where it is, its evidence saying how few
pairs it keeps. The
caller re-polishes from the moved rotations and keeps the result only if the polish's mixture likelihood (its own
objective, in which an outlier edge costs the same wherever its camera is) is higher
(:func:`pipeline.averaging.irls.irls`).

Pure functions on arrays; the loop is over the (few) suspect cameras, each step vectorized over its edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.averaging.evidence import MINORITY_SHARE
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["Rescue", "rescue_cameras"]


@dataclass
class Rescue:
    """The moved cameras (indices), their support before and after (edges within ``tol``), and the rotations."""

    R: np.ndarray
    cameras: np.ndarray
    support_before: np.ndarray
    support_after: np.ndarray
    degree: np.ndarray


def rescue_cameras(vg: ViewGraph, R: np.ndarray, theta: np.ndarray, tol: float, min_support: int = 4,
                   max_share: float = MINORITY_SHARE, max_proposals: int = 400) -> Rescue:
    """Move each camera that its edges do not support to the rotation most of its edges' proposals agree on.

    Args:
        vg: the view graph; R: (N, 3, 3) its current rotations; theta: (M,) residual angles at R (radians).
        tol: agreement radius (radians).
        min_support: fewest agreeing proposals to move a camera.
        max_share: a camera is a suspect when fewer than this share of its edges are within ``tol`` (the share
            below which its evidence calls the support a "minority").
        max_proposals: a suspect with more edges uses this many (its edges with the smallest residuals at the
            neighbours' side are not known, so an even stride; the cluster test is O(d²)).

    Returns:
        :class:`Rescue` (``R`` a copy with the moved cameras replaced).
    """
    E = vg.edges
    n = vg.n_cameras
    good = theta < tol
    degree = np.bincount(E.ravel(), minlength=n)
    support = np.bincount(E[good].ravel(), minlength=n)
    suspects = np.flatnonzero((degree >= min_support) & (support < max_share * degree))
    R_new = R.copy()
    moved, before, after = [], [], []
    if suspects.size == 0:
        return Rescue(R_new, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), degree)
    order = np.argsort(np.r_[E[:, 0], E[:, 1]], kind="stable")  # incident edges of every camera, grouped
    ends = np.r_[E[:, 0], E[:, 1]][order]
    start = np.searchsorted(ends, np.arange(n + 1))
    cos_half = np.cos(0.5 * tol)  # |⟨q_a, q_b⟩| ≥ cos(tol/2) ⇔ angle(R_a, R_b) ≤ tol
    for k in suspects:  # few cameras; each vectorized over its edges
        at = order[start[k]:start[k + 1]] % vg.n_edges
        if at.size > max_proposals:
            at = at[np.linspace(0, at.size - 1, max_proposals).astype(np.int64)]
        i, j = E[at, 0], E[at, 1]
        # the proposals for R_k: from (k, j), R̃ R_k = R_j gives R_k = R̃ᵀ R_j; from (i, k), R_k = R̃ R_i
        prop = np.where((i == k)[:, None, None], np.swapaxes(vg.R_rel[at], 1, 2) @ R[j], vg.R_rel[at] @ R[i])
        q = so3.quat_from_matrix(prop)
        agree = np.abs(q @ q.T) >= cos_half
        count = agree.sum(1)
        best = int(np.argmax(count))
        rest = ~agree[best]  # the proposals outside the best cluster: is there a rival cluster?
        second = int(agree[np.ix_(rest, rest)].sum(1).max()) if rest.any() else 0
        if count[best] < min_support or count[best] <= 2 * support[k] or count[best] < 2 * second:
            continue  # too few, not better than where it is, or ambiguous (a symmetric structure's rival)
        R_new[k] = so3.chordal_mean(prop[agree[best]])
        moved.append(k)
        before.append(support[k])
        after.append(count[best])
    return Rescue(R_new, np.asarray(moved, np.int64), np.asarray(before, np.int64), np.asarray(after, np.int64),
                  degree)
