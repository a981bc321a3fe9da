"""Loop consistency: the view graph's own redundancy judges its edges.

Pure functions on arrays (``edges`` (M, 2), ``R_rel`` (M, 3, 3), per-edge standard
deviations ``sigma_deg`` (M,)); cycles from :mod:`pipeline.graph.cycles`.

- :func:`cycle_filter`: every triangle and 4-cycle is *consistent* when the angle of its
  composed rotation is at most ``clip(k·κ·σ_C, min_deg, max_deg)``, ``σ_C² = Σ σ_e²``
  over its edges; ``κ² = max(1, median(θ²/σ_C²) / median(χ²₃))`` is calibrated on all
  cycles once (the σ are overconfident on real images by a common factor; the outliers are
  a minority). Greedily, the edge with the largest fraction of bad cycles is removed when
  that fraction exceeds ``max_bad_fraction`` and it is, in at least one of its bad cycles,
  strictly the most suspicious edge (its partners are consistent elsewhere); then the
  counts are updated and the step repeated. A lone bad triangle blames nobody: its
  edges stay, unconfirmed. Cycles are enumerated once: the cycles of the kept graph are
  those whose edges are all kept.
- :func:`cycle_check`: an edge in no consistent short cycle is compared with the
  cheapest other path between its cameras (Dijkstra on σ²): first through confirmed
  edges only (all sources in one call), else through any kept edge. It is rejected only
  when it disagrees with a path of confirmed edges.
- :func:`colocation_check`: a rotation-only pair (``t = 0``: the two-view stage's
  zero-baseline model) claims that its cameras share a centre; a third camera with an
  ordinary pair to each must then see both centres in one direction. Static content and
  repeated structure fit the rotation-only model well and fail this test.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.stats import chi2

from pipeline.core import so3
from pipeline.graph.cycles import (Cycles, EdgeIndex, cycle_angles, cycle_variance, edge_cycles, expand_rows,
                                   find_cycles, find_triangles)

__all__ = ["CycleResult", "CycleRounds", "cycle_filter", "PathCheck", "cycle_check", "colocation_check", "group_median"]


@dataclass
class CycleResult:
    """Result of :func:`cycle_filter`.

    Attributes:
        kept: (M,) bool edges kept.
        removed: edge indices in the order they were removed.
        n_cycles, n_bad: (M,) cycles and inconsistent cycles through each edge (kept edges: in the
            final graph; removed edges: when they were removed).
        kappa2: the calibrated inflation of σ.
        confirmed: (M,) bool kept edges in at least one consistent cycle of the final graph.
        cycles: every cycle of the input graph; ``consistent`` (C,) and ``alive`` (C,) their state.
        angles: (C,) their angles, degrees.
        confirm_deg: (M,) the angle of the tightest consistent cycle of the final graph through each edge (inf:
            none), degrees: how closely its confirmation checks it.
    """

    kept: np.ndarray
    removed: list[int]
    n_cycles: np.ndarray
    n_bad: np.ndarray
    kappa2: float
    confirmed: np.ndarray
    cycles: Cycles
    consistent: np.ndarray
    alive: np.ndarray
    angles: np.ndarray
    confirm_deg: np.ndarray


def _fraction(n_b: np.ndarray, n_c: np.ndarray) -> np.ndarray:
    """The share of inconsistent cycles among an edge's cycles (0 for an edge in none)."""
    return np.where(n_c > 0, n_b / np.maximum(n_c, 1), 0.0)


