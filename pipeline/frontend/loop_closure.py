"""Loop closure: the second matching round's pairs, chosen from the first round's verified view graph.

Retrieval matches each image with its k most similar images. Where a scene's look changes
abruptly (a weak junction of a ring, a corner of a street), the two sides can rank each
other below k; then no verified pair crosses there, the view graph is an open chain, and
nothing holds its drift (notes/issue-16.md: on a rendered ring of 300 views, the two
junction images rank each other 21st and 29th with k = 12, and IRLS-ℓ½ gives 0.705°
against 0.315° with those two pairs added). The first round's result says where to look:

- a **candidate** is a pair among each image's next-ranked retrieval neighbours (up to
  ``RANKED_PER_K``·k, :func:`pipeline.frontend.retrieval.ranked_neighbours`) that the first
  round did not match;
- its **value** is its hop distance in the first round's verified graph (∞ across
  components): the length of the loop it would close. A pair two hops apart closes a triangle
  the graph nearly has already; a pair at the two ends of an open ring closes the ring;
- the first round's averaged rotations rule out pairs whose viewing directions (optical axes) are
  more than ``max_angle_deg`` apart: they cannot overlap. A camera's roll about its own axis does not
  count, so nadir views of a survey flown as a serpentine, whose neighbouring lanes have opposite
  headings (a relative rotation of 180°), stay candidates; where either camera is unsolved, no pair is
  ruled out;
- pairs at least ``min_hops`` apart are taken longest loop first (then most similar), up to
  a budget of pairs, each as if it will verify: a candidate that a pair already taken brings
  within ``min_hops`` (through that pair) is passed over. So one weak junction costs a few
  pairs spread along it, not the whole budget.

Every pair taken is matched and verified like any other (two-view geometry, two-view BA,
the view graph's checks): a wrong candidate costs time, not accuracy.

**Saturated images** (:func:`saturated_candidates`). Retrieval's k is a guess of how many images
each image overlaps. Where almost every pair the first round matched verified, and the lower-ranked
half of an image's own k candidates verified too, its overlap reaches further down its ranking than k.
Such an image's further ranked neighbours that do not look more than ``max_angle_deg`` apart are
candidates as well (where the angle is not known, the next k ranked only). On a
rendered low-texture turntable ring of 48 views each image overlaps about 15 others, k is 8, 98% of the
matched pairs verified, and retrieval alone found 55% of the truly overlapping pairs. Where the views
overlap fewer others than k, many candidates fail: the rendered street, ring and grid of 100 views
verified 58, 74 and 83% of their matched pairs, the ring of 300 views 45%.

**Transitive pairs** (:func:`transitive_candidates`). A keypoint of image b that a verified pair matched to
image a and another verified pair matched to image c is a transitive correspondence of (a, c). COLMAP's
transitive matcher matches a with c wherever a–b and b–c matched; here a pair is matched only where its
transitive correspondences reach the view graph's least inliers of a pair (on the rings below, 107–121 pairs
instead of the ~800 two hops apart). Retrieval ranks a pair whose images share only part of their view
(two views 3–6 apart on a ring, each also seeing what the other does not) below the pairs that look alike;
their shared points still chain through the views between them. On the rendered rings of 300 views (five
renders), exhaustive matching verified 17–34 pairs that retrieval and the loop round had not matched, every one
two hops apart in their graph (23–336 transitive correspondences each on the first render), and those pairs
took IRLS-ℓ½ from 0.132° to 0.072° on that render. Of the unmatched pairs, 107–121 per render have at least
as many transitive correspondences as the view graph asks inliers of a pair (15), and they hold 132 of those 134
verified pairs; the loop-closure round matches them, the most transitive correspondences first.

Pure functions (arrays in, arrays out). Shapes: N images, m ranked neighbours per image,
E verified edges, P candidate pairs.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra, shortest_path

from pipeline.core.viewgraph import pair_keys

__all__ = ["hop_distances", "loop_candidates", "saturated_candidates", "transitive_candidates"]

_BFS_BLOCK = 256  # sources per shortest-path call: (256, N) distances at a time


def _adjacency(edges: np.ndarray, n: int) -> sp.csr_matrix:
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    A = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return sp.csr_matrix(A + A.T)


def hop_distances(edges: np.ndarray, n: int, pairs: np.ndarray) -> np.ndarray:
    """Hop distance (P,) in the graph of ``edges`` (E, 2) on n nodes between the two images of each pair (P, 2);
    ``inf`` when they lie in different components. Breadth-first from each distinct first image, in blocks."""
    return _hops(_adjacency(edges, n), np.asarray(pairs, np.int64).reshape(-1, 2))


def _hops(A: sp.csr_matrix, pairs: np.ndarray) -> np.ndarray:
    """:func:`hop_distances` on the symmetric adjacency A."""
    out = np.full(len(pairs), np.inf)
    if not len(pairs):
        return out
    _, comp = connected_components(A, directed=False)
    same = comp[pairs[:, 0]] == comp[pairs[:, 1]]
    src, row = np.unique(pairs[same, 0], return_inverse=True)
    idx = np.flatnonzero(same)
    for s in range(0, len(src), _BFS_BLOCK):  # blocks of sources, each block one C call
        sel = (row >= s) & (row < s + _BFS_BLOCK)
        D = shortest_path(A, unweighted=True, directed=False, indices=src[s:s + _BFS_BLOCK])
        out[idx[sel]] = D[row[sel] - s, pairs[idx[sel], 1]]
    return out


def _best_per_pair(keys: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Positions of the first occurrence of each distinct key of ``keys`` (P,) once ordered by key and, per key,
    by similarity ``s`` (P,) from the best: each pair once, with its best similarity, in key order."""
    order = np.lexsort((-s, keys))
    k = keys[order]
    return order[np.r_[True, k[1:] != k[:-1]]] if len(k) else order


