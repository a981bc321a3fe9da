"""ℓ1 rotation averaging by the Weiszfeld algorithm (Hartley, Aftab & Trumpf, CVPR 2011): a baseline.

Each camera in turn is moved to the geodesic ℓ1 median of the estimates its
neighbours give it, with every other camera held fixed (a distributed,
Gauss–Seidel averaging). For edge ``(i, j)`` with ``R_ij ≈ R_j R_iᵀ``, camera
``j`` is estimated by ``R_ij R_i`` and camera ``i`` by ``R_ijᵀ R_j``. The median
is found by Weiszfeld steps in the tangent space at the current estimate:

    v_k = log(S_k R_jᵀ),   R_j ← exp([Σ v_k/‖v_k‖ / Σ 1/‖v_k‖]×) R_j.

Vectorization: the cameras are split into independent sets (a graph colouring);
cameras of one set share no edge, so updating them together is exactly the
sequential sweep in that order. A given ``order`` makes every camera its own set.

Stopping rule (paper 1, §6): the relaxed criterion "the update of every vertex in
a sweep is below ``tol_rad``" (1e-3 rad), against IRLS's mean update.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp

from pipeline.averaging.init import StartConfig, initial_rotations
from pipeline.averaging.kernel import check_graph, graph_residuals
from pipeline.averaging.result import AveragingResult, method_config, start_of
from pipeline.core import so3
from pipeline.core.config import option
from pipeline.core.viewgraph import ViewGraph

__all__ = ["WeiszfeldConfig", "weiszfeld", "independent_sets"]

logger = logging.getLogger(__name__)


def independent_sets(vg: ViewGraph, seed: int = 0) -> list[np.ndarray]:
    """Partition the cameras into independent sets (Jones–Plassmann colouring).

    Each round colours every uncoloured camera whose random priority beats all
    its uncoloured neighbours; all rounds are vectorized sparse operations.

    Returns:
        list of camera index arrays; no edge joins two cameras of one set.
    """
    N = vg.n_cameras
    rng = np.random.default_rng(seed)
    prio = rng.permutation(N).astype(np.float64) + 1.0
    Adj = vg.adjacency().tocsr()
    Adj.data[:] = 1.0
    left = np.ones(N, dtype=bool)
    sets: list[np.ndarray] = []
    while left.any():
        p = np.where(left, prio, 0.0)
        # Max priority among uncoloured neighbours: sparse "max-product".
        nb = Adj.multiply(p[None, :]).max(axis=1).toarray().ravel()
        pick = left & (p > nb)
        sets.append(np.flatnonzero(pick))
        left &= ~pick
    return sets


def _estimates(vg: ViewGraph, R: np.ndarray, cams: np.ndarray, inc: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour estimates ``S_k`` of each camera in ``cams`` and the owner index."""
    sub = inc[cams]
    owner = np.repeat(np.arange(cams.size), np.diff(sub.indptr))
    eidx = sub.indices
    i, j = vg.edges[eidx, 0], vg.edges[eidx, 1]
    is_j = j == cams[owner]
    Rr = vg.R_rel[eidx]
    # camera j ≈ R_ij R_i; camera i ≈ R_ijᵀ R_j.
    other = np.where(is_j, i, j)
    rel = np.where(is_j[:, None, None], Rr, np.swapaxes(Rr, 1, 2))
    return rel @ R[other], owner


@dataclass(frozen=True, kw_only=True)
class WeiszfeldConfig(StartConfig):
    """Options of :func:`weiszfeld` (the ``weiszfeld`` method); see :func:`weiszfeld`."""

    SECTION = "averaging.weiszfeld"
    max_iterations: int = option(1000, "cap on sweeps over all cameras", ge=1)
    tol_rad: float = option(1e-3, "stop after a sweep whose largest camera update is below this (radians)", ge=0)
    inner_iterations: int = option(3, "Weiszfeld steps per camera update (the median search)", ge=1)
    inner_tol_rad: float = option(1e-6, "stop the median search when its step is below this (radians)", ge=0)
    loss: Literal["l1", "l2"] = option("l1", "l1 (Weiszfeld) or l2 (distributed Karcher mean)")
    vardi_zhang: bool = option(True, "Vardi–Zhang step at a camera that coincides with some estimates")


