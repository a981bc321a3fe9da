"""Initial rotations from a spanning tree of the view graph (paper 1, §4.5).

A spanning tree fixes every rotation from N − 1 relative rotations: the root gets
the identity and each child ``j`` of a parent ``i`` gets ``R_j = R_ij R_i`` (edge
``(i, j)``) or ``R_j = R_jiᵀ R_i`` (edge ``(j, i)``). The propagation loops over
tree levels (O(depth)) and is vectorized within a level.

Trees:

* ``"mst"``: maximum spanning tree by inlier count when the graph has counts,
  else by a given per-edge weight, else uniform (any spanning tree).
* ``"random"``: the minimum spanning tree of i.i.d. uniform edge weights (paper 1
  initializes from "a random spanning tree"; this is not uniform over trees).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from pipeline.core.config import Config, option
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["StartConfig", "spanning_tree", "rotations_from_tree", "initial_rotations"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class StartConfig(Config):
    """The spanning-tree start, shared by the options of every iterative method."""

    init: Literal["mst", "random"] = option("mst", "spanning tree of the start: mst (by inliers) or random")
    seed: int | None = option(0, "seed of the random spanning tree (and of Weiszfeld's colouring)")


def _edge_lookup(vg: ViewGraph, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Index of the edge joining cameras ``a[k]`` and ``b[k]`` (either order)."""
    N = vg.n_cameras
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys = vg.edges[:, 0] * N + vg.edges[:, 1]
    order = np.argsort(keys)
    pos = np.searchsorted(keys[order], lo * N + hi)
    return order[pos]


def spanning_tree(
    vg: ViewGraph,
    kind: str = "mst",
    weights: np.ndarray | None = None,
    seed: int | None = 0,
) -> np.ndarray:
    """Edge indices of a spanning tree.

    Args:
        vg: a connected view graph.
        kind: ``"mst"`` (maximum spanning tree by ``weights``, else by
            ``vg.inliers``, else uniform) or ``"random"``.
        weights: (M,) larger is better, for ``"mst"``.
        seed: random seed for ``"random"``.

    Returns:
        (N − 1,) indices into ``vg.edges``.

    Raises:
        ViewGraphError: the graph is not connected, or ``weights`` has a bad shape.
    """
    N, M = vg.n_cameras, vg.n_edges
    if N == 0:
        raise ViewGraphError("the view graph is empty: no cameras to initialize")
    if not vg.is_connected():
        raise ViewGraphError(
            f"the view graph has {int(vg.components().max()) + 1} connected components; "
            "restrict it with vg.largest_component() before building a spanning tree"
        )
    if N == 1:
        return np.zeros(0, dtype=np.int64)
    if kind == "random":
        rng = np.random.default_rng(seed)
        cost = rng.random(M) + 1.0
    elif kind == "mst":
        w = weights if weights is not None else vg.inliers
        if w is None:
            w = np.ones(M)
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (M,) or not np.all(np.isfinite(w)):
            raise ViewGraphError(f"spanning-tree weights must be finite with shape ({M},), got {w.shape}")
        # Maximum spanning tree = minimum tree of (max − w + 1) > 0; scipy ignores zeros.
        cost = w.max() - w + 1.0
    else:
        raise ValueError(f"unknown spanning tree kind {kind!r}; use 'mst' or 'random'")
    i, j = vg.edges.T
    G = sp.coo_matrix((cost, (i, j)), shape=(N, N)).tocsr()
    T = minimum_spanning_tree(G).tocoo()
    tree = _edge_lookup(vg, T.row.astype(np.int64), T.col.astype(np.int64))
    if tree.size != N - 1:
        raise ViewGraphError(f"spanning tree has {tree.size} edges, expected {N - 1}; is the graph connected?")
    return np.sort(tree)


def rotations_from_tree(vg: ViewGraph, tree: np.ndarray, root: int = 0) -> np.ndarray:
    """Chain relative rotations along a spanning tree.

    Args:
        vg: the view graph.
        tree: (N − 1,) edge indices of a spanning tree.
        root: camera given the identity.

    Returns:
        (N, 3, 3) cam_from_world rotations consistent with every tree edge.
    """
    N = vg.n_cameras
    tree = np.asarray(tree, dtype=np.int64)
    e = vg.edges[tree]
    T = sp.coo_matrix((np.ones(tree.size), (e[:, 0], e[:, 1])), shape=(N, N)).tocsr()
    order, pred = breadth_first_order(T, root, directed=False, return_predecessors=True)
    if order.size != N:
        raise ViewGraphError(f"the tree reaches {order.size} of {N} cameras; it does not span the graph")
    child = order[1:]
    parent = pred[child]
    eidx = _edge_lookup(vg, parent, child)
    forward = vg.edges[eidx, 0] == parent  # edge (parent, child): R_c = R_pc R_p
    Rrel = vg.R_rel[eidx]
    # Pointer doubling: R[c] holds R_c R_{jump[c]}ᵀ; each round composes a camera's step with its target's
    # and doubles the hops it spans, so a chain of depth D takes ⌈log₂ D⌉ rounds of N products (a sequence
    # of thousands of frames is a tree thousands deep: one round per level would be O(N·D)).
    R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    R[child] = np.where(forward[:, None, None], Rrel, np.swapaxes(Rrel, 1, 2))
    jump = np.full(N, root, dtype=np.int64)
    jump[child] = parent
    while np.any(jump != root):
        R = R @ R[jump]
        jump = jump[jump]
    return R


def initial_rotations(
    vg: ViewGraph,
    init: str | np.ndarray = "mst",
    weights: np.ndarray | None = None,
    seed: int | None = 0,
) -> np.ndarray:
    """Initial rotations for an iterative solver.

    Args:
        vg: a connected view graph.
        init: ``"mst"``, ``"random"`` (spanning trees, see the module docstring) or
            an (N, 3, 3) array of user rotations.
        weights: (M,) edge weights for ``"mst"`` (default: inlier counts).
        seed: seed for ``"random"``.

    Returns:
        (N, 3, 3) rotations.
    """
    if isinstance(init, str):
        tree = spanning_tree(vg, init, weights=weights, seed=seed)
        return rotations_from_tree(vg, tree)
    R0 = np.asarray(init, dtype=np.float64)
    if R0.shape != (vg.n_cameras, 3, 3):
        raise ValueError(f"init rotations have shape {R0.shape} but expected ({vg.n_cameras}, 3, 3)")
    if not np.all(np.isfinite(R0)):
        raise ValueError("init rotations contain NaN or inf")
    from pipeline.core import so3

    if not np.all(so3.is_rotation(R0, 1e-5)):
        raise ValueError("init rotations are not all rotation matrices; project them with so3.project_to_so3")
    return R0.copy()