def _pair_angles(R: np.ndarray | None, P: np.ndarray) -> np.ndarray:
    """:func:`_angles_deg` of the pairs P (K, 2); all NaN (not known) when there are no rotations."""
    return np.full(len(P), np.nan) if R is None else _angles_deg(np.asarray(R, float), P[:, 0], P[:, 1])


def _angles_deg(R: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (P,) in degrees between the viewing directions of cameras a and b, for cam_from_world rotations R
    (N, 3, 3): the optical axis of camera i in the world is the third row of R_i. NaN where either is NaN."""
    cos = np.einsum("pj,pj->p", R[b, 2], R[a, 2])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _spread(A: sp.csr_matrix, P: np.ndarray, min_hops: int, budget: int) -> np.ndarray:
    """Positions of the pairs taken from ``P`` (C, 2), in order: each in turn unless a pair taken before brings
    its two images within ``min_hops`` through itself (as if it verified). Per pair taken: one breadth-first
    search bounded at ``min_hops`` hops from each of its images, and an update of the pairs near them."""
    n = A.shape[0]
    ends = np.r_[P[:, 0], P[:, 1]]
    touch = sp.csr_matrix((np.ones(len(ends)), (ends, np.r_[np.arange(len(P)), np.arange(len(P))])),
                          shape=(n, len(P)))  # image → the candidates it belongs to
    passed = np.zeros(len(P), bool)
    taken: list[int] = []
    pos = 0
    while len(taken) < budget and pos < len(P):  # one iteration per pair taken (≤ budget)
        nxt = pos + int(np.argmax(~passed[pos:]))
        if passed[nxt]:
            break
        taken.append(nxt)
        pos = nxt + 1
        D = dijkstra(A, indices=P[nxt], unweighted=True, limit=min_hops)  # (2, n), inf beyond min_hops
        near = np.flatnonzero(np.isfinite(D).any(axis=0))
        cand = np.unique(touch[near].indices)
        cand = cand[cand > nxt]
        c, d = P[cand, 0], P[cand, 1]
        via = np.minimum(D[0, c] + 1 + D[1, d], D[1, c] + 1 + D[0, d])
        passed[cand[via < min_hops]] = True
    return np.asarray(taken, np.int64)


def loop_candidates(n: int, matched: np.ndarray, verified: np.ndarray, neighbours: np.ndarray,
                    similarities: np.ndarray, R: np.ndarray | None = None, *, min_hops: int = 3,
                    max_angle_deg: float = 60.0, budget: int) -> dict[str, Any]:
    """The pairs of a loop-closure round (see the module docstring).

    Args:
        n: number of images N.
        matched: (P1, 2) the pairs the first round matched (verified or not), ``a < b``.
        verified: (E, 2) the pairs it verified (the two-view BA's edges).
        neighbours: (N, m) each image's ranked retrieval neighbours, best first.
        similarities: (N, m) their similarities.
        R: (N, 3, 3) the first round's averaged rotations, NaN for unsolved images; None: no angle test.
        min_hops: the least hop distance of a pair taken, in the verified graph and through each pair taken
            before it.
        max_angle_deg: pairs whose viewing directions are further apart are not taken.
        budget: the most pairs taken.
    Returns:
        ``pairs`` (P, 2) ``a < b`` in the order taken, and per pair ``hops``, ``angle_deg`` (NaN: not known)
        and ``similarity``; the counts ``n_candidates`` (unmatched ranked pairs), ``n_far`` (of them at least
        ``min_hops`` apart or across components), ``n_apart`` (of those, ruled out by the angle),
        ``n_eligible`` (far and not apart: the pairs examined, longest loop first), ``n_across`` (of the pairs
        taken, those across components).
    """
    nb = np.asarray(neighbours, np.int64)
    a = np.repeat(np.arange(n), nb.shape[1])
    b, s = nb.ravel(), np.asarray(similarities, np.float64).ravel()
    ok = a != b
    P = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)[ok]
    s = s[ok]
    key = pair_keys(P[:, 0], P[:, 1], n)
    best = _best_per_pair(key, s)
    key, P, s = key[best], P[best], s[best]
    m = np.asarray(matched, np.int64).reshape(-1, 2)
    new = ~np.isin(key, pair_keys(m[:, 0], m[:, 1], n))
    P, s = P[new], s[new]
    A = _adjacency(verified, n)
    hops = _hops(A, P)
    far = hops >= min_hops
    ang = _pair_angles(R, P)
    apart = far & (ang > max_angle_deg)  # NaN compares False: unknown angles never rule a pair out
    take = np.flatnonzero(far & ~apart)
    take = take[np.lexsort((-s[take], -hops[take]))]  # longest loop first, then most similar
    if budget > 0 and len(take):
        take = take[_spread(A, P[take], min_hops, int(budget))]
    else:
        take = take[:0]
    return {"pairs": P[take], "hops": hops[take], "angle_deg": ang[take], "similarity": s[take],
            "n_candidates": int(len(P)), "n_far": int(far.sum()), "n_apart": int(apart.sum()),
            "n_across": int(np.isinf(hops[take]).sum()), "n_eligible": int((far & ~apart).sum())}


def saturated_candidates(n: int, k: int, matched: np.ndarray, verified: np.ndarray, neighbours: np.ndarray,
                         similarities: np.ndarray, R: np.ndarray | None = None, *, share: float = 0.95,
                         max_angle_deg: float = 60.0, budget: int) -> dict[str, Any]:
    """The next-ranked neighbours of the saturated images (module docstring), most similar first.

    Args:
        n, matched, verified, neighbours, similarities, R, max_angle_deg: as :func:`loop_candidates`.
        k: the retrieval neighbours per image of the first round.
        share: an image is saturated when at least this share of its candidates ranked ``⌈k/2⌉ … k − 1`` verified,
            and at least this share of all the pairs ``matched`` verified (the collection's overlap exceeds k).
            A saturated image's candidates are its ranked neighbours after the k-th that do not look more than
            ``max_angle_deg`` apart by ``R``; where the angle is not known, its next k only.
        budget: the most pairs taken.
    Returns:
        ``pairs`` (P, 2) ``a < b``, ``similarity`` and ``angle_deg`` (P,); ``saturated`` (N,) bool;
        ``verified_share`` (of ``matched``); the counts ``n_saturated``, ``n_candidates`` (unmatched next-ranked
        pairs of saturated images) and ``n_apart`` (of them ruled out by the angle).
    """
    nb = np.asarray(neighbours, np.int64)
    sim = np.asarray(similarities, np.float64)
    k = int(min(k, nb.shape[1]))
    v = np.asarray(verified, np.int64).reshape(-1, 2)
    m = np.asarray(matched, np.int64).reshape(-1, 2)

    tail = nb[:, (k + 1) // 2:k]
    vkeys, mkeys = pair_keys(v[:, 0], v[:, 1], n), pair_keys(m[:, 0], m[:, 1], n)
    collection = float(np.isin(mkeys, vkeys).mean()) if len(m) else 0.0
    saturated = (np.isin(pair_keys(np.arange(n)[:, None], tail, n), vkeys).mean(axis=1) >= share
                 if tail.shape[1] and collection >= share else np.zeros(n, bool))
    nxt, s = nb[saturated, k:], sim[saturated, k:]
    a = np.broadcast_to(np.flatnonzero(saturated)[:, None], nxt.shape).ravel()
    b, s = nxt.ravel(), s.ravel()
    near = np.broadcast_to(np.arange(nxt.shape[1]) < k, nxt.shape).ravel()  # the next k ranks
    keys = pair_keys(a, b, n)
    fresh = (a != b) & ~np.isin(keys, mkeys)
    keys, s, near_keys = keys[fresh], s[fresh], keys[fresh & near]
    best = _best_per_pair(keys, s)
    keys, s = keys[best], s[best]
    near = np.isin(keys, near_keys)  # within the next k ranks of either image
    P = np.stack([keys // n, keys % n], axis=1)
    ang = _pair_angles(R, P)
    apart = ang > max_angle_deg
    # a known angle decides at any rank; without one (no rotations, an unsolved image) only the next k ranks
    take = np.flatnonzero(np.where(np.isnan(ang), near, ~apart))
    take = take[np.argsort(-s[take], kind="stable")][:max(int(budget), 0)]
    return {"pairs": P[take], "similarity": s[take], "angle_deg": ang[take], "saturated": saturated,
            "verified_share": collection,
            "n_saturated": int(saturated.sum()), "n_candidates": int(len(P)), "n_apart": int(apart.sum())}


def transitive_candidates(n: int, matched: np.ndarray, edges: np.ndarray, offsets: np.ndarray, kp_a: np.ndarray,
                          kp_b: np.ndarray, *, min_count: int, budget: int) -> dict[str, Any]:
    """The unmatched pairs with at least ``min_count`` transitive correspondences (module docstring), the most first.

    Args:
        n: number of images N.
        matched: (P1, 2) the pairs matched already (verified or not).
        edges: (E, 2) the verified pairs whose inliers chain.
        offsets: (E+1,) start of each edge's inliers in ``kp_a``, ``kp_b``.
        kp_a, kp_b: (total,) keypoint indices of the inliers in images ``edges[:, 0]`` and ``edges[:, 1]``.
        min_count: the least transitive correspondences of a pair taken.
        budget: the most pairs taken.
    Returns:
        ``pairs`` (P, 2) ``a < b`` and ``count`` (P,) in the order taken; ``n_candidates`` (unmatched pairs with
        any transitive correspondence) and ``n_eligible`` (of them with at least ``min_count``).
    """
    E = np.asarray(edges, np.int64).reshape(-1, 2)
    per = np.diff(np.asarray(offsets, np.int64))
    if len(per) != len(E):
        raise ValueError(f"{len(E)} edges but {len(per)} inlier ranges")
    e = np.repeat(np.arange(len(E)), per)
    ka, kb = np.asarray(kp_a, np.int64), np.asarray(kp_b, np.int64)
    width = int(max(ka.max(initial=-1), kb.max(initial=-1))) + 1
    # one row per keypoint (image b, keypoint k) that a verified pair matched; a column per image it matched in
    rows = np.r_[E[e, 1] * width + kb, E[e, 0] * width + ka]
    cols = np.r_[E[e, 0], E[e, 1]]
    _, rows = np.unique(rows, return_inverse=True)
    T = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(int(rows.max(initial=-1)) + 1, n))
    T.data[:] = 1.0  # one keypoint matched twice into the same image counts once
    C = sp.triu(T.T @ T, k=1).tocoo()  # (a, c): keypoints matched into both a and c
    P = np.stack([C.row, C.col], axis=1).astype(np.int64)
    count = np.rint(C.data).astype(np.int64)
    m = np.asarray(matched, np.int64).reshape(-1, 2)
    key = pair_keys(P[:, 0], P[:, 1], n)
    new = ~np.isin(key, pair_keys(m[:, 0], m[:, 1], n))
    P, count, key = P[new], count[new], key[new]
    take = np.flatnonzero(count >= min_count)
    take = take[np.lexsort((key[take], -count[take]))][:max(int(budget), 0)]
    return {"pairs": P[take], "count": count[take], "n_candidates": int(len(P)),
            "n_eligible": int((count >= min_count).sum())}