def weiszfeld(vg: ViewGraph, config: WeiszfeldConfig | None = None, *, init: str | np.ndarray | None = None,
              init_weights: np.ndarray | None = None, order: np.ndarray | None = None, eps_rad: float = 1e-12,
              **options: Any) -> AveragingResult:
    """ℓ1 averaging one camera at a time (Hartley et al. 2011).

    Args:
        vg: a connected view graph.
        config: the options; ``**options`` override its fields (:class:`WeiszfeldConfig`):
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations.
        max_iterations: cap on sweeps over all cameras.
        tol_rad: stop after a sweep whose largest camera update is below this.
        inner_iterations: Weiszfeld steps per camera update (the median search).
        inner_tol_rad: stop the median search when its step is below this.
        order: a camera sequence; each camera is updated alone, in this order.
            Default: independent sets (same result as some sequential order).
        seed: seed of the random spanning tree and of the colouring.
        init_weights: (M,) weights for the ``"mst"`` tree.
        eps_rad: guard on ``‖v_k‖`` (an estimate exactly at the current point).
        loss: ``"l1"`` (Weiszfeld, the default) or ``"l2"``: the same sweep with
            each camera moved to the geodesic (Karcher) mean of its neighbours'
            estimates, i.e. distributed ℓ2 averaging (Tron & Vidal), used to
            illustrate paper 1, Fig. 3(a).
        vardi_zhang: at a camera that coincides with some estimates, scale the
            step by the Vardi–Zhang factor (stay if the coincident estimates
            outweigh the pull of the others). False: plain Weiszfeld that skips
            coincident estimates, which always moves off them.

    Returns:
        :class:`AveragingResult`; ``iterations`` counts sweeps, ``history`` has one
        record per sweep (``cost`` = Σ‖r_ij‖, ``mean_step_rad``,
        ``max_step_rad``, ``time_s``).
    """
    cfg = method_config(WeiszfeldConfig, config, options, init)
    loss, seed, tol_rad = cfg.loss, cfg.seed, cfg.tol_rad
    check_graph(vg)
    t0 = time.perf_counter()
    N, M = vg.n_cameras, vg.n_edges
    R = initial_rotations(vg, start_of(init, cfg), weights=init_weights, seed=seed)
    if order is not None:
        order = np.asarray(order, dtype=np.int64)
        sets = [np.array([c]) for c in order]
    else:
        sets = independent_sets(vg, seed=seed or 0)
    # Camera × edge incidence, rows listing each camera's edges.
    rows = vg.edges.T.ravel()
    inc = sp.csr_matrix((np.ones(2 * M), (rows, np.r_[np.arange(M), np.arange(M)])), shape=(N, M))
    inc.sort_indices()
    history: list[dict[str, float]] = []
    converged = False
    sweep = 0
    for sweep in range(1, cfg.max_iterations + 1):
        steps = np.zeros(N)
        for cams in sets:
            S, owner = _estimates(vg, R, cams, inc)
            Rc = R[cams].copy()
            for _ in range(cfg.inner_iterations):
                v = so3.log(S @ np.swapaxes(Rc[owner], 1, 2))
                nv = np.linalg.norm(v, axis=1)
                # Estimates at the current point (e.g. the tree parent after a
                # spanning-tree init) would get infinite weight and freeze the
                # camera: leave them out and use the Vardi–Zhang correction.
                at = (nv < eps_rad) if loss == "l1" else np.zeros(nv.shape, bool)
                w = np.where(at, 0.0, 1.0 / np.maximum(nv, eps_rad)) if loss == "l1" else np.ones(nv.shape)
                num = np.zeros((cams.size, 3))
                np.add.at(num, owner, v * w[:, None])
                den = np.bincount(owner, weights=w, minlength=cams.size)
                eta = np.bincount(owner, weights=at.astype(float), minlength=cams.size)
                T = num / np.maximum(den, 1e-300)[:, None]
                # ‖Σ v/‖v‖‖ is the pull of the other estimates; move only if it
                # beats the η coincident ones.
                pull = np.linalg.norm(num, axis=1)
                scale = np.where(eta > 0, np.clip(1.0 - eta / np.maximum(pull, 1e-300), 0.0, 1.0), 1.0)
                if not cfg.vardi_zhang:
                    scale = np.ones_like(scale)
                d = T * scale[:, None]
                Rc = so3.exp(d) @ Rc
                if np.linalg.norm(d, axis=1).max() < cfg.inner_tol_rad:
                    break
            steps[cams] = so3.angle_between(Rc, R[cams])
            R[cams] = Rc
        r = graph_residuals(vg, R)
        history.append(
            {
                "stage": "weiszfeld",
                "cost": float(np.linalg.norm(r, axis=1).sum()),
                "mean_step_rad": float(steps.mean()),
                "max_step_rad": float(steps.max()),
                "time_s": time.perf_counter() - t0,
            }
        )
        if steps.max() < tol_rad:
            converged = True
            break
    r = graph_residuals(vg, R)
    theta = np.linalg.norm(r, axis=1)
    elapsed = time.perf_counter() - t0
    if not converged:
        logger.warning("Weiszfeld stopped at the sweep cap (%d); largest update %.3g rad", cfg.max_iterations,
                       history[-1]["max_step_rad"])
    return AveragingResult(
        method="weiszfeld" if loss == "l1" else "distributed-l2",
        names=list(vg.names),
        R=R,
        time_s=elapsed,
        iterations=sweep,
        edge_index=np.arange(M),
        residuals_rad=theta,
        weights=1.0 / np.maximum(theta, eps_rad),
        history=history,
        stats={"converged": converged, "n_independent_sets": len(sets), "final_cost": float(theta.sum())},
    )