def _owners(cyc_edges: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """(K,) the edge of each cycle whose ``frac`` is strictly the largest, −1 on a tie.

    ``cyc_edges`` (K, 4) pads a triangle with the sentinel edge ``len(frac) − 1``, whose ``frac`` is −1.
    """
    f = frac[cyc_edges]
    arg = np.argmax(f, axis=1)
    rows = np.arange(len(f))
    top = f[rows, arg]
    unique = np.count_nonzero(f == top[:, None], axis=1) == 1
    return np.where(unique, cyc_edges[rows, arg], -1)


def _reown(cycles: np.ndarray, owner: np.ndarray, blame: np.ndarray, padded: np.ndarray, frac: np.ndarray) -> None:
    """Recompute the owner (:func:`_owners`; a tie: the sentinel edge M) of ``cycles`` (unique, live, inconsistent)
    from the current ``frac`` and move their counts in ``blame`` ((M + 1,): the live inconsistent cycles each edge
    owns)."""
    new = _owners(padded[cycles], frac)
    new = np.where(new >= 0, new, len(frac) - 1)
    np.subtract.at(blame, owner[cycles], 1)
    np.add.at(blame, new, 1)
    owner[cycles] = new


@dataclass
class CycleRounds:
    """What the greedy rounds of :func:`cycle_filter` work on: every short cycle, judged once, and the counts of live
    cycles through each edge (:meth:`start`; :meth:`drop` removes an edge; :meth:`result`). Which edge goes: the caller.

    Attributes:
        kept: (M,) bool edges still kept.
        cycles: every cycle of the input graph; ``angles`` (C,) degrees, ``consistent`` (C,), ``alive`` (C,).
        kappa2: the calibrated inflation of σ.
        n_c, n_b: (M,) live cycles and live inconsistent cycles through each edge.
        ptr, through: the cycles through each edge (:func:`~pipeline.graph.cycles.edge_cycles`).
        removed: the edges dropped, in order; ``n_c_at``, ``n_b_at`` (M,) their counts when they went.
    """

    kept: np.ndarray
    cycles: Cycles
    angles: np.ndarray
    kappa2: float
    consistent: np.ndarray
    alive: np.ndarray
    n_c: np.ndarray
    n_b: np.ndarray
    ptr: np.ndarray
    through: np.ndarray
    removed: list[int] = field(default_factory=list)
    n_c_at: np.ndarray = field(init=False)
    n_b_at: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.n_c_at, self.n_b_at = self.n_c.copy(), self.n_b.copy()

    @classmethod
    def start(cls, edges: np.ndarray, R_rel: np.ndarray, n_cameras: int, sigma_deg: np.ndarray, *, max_len: int = 4,
              k_sigma: float = 3.0, min_deg: float = 1.0, max_deg: float | None = 10.0, calibrate: bool = True,
              active: np.ndarray | None = None, max_four_cycles: int = 2_000_000) -> "CycleRounds":
        """The cycles of ``edges`` (``active`` ones only), their angles, κ², each judged consistent or not
        (:func:`cycle_filter`'s arguments), and the counts through each edge."""
        edges = np.asarray(edges, np.int64).reshape(-1, 2)
        M = len(edges)
        kept = np.ones(M, bool) if active is None else np.asarray(active, bool).copy()
        cyc = find_cycles(edges, n_cameras, kept, max_len, max_four_cycles)
        ang = cycle_angles(R_rel, cyc)
        sC2 = cycle_variance(np.maximum(np.asarray(sigma_deg, float), 1e-6) ** 2, cyc)
        kappa2 = max(1.0, float(np.median(ang**2 / sC2)) / chi2.median(3)) if calibrate and len(cyc) else 1.0
        thr = np.maximum(min_deg, k_sigma * np.sqrt(kappa2 * sC2))
        if max_deg is not None:
            thr = np.minimum(thr, max_deg)
        ok = ang <= thr
        valid = cyc.edges >= 0
        flat, bad_rep = cyc.edges[valid], np.broadcast_to(~ok[:, None], cyc.edges.shape)[valid]
        ptr, through = edge_cycles(cyc, M)
        return cls(kept, cyc, ang, kappa2, ok, np.ones(len(cyc), bool), np.bincount(flat, minlength=M),
                   np.bincount(flat[bad_rep], minlength=M), ptr, through)

    def inconsistent(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The inconsistent cycles (indices of all cycles), those through each edge (``bptr``, ``bthrough``: indices
        of all cycles), and every cycle's edges with a triangle's padding as the sentinel edge M."""
        cyc, M = self.cycles, len(self.kept)
        bad_idx = np.flatnonzero(~self.consistent)
        bptr, bthrough = edge_cycles(Cycles(cyc.edges[bad_idx], cyc.forward[bad_idx], cyc.length[bad_idx]), M)
        return bad_idx, bptr, bad_idx[bthrough], np.where(cyc.edges >= 0, cyc.edges, M)

    def drop(self, best: int) -> tuple[np.ndarray, np.ndarray]:
        """Remove edge ``best`` (its counts recorded): its live cycles die and leave the counts. Returns those cycles
        and the edges they ran through (unique)."""
        self.n_c_at[best], self.n_b_at[best] = self.n_c[best], self.n_b[best]
        self.removed.append(best)
        self.kept[best] = False
        dead = self.through[self.ptr[best]:self.ptr[best + 1]]
        dead = np.unique(dead[self.alive[dead]])  # a walk through a pair measured twice can pass an edge twice
        self.alive[dead] = False
        e = self.cycles.edges[dead]
        m = e >= 0
        np.subtract.at(self.n_c, e[m], 1)
        np.subtract.at(self.n_b, e[m & ~self.consistent[dead, None]], 1)
        return dead, np.unique(e[m])

    def result(self) -> CycleResult:
        """The final graph's :class:`CycleResult` (a removed edge's counts: when it went)."""
        kept, ok, alive, ang = self.kept, self.consistent, self.alive, self.angles
        n_c_at, n_b_at = self.n_c_at.copy(), self.n_b_at.copy()
        confirmed = np.zeros(len(kept), bool)
        ce = self.cycles.edges[alive & ok]
        confirmed[ce[ce >= 0]] = True
        confirm_deg = np.full(len(kept), np.inf)
        np.minimum.at(confirm_deg, ce[ce >= 0], np.broadcast_to(ang[alive & ok][:, None], ce.shape)[ce >= 0])
        n_c_at[kept], n_b_at[kept] = self.n_c[kept], self.n_b[kept]
        return CycleResult(kept, list(self.removed), n_c_at, n_b_at, self.kappa2, confirmed & kept, self.cycles, ok,
                           alive, ang, np.where(confirmed & kept, confirm_deg, np.inf))


def cycle_filter(edges: np.ndarray, R_rel: np.ndarray, n_cameras: int, sigma_deg: np.ndarray, *, max_len: int = 4,
                 k_sigma: float = 3.0, min_deg: float = 1.0, max_deg: float | None = 10.0,
                 max_bad_fraction: float = 0.5, min_cycles: int = 1, calibrate: bool = True,
                 active: np.ndarray | None = None, max_four_cycles: int = 2_000_000) -> CycleResult:
    """Greedy removal of the edges that most short cycles disagree with (module docstring).

    Args:
        edges: (M, 2); R_rel: (M, 3, 3); n_cameras: N.
        sigma_deg: (M,) per-edge standard deviation, degrees.
        max_len: 3 (triangles) or 4 (also 4-cycles: a ring whose pairs (i, i+1), (i, i+2)
            are partly missing keeps 4-cycles).
        k_sigma, min_deg, max_deg: the consistency threshold.
        max_bad_fraction, min_cycles: when an edge is judged.
        calibrate: estimate κ²; otherwise κ² = 1.
        active: (M,) bool edges to consider (default all).
        max_four_cycles: the budget of 4-cycles (:func:`~pipeline.graph.cycles.find_cycles`).
    Returns:
        :class:`CycleResult`.
    """
    st = CycleRounds.start(edges, R_rel, n_cameras, sigma_deg, max_len=max_len, k_sigma=k_sigma, min_deg=min_deg,
                           max_deg=max_deg, calibrate=calibrate, active=active, max_four_cycles=max_four_cycles)
    cyc, ok, alive, n_c, n_b, kept = st.cycles, st.consistent, st.alive, st.n_c, st.n_b, st.kept
    M = len(kept)
    # An edge is removable when, in at least one live inconsistent cycle, it is strictly the most suspicious (its
    # "blame"); of the removable candidates, the first in priority order (largest bad fraction, then most bad cycles,
    # then lowest index) goes. Each cycle's owner is kept up to date: a round recomputes only the owners of the live
    # inconsistent cycles through an edge whose fraction changed (the same choice as recounting every cycle).
    bad_idx, bptr, bthrough, padded = st.inconsistent()
    frac = np.append(_fraction(n_b, n_c), -1.0)  # (M + 1,): the sentinel edge M's is −1
    owner, blame = np.full(len(cyc), M, np.int64), np.zeros(M + 1, np.int64)  # a consistent cycle owns nothing
    blame[M] = bad_idx.size
    _reown(bad_idx, owner, blame, padded, frac)
    while True:
        c = np.flatnonzero(kept & (n_c >= min_cycles) & (frac[:M] > max_bad_fraction) & (blame[:M] > 0))
        if not c.size:
            break
        c = c[frac[c] == frac[c].max()]
        best = int(c[np.argmax(n_b[c])])  # the first of the most bad cycles: the lowest index
        dead, changed = st.drop(best)
        np.subtract.at(blame, owner[dead[~ok[dead]]], 1)
        frac[changed] = _fraction(n_b[changed], n_c[changed])
        near = bthrough[expand_rows(bptr, changed)[1]]
        _reown(np.unique(near[alive[near]]), owner, blame, padded, frac)
    return st.result()


@dataclass
class PathCheck:
    """Result of :func:`cycle_check`.

    Attributes:
        checked: (M,) bool: another path between the edge's cameras was found.
        consistent: (M,) bool: the edge agrees with it.
        discrepancy_deg, threshold_deg: (M,) the angle between the edge and the path's composition
            and the threshold it was held to (NaN: no path).
        path_length: (M,) edges on the path (0: none).
        path_confirmed: (M,) bool: every edge of the path is confirmed.
    """

    checked: np.ndarray
    consistent: np.ndarray
    discrepancy_deg: np.ndarray
    threshold_deg: np.ndarray
    path_length: np.ndarray
    path_confirmed: np.ndarray


def _compose_paths(pred: np.ndarray, rows: np.ndarray, i: np.ndarray, j: np.ndarray, index: EdgeIndex,
                   R_rel: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compose the rotations along the predecessor paths from ``i`` to ``j`` (all paths at once, step by step).

    Returns the (K, 3, 3) composition ``R_{i→j}``, (K,) path lengths and the (K, L) edges walked (-1 padded).
    """
    K = len(i)
    P = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
    v = j.copy()
    length = np.zeros(K, np.int64)
    walked: list[np.ndarray] = []
    live = v != i
    while live.any():  # one step of every path per round: the loop is over path lengths
        u = np.where(live, pred[rows, v], v)
        e = np.where(live, index.lookup(u, v), -1)
        Ruv = np.where((u < v)[:, None, None], R_rel[np.maximum(e, 0)], np.swapaxes(R_rel[np.maximum(e, 0)], 1, 2))
        P[live] = P[live] @ Ruv[live]  # R_{i→j} = R_{v_{L-1}→j} ··· R_{i→v_1}: prepend walking back
        length += live
        walked.append(e)
        v = u
        live = v != i
    return P, length, (np.stack(walked, 1) if walked else np.zeros((K, 0), np.int64))


def _graph(edges: np.ndarray, var: np.ndarray, use: np.ndarray, n: int) -> sp.csr_matrix:
    """The (n, n) graph of the edges ``use`` selects, both directions, weighted by ``var``; indices sorted."""
    e, w = edges[use], var[use]
    G = sp.csr_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
    G.sort_indices()
    return G


def _shortest(edges: np.ndarray, var: np.ndarray, use: np.ndarray, n: int, sources: np.ndarray,
              limit: float) -> tuple[np.ndarray, np.ndarray]:
    return dijkstra(_graph(edges, var, use, n), directed=False, indices=sources, return_predecessors=True,
                    limit=limit)


def cycle_check(edges: np.ndarray, R_rel: np.ndarray, n_cameras: int, kept: np.ndarray, which: np.ndarray,
                sigma_deg: np.ndarray, confirmed: np.ndarray, *, k_sigma: float = 3.0, min_deg: float = 2.0,
                max_path_deg: float = 15.0) -> PathCheck:
    """Check each edge of ``which`` against the cheapest other path between its cameras (module docstring).

    The edge is consistent when the angle between it and the path's composition is at most
    ``max(min_deg, k_sigma·√(σ_e² + Σ_path σ²))``. Paths whose threshold would exceed
    ``max_path_deg`` check nothing and are not searched.

    Args:
        edges: (M, 2); R_rel: (M, 3, 3); n_cameras: N.
        kept: (M,) bool the graph searched; which: (M,) bool edges to check (subset of kept).
        sigma_deg: (M,) per-edge standard deviation, degrees.
        confirmed: (M,) bool edges confirmed by a consistent short cycle.
    Returns:
        :class:`PathCheck`.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    M = len(edges)
    kept, conf = np.asarray(kept, bool), np.asarray(confirmed, bool) & np.asarray(kept, bool)
    out = PathCheck(np.zeros(M, bool), np.zeros(M, bool), np.full(M, np.nan), np.full(M, np.nan),
                    np.zeros(M, np.int64), np.zeros(M, bool))
    var = np.maximum(np.asarray(sigma_deg, float), 1e-6) ** 2
    limit = (max_path_deg / k_sigma) ** 2
    todo = np.flatnonzero(np.asarray(which, bool) & kept)
    index = EdgeIndex(edges, n_cameras, kept)
    # 1. through confirmed edges only: every source in one call (the edges checked are not confirmed)
    # 2. the rest: through any other kept edge, one search per edge (those no confirmed path reaches)
    for phase in (1, 2):
        if not len(todo):
            break
        if phase == 1:
            src, rows_of = np.unique(edges[todo, 0], return_inverse=True)
            dist, pred = _shortest(edges, var, conf, n_cameras, src, limit)
            rows, ok = rows_of, np.isfinite(dist[rows_of, edges[todo, 1]])
            batch = [(todo[ok], rows[ok], dist, pred)]
            todo = todo[~ok]
        else:
            batch = []
            # the few edges no confirmed path reaches (e.g. a ring without triangles): one search each through the
            # other kept edges. The graph is built once; the edge searched around is blocked by a weight beyond
            # the search's limit, so no path within the limit can use it (as if it were removed).
            G = _graph(edges, var, kept, n_cameras)
            blocked = 2.0 * limit + 1.0
            for e in todo:
                i, j = edges[e]
                at = [G.indptr[a] + int(np.searchsorted(G.indices[G.indptr[a]:G.indptr[a + 1]], b))
                      for a, b in ((i, j), (j, i))]
                saved = G.data[at].copy()
                G.data[at] = blocked
                d, p = dijkstra(G, directed=True, indices=np.array([i]), return_predecessors=True, limit=limit)
                G.data[at] = saved
                if np.isfinite(d[0, j]):
                    batch.append((np.array([e]), np.zeros(1, np.int64), d, p))
        for es, rows, dist, pred in batch:
            i, j = edges[es, 0], edges[es, 1]
            P, length, walked = _compose_paths(pred, rows, i, j, index, R_rel, edges)
            ang = np.degrees(so3.angle_between(P, R_rel[es]))
            thr = np.maximum(min_deg, k_sigma * np.sqrt(var[es] + dist[rows, j]))
            out.checked[es] = True
            out.discrepancy_deg[es], out.threshold_deg[es] = ang, thr
            out.consistent[es] = ang <= thr
            out.path_length[es] = length
            out.path_confirmed[es] = np.where(walked >= 0, conf[np.maximum(walked, 0)], True).all(1)
    return out


def group_median(groups: np.ndarray, values: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) count and median of ``values`` per group id in ``groups`` (NaN where empty)."""
    order = np.lexsort((values, groups))
    g, x = groups[order], values[order]
    count = np.bincount(g, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    med = np.full(n, np.nan)
    has = count > 0
    lo = start[has] + (count[has] - 1) // 2
    hi = start[has] + count[has] // 2
    med[has] = 0.5 * (x[lo] + x[hi])
    return count, med


def colocation_check(edges: np.ndarray, R_rel: np.ndarray, t: np.ndarray, rotation_only: np.ndarray,
                     kept: np.ndarray, n_cameras: int, max_deg: float = 10.0, witness: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Test the claim of every rotation-only pair that its two cameras stand at one place.

    Camera c's centre, seen from camera k across edge e: ``t_ck`` when e is stored (c, k)
    (``x_k = R_ck x_c + t_ck``), ``−R_kcᵀ t_kc`` when stored (k, c). Witnesses: a triangle
    (a, b, k) with (a, b) rotation-only and ordinary pairs (a, k), (b, k): both centres in one
    direction from k; a 4-cycle with two opposite rotation-only edges (v₀, v₁), (v₂, v₃): the
    two claims make the baselines v₁ → v₂ and v₀ → v₃ parallel (a ring around two copies of an
    object has such cycles and no triangle).

    A witness's own pairs must have a baseline that is large against the claim's (``witness``):
    a third view of the same pan on the spot, a few centimetres from both, sees their centres
    in directions that say nothing (a rendered street's pan views, 5 cm of hand motion apart,
    saw each other's centres 20° apart through a pair with 1° of parallax).

    Args:
        edges: (M, 2); R_rel: (M, 3, 3); t: (M, 3) translations (zeros for rotation-only pairs).
        rotation_only: (M,) bool; kept: (M,) bool; n_cameras: N; max_deg: largest median angle accepted.
        witness: (M,) bool the pairs a witness may use (default: every pair that is not rotation-only).
    Returns:
        number of witnesses (M,), their median angle (M,) in degrees (NaN: none), reject (M,) bool.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    M = len(edges)
    t = np.asarray(t, float)
    tn = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    ro = np.asarray(rotation_only, bool) | (np.linalg.norm(t, axis=1) < 1e-9)
    wit = ~ro if witness is None else ~ro & np.asarray(witness, bool)
    if not (ro & kept).any():
        return np.zeros(M, np.int64), np.full(M, np.nan), np.zeros(M, bool)

    def centre_dir(cam: np.ndarray, e: np.ndarray) -> np.ndarray:
        """(K, 3) direction of camera ``cam``'s centre in the frame of the other end of edge ``e``."""
        first = edges[e, 0] == cam
        return np.where(first[:, None], tn[e], -np.einsum("kji,kj->ki", R_rel[e], tn[e]))

    rows, angs = [], []
    tri = find_triangles(edges, n_cameras, kept).edges[:, :3]  # edges ij, jk, ik of i < j < k
    ends = (lambda e: (edges[e, 0], edges[e, 1]))  # noqa: E731
    for pos in range(3):
        if not len(tri):
            break
        others = [c for c in range(3) if c != pos]
        e_ro, e1, e2 = tri[:, pos], tri[:, others[0]], tri[:, others[1]]
        sel = ro[e_ro] & wit[e1] & wit[e2]
        e_ro, e1, e2 = e_ro[sel], e1[sel], e2[sel]
        cu, cv = ends(e_ro)
        ea = np.where((edges[e1] == cu[:, None]).any(1), e1, e2)  # the witness's edge to cu
        eb = np.where(ea == e1, e2, e1)
        d = np.sum(centre_dir(cu, ea) * centre_dir(cv, eb), 1)
        rows.append(e_ro)
        angs.append(np.degrees(np.arccos(np.clip(d, -1, 1))))
    cyc = find_cycles(edges, n_cameras, kept, 4)
    q = cyc.length == 4
    E4, F4 = cyc.edges[q], cyc.forward[q]
    for shift in (0, 1):
        Es, Fs = np.roll(E4, -shift, axis=1), np.roll(F4, -shift, axis=1)
        sel = ro[Es[:, 0]] & ro[Es[:, 2]] & wit[Es[:, 1]] & wit[Es[:, 3]]
        Es, Fs = Es[sel], Fs[sel]
        v = np.where(Fs, edges[Es, 0], edges[Es, 1])  # start camera of each walked edge
        d_a = centre_dir(v[:, 2], Es[:, 1])  # centre of v₂ in v₁'s frame
        d_b = centre_dir(v[:, 3], Es[:, 3])  # centre of v₃ in v₀'s frame
        R01 = np.where(Fs[:, 0, None, None], R_rel[Es[:, 0]], np.swapaxes(R_rel[Es[:, 0]], 1, 2))
        ang = np.degrees(np.arccos(np.clip(np.sum(d_a * np.einsum("kij,kj->ki", R01, d_b), 1), -1, 1)))
        rows += [Es[:, 0], Es[:, 2]]
        angs += [ang, ang]
    r, a = np.concatenate(rows), np.concatenate(angs)
    n_w, med = group_median(r, a, M)
    return n_w, med, (n_w > 0) & (med > max_deg)
