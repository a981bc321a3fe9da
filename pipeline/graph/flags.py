"""Flags of the cameras whose rotation rests on evidence nothing checks, with the reason.

Pure functions on arrays. A camera is flagged when

- it rests on a single pair (degree 1): that pair's error is the camera's;
- it is joined to the rest only through a *bridge* (an edge in no cycle: its error
  can never be detected), i.e. it lies outside the largest 2-edge-connected block of
  its component; every bridge on the path from its block to that one is named, in
  order (its rotation rests on each of them);
- its block is that largest one, but more than half of its component's cameras hang off it through one
  bridge: aligned as a whole (to the truth, to another model), an error δ in that pair moves the block by
  δ·(far side)/N and the cameras beyond by the rest, so the block takes the larger share of an error nothing
  can detect; or it is one of several equally large blocks (which of them is the reference the others hang
  off is then arbitrary: each is flagged, whatever the cameras' labels);
- none of its pairs is in a consistent cycle (unconfirmed);
- one of its pairs is confirmed only loosely: every cycle (or path) that confirms it closes above
  ``confirm_max_deg`` (the checks' tolerance widens with the pairs' overconfidence, κ, up to
  ``cycle_max_deg``; a triangle closing at 6° has a pair 2° off, so it does not vouch for a degree or two, and
  such a pair may be degrees off and pull the camera);
- some of its pairs were rejected as inconsistent with the others;
- it is joined to the largest block only through pairs that no cycle confirmed and that
  the checks kept only so as not to lose cameras (``bridged``: a pan on the spot).

A graph without cycles (a forest) gets the message that its result cannot be verified.

Bridges (:func:`bridges`) come from one depth-first order (scipy) and the low points of
its subtrees, computed on the preorder with sparse tables: O((N + M) log N), vectorized.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, depth_first_order

from pipeline.graph.cycles import EdgeIndex

__all__ = ["bridges", "two_edge_blocks", "GraphFlags", "graph_flags", "NO_CYCLE"]

NO_CYCLE = ("the view graph has no cycle: no relative rotation is checked by another, so the result cannot be "
            "verified")


def _graph(a: np.ndarray, b: np.ndarray, n: int) -> sp.csr_matrix:
    return sp.csr_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(n, n))


def _depths(pred: np.ndarray, root: int) -> np.ndarray:
    """Depth of every node of a tree given by its predecessors (pointer doubling, log N rounds)."""
    jump = np.where(pred < 0, root, pred)
    jump[root] = root
    dist = (np.arange(len(pred)) != root).astype(np.int64)
    while np.any(jump != root):
        dist = dist + np.where(jump != root, dist[jump], 0)
        jump = jump[jump]
    return dist


def _sparse_table(x: np.ndarray) -> list[np.ndarray]:
    """Range-minimum tables: ``t[k][p] = min(x[p : p + 2^k])``."""
    t = [x]
    k = 1
    while (1 << k) <= len(x):
        prev = t[-1]
        h = 1 << (k - 1)
        t.append(np.minimum(prev[:-h], prev[h:]))
        k += 1
    return t


def _range_min(t: list[np.ndarray], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """min(x[lo:hi]) for hi > lo (vectorized)."""
    k = np.floor(np.log2(np.maximum(hi - lo, 1))).astype(np.int64)
    out = np.empty(len(lo), t[0].dtype)
    for kk in np.unique(k):
        s = k == kk
        out[s] = np.minimum(t[kk][lo[s]], t[kk][hi[s] - (1 << kk)])
    return out


def bridges(edges: np.ndarray, n: int, active: np.ndarray | None = None) -> np.ndarray:
    """(M,) bool: the active edges whose removal disconnects their component (edges in no cycle)."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    act = np.ones(len(edges), bool) if active is None else np.asarray(active, bool)
    out = np.zeros(len(edges), bool)
    if not act.any():
        return out
    a, b = edges[act, 0], edges[act, 1]
    _, lab = connected_components(_graph(a, b, n), directed=False)
    reps = np.unique(lab, return_index=True)[1]  # one camera per component, joined to a virtual root n
    G = _graph(np.r_[a, np.full(len(reps), n)], np.r_[b, reps], n + 1)
    order, pred = depth_first_order(G, n, directed=False, return_predecessors=True)
    depth = _depths(pred, n)
    pos = np.empty(n + 1, np.int64)
    pos[order] = np.arange(n + 1)
    index = EdgeIndex(edges, n, act)
    child = np.flatnonzero((pred >= 0) & (pred < n))  # real tree edges (pred[child], child)
    tree = index.lookup(pred[child], child)
    non_tree = act.copy()
    non_tree[tree] = False
    lowd = depth.copy()  # the shallowest depth reached from each node by one non-tree edge
    ea, eb = edges[non_tree, 0], edges[non_tree, 1]
    np.minimum.at(lowd, ea, depth[eb])
    np.minimum.at(lowd, eb, depth[ea])
    D = depth[order]
    tD = _sparse_table(D)
    # end of each subtree in preorder: the first later position whose depth is not deeper
    s = pos[child] + 1
    dx = depth[child]
    for k in range(len(tD) - 1, -1, -1):
        step = 1 << k
        can = s + step <= n + 1
        m = np.full(len(s), -1)
        m[can] = tD[k][s[can]]
        s = np.where(can & (m > dx), s + step, s)
    sub_min = _range_min(_sparse_table(lowd[order]), pos[child], s)
    out[tree[sub_min >= dx]] = True
    return out


def two_edge_blocks(edges: np.ndarray, n: int, kept: np.ndarray, bridge: np.ndarray) -> np.ndarray:
    """(N,) label of each camera's 2-edge-connected block (the pieces left when the bridges are cut)."""
    use = np.asarray(kept, bool) & ~np.asarray(bridge, bool)
    return connected_components(_graph(edges[use, 0], edges[use, 1], n), directed=False)[1]


@dataclass
class GraphFlags:
    """Result of :func:`graph_flags`.

    Attributes:
        cameras: {camera index: [reasons]} of every flagged camera.
        bridge: (M,) bool the kept edges in no cycle.
        messages: graph-level messages (no cycle).
        n_cycles: the cycle rank M − N + c of the kept graph over the cameras considered.
    """

    cameras: dict[int, list[str]] = field(default_factory=dict)
    bridge: np.ndarray | None = None
    messages: list[str] = field(default_factory=list)
    n_cycles: int = 0


def _bridges_towards_core(edges: np.ndarray, n: int, kept: np.ndarray, br: np.ndarray, block: np.ndarray,
                          shown: int = 3) -> tuple[np.ndarray, ...]:
    """Per camera: whether its block is its component's largest (the core), the bridges on the path from its block
    to the core in order, the one leaving its block first ((N, ``shown``) edge indices, -1 past the path's end),
    how many bridges that path has, its component's label (of the kept edges), and how many blocks of its component
    are as large as the largest when its own is one of them (else 0: :func:`_ties_of_largest`)."""
    n_blocks = int(block.max()) + 1
    _, comp = connected_components(_graph(edges[kept, 0], edges[kept, 1], n), directed=False)
    comp_of_block = np.zeros(n_blocks, np.int64)
    comp_of_block[block] = comp
    tied = _ties_of_largest(block, comp, np.ones(n, bool))[:n_blocks]
    # the core of a component: its largest block (the lowest label among equals)
    largest = np.flatnonzero(tied > 0)
    core = np.zeros(n_blocks, bool)
    core[largest[np.unique(comp_of_block[largest], return_index=True)[1]]] = True
    bi = np.flatnonzero(br)
    ba, bb = block[edges[bi, 0]], block[edges[bi, 1]]
    cores = np.flatnonzero(core)
    # the blocks and bridges form a tree per component: its cores joined to a virtual root, n_blocks
    T = _graph(np.r_[ba, np.full(len(cores), n_blocks)], np.r_[bb, cores], n_blocks + 1)
    _, pred = breadth_first_order(T, n_blocks, directed=False, return_predecessors=True)
    towards = np.full(n_blocks, -1)  # the bridge from each block to the next one towards its core
    nc = ~core & (pred[:n_blocks] >= 0)
    towards[nc] = EdgeIndex(np.stack([np.minimum(ba, bb), np.maximum(ba, bb)], 1), n_blocks).lookup(
        np.flatnonzero(nc), pred[:n_blocks][nc])
    towards = np.where(towards >= 0, bi[np.maximum(towards, 0)], -1) if len(bi) else towards
    parent = np.where(nc, pred[:n_blocks], -1)
    count = np.where(core, 0, _depths(pred, n_blocks)[:n_blocks] - 1)  # the root is 1 hop beyond the core
    path = np.full((n_blocks, shown), -1)
    at = np.arange(n_blocks)
    for k in range(shown):  # one block towards the core per step, every block at once
        path[:, k] = np.where(at >= 0, towards[np.maximum(at, 0)], -1)
        at = np.where(at >= 0, parent[np.maximum(at, 0)], -1)
    return core[block], path[block], count[block], comp, tied[block]


def _minor_core(edges: np.ndarray, n: int, kept: np.ndarray, core: np.ndarray, comp: np.ndarray, size: np.ndarray,
                tied: np.ndarray, pair: Callable[[int], str]) -> tuple[np.ndarray, list[str]]:
    """The core cameras that lie on the smaller side of a bridge (module docstring), or whose block is one of
    ``tied`` (per camera) equally large ones (:func:`_ties_of_largest`), and why, naming the bridge.

    Without the core's cameras, each part of a component that hung off the core through one bridge is a
    connected piece of its own (blocks and bridges form a tree): the core is the smaller side of a bridge
    when the largest such piece holds more than half of the component's cameras. A kept pair with one camera
    in the core and one outside is a bridge (the core is 2-edge-connected): the one into the largest piece is
    named. ``kept`` holds the considered cameras' pairs only, so every other camera is a component of its own."""
    comp_size = np.bincount(comp, minlength=n)
    rest = kept & ~core[edges[:, 0]] & ~core[edges[:, 1]]
    piece = connected_components(_graph(edges[rest, 0], edges[rest, 1], n), directed=False)[1]
    piece_size = np.bincount(piece[~core], minlength=n)
    out = np.flatnonzero(kept & (core[edges[:, 0]] != core[edges[:, 1]]))  # the bridges leaving a core
    beyond = np.where(core[edges[out, 0]], edges[out, 1], edges[out, 0])
    far = np.zeros(n, np.int64)  # per component: its largest piece hanging off the core, and its bridge
    via = np.full(n, -1)
    order = np.lexsort((out, -piece_size[piece[beyond]]))  # largest piece first, then the lowest edge
    c = comp[beyond[order]]
    first = np.unique(c, return_index=True)[1]
    far[c[first]] = piece_size[piece[beyond[order[first]]]]
    via[c[first]] = out[order[first]]
    # a block of one camera (a tree's lowest label) is not joined by cycles: nothing to judge
    minor = core & (size > 1) & (2 * far[comp] > comp_size[comp])
    ks = np.flatnonzero(minor | (core & (size > 1) & (tied > 1) & (via[comp] >= 0)))
    return ks, [f"{far[comp[k]]} of the {comp_size[comp[k]]} cameras of its component hang off its block (the "
                f"largest that cycles join, {size[k]} cameras) through the bridge pair {pair(via[comp[k]])}: "
                "aligned as a whole, an error in that pair moves this block more than the cameras beyond it, and "
                "nothing can detect it" if minor[k] else
                f"its block is one of {tied[k]} equally large ones that cycles join in its component ({size[k]} "
                f"cameras each), joined only through bridges (from this one, {pair(via[comp[k]])}): no block is "
                "the reference the others hang off, and an error in such a pair moves this block and cannot be "
                "detected" for k in ks]


def _ties_of_largest(piece: np.ndarray, group: np.ndarray, cams: np.ndarray) -> np.ndarray:
    """Per piece label: if the piece is one of the largest of its component, how many pieces of that component are
    that large (1: it alone), else 0. ``piece``, ``group``: each camera's piece and component; a piece's size counts
    the cameras ``cams``. Which of several largest pieces is the reference is arbitrary, so each is flagged."""
    n = len(piece)
    size = np.bincount(piece[cams], minlength=n)
    group_of = np.zeros(n, np.int64)
    group_of[piece[cams]] = group[cams]
    top = np.zeros(n, np.int64)
    np.maximum.at(top, group_of, size)
    largest = (size > 0) & (size == top[group_of])
    return np.where(largest, np.bincount(group_of[largest], minlength=n)[group_of], 0)


def _bridge_reason(path: np.ndarray, count: int, pair: Callable[[int], str]) -> str:
    """Why a camera is flagged whose block hangs off the core through ``count`` bridges in series (``path``: the
    first of them, from its block on)."""
    if count == 1:
        return f"joined to the rest only through the bridge pair {pair(path[0])}: an error in that pair cannot be " \
               "detected"
    named = [pair(e) for e in path[:count]] + ([f"{count - len(path)} more"] if count > len(path) else [])
    return (f"joined to the rest only through the bridge pairs {', '.join(named[:-1])} and {named[-1]} in series: "
            "an error in any of them cannot be detected")


def _flag_bridged(edges: np.ndarray, n: int, kept: np.ndarray, bridged: np.ndarray, cams: np.ndarray,
                  comp: np.ndarray, pair: Callable[[int], str], add: Callable[[np.ndarray, list[str]], None]) -> None:
    """Flag the cameras outside the largest part of their component (``comp``) that the kept edges without
    ``bridged`` leave, naming the bridged pairs that join their part (a few bridged edges: one loop over them).
    Where several parts of a component are the largest, none is the reference: each is flagged."""
    rest = kept & ~bridged
    _, part = connected_components(_graph(edges[rest, 0], edges[rest, 1], n), directed=False)
    main = _ties_of_largest(part, comp, cams) == 1  # per part: its component's one largest
    via: dict[int, list[int]] = {}
    for e in np.flatnonzero(bridged):
        for p in {int(part[edges[e, 0]]), int(part[edges[e, 1]])}:
            via.setdefault(p, []).append(int(e))
    out = np.flatnonzero(cams & ~main[part])
    add(out, [_bridged_reason(via.get(int(part[k]), []), pair) for k in out])


def _bridged_reason(pairs: list[int], pair: Callable[[int], str]) -> str:
    return (f"joined to the rest only through {len(pairs)} pair(s) that no cycle confirms, kept so that its part of "
            "the graph is not lost: " + ", ".join(pair(e) for e in pairs[:3]) + ("…" if len(pairs) > 3 else ""))


def _loose_reasons(edges: np.ndarray, loose: np.ndarray, cd: np.ndarray, cams: np.ndarray,
                   pair: Callable[[int], str], limit: float) -> tuple[np.ndarray, list[str]]:
    """The cameras of the loosely confirmed pairs ``loose`` (edge indices) and, for each, its reason naming them."""
    cam, via = np.r_[edges[loose, 0], edges[loose, 1]], np.r_[loose, loose]
    order = np.lexsort((cd[via], cam))  # by camera, then tightest first
    cam, via = cam[order], via[order]
    starts = np.flatnonzero(np.r_[True, cam[1:] != cam[:-1]]) if cam.size else np.zeros(0, np.int64)
    out_c, out_w = [], []
    for lo, hi in zip(starts.tolist(), np.r_[starts[1:], cam.size].tolist()):  # one per flagged camera
        if not cams[cam[lo]]:
            continue
        ps = via[lo:hi]
        one = ps.size == 1
        out_c.append(cam[lo])
        out_w.append(f"{'its pair' if one else f'{ps.size} of its pairs'} {', '.join(pair(e) for e in ps[:3])}"
                     f"{'…' if ps.size > 3 else ''} {'is' if one else 'are'} confirmed only loosely (the tightest "
                     f"cycle through {'it' if one else 'each'} closes at "
                     f"{', '.join(f'{cd[e]:.1f}°' for e in ps[:3])}, > {limit:g}°): such a pair may be degrees off "
                     "and pull this rotation")
    return np.asarray(out_c, np.int64), out_w


def graph_flags(edges: np.ndarray, n: int, kept: np.ndarray, confirmed: np.ndarray, inconsistent: np.ndarray,
                names: list[str], cameras: np.ndarray | None = None, cycles_checked: bool = True,
                bridged: np.ndarray | None = None, confirm_deg: np.ndarray | None = None,
                confirm_max_deg: float = 5.0) -> GraphFlags:
    """Flag the cameras whose rotation rests on unchecked or disputed evidence (module docstring).

    Args:
        edges: (M, 2); n: number of cameras.
        kept: (M,) bool the edges the averaging uses.
        confirmed: (M,) bool kept edges in a consistent cycle (or consistent with a longer one).
        inconsistent: (M,) bool edges rejected because they disagree with the others.
        names: camera names (for the reasons).
        cameras: (N,) bool the cameras to flag (default all with a kept edge); the cycle rank
            and the messages are those of the kept edges among them.
        cycles_checked: False when no cycle was tested (``confirmed`` means nothing): the
            structural flags only (single pair, bridge).
        bridged: (M,) bool kept edges that the checks kept only because they join cameras to the rest.
        confirm_deg: (M,) how closely each confirmed edge was checked, degrees (the checks' ``confirm_deg``);
            with it, a camera with a kept pair confirmed only above ``confirm_max_deg`` is flagged.
    Returns:
        :class:`GraphFlags`.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    kept = np.asarray(kept, bool)
    deg = np.bincount(edges[kept].ravel(), minlength=n)
    cams = deg > 0 if cameras is None else np.asarray(cameras, bool) & (deg > 0)
    kept = kept & cams[edges[:, 0]] & cams[edges[:, 1]]
    flags: dict[int, list[str]] = {}
    if not kept.any():
        return GraphFlags(flags, np.zeros(len(edges), bool), [], 0)

    def add(ks: np.ndarray, why: list[str]) -> None:
        for k, w in zip(ks.tolist(), why):
            flags.setdefault(int(k), []).append(w)

    pair = lambda e: f"({names[edges[e, 0]]}, {names[edges[e, 1]]})"  # noqa: E731
    # the single kept edge of each degree-1 camera
    inc_e = np.r_[np.flatnonzero(kept), np.flatnonzero(kept)]
    inc_c = np.r_[edges[kept, 0], edges[kept, 1]]
    one = deg[inc_c] == 1
    add(inc_c[one], [f"rests on a single pair {pair(e)}: nothing checks it" for e in inc_e[one]])
    br = bridges(edges, n, kept)
    block = two_edge_blocks(edges, n, kept, br)
    in_core, path, n_path, comp, tied = _bridges_towards_core(edges, n, kept, br, block)
    size = np.bincount(block, minlength=int(block.max()) + 1)[block]
    # a lone camera's one pair is said above, unless the bridges beyond it are more
    cut = np.flatnonzero(cams & ~in_core & (path[:, 0] >= 0) & ((deg > 1) | (size > 1) | (n_path > 1)))
    add(cut, [_bridge_reason(path[k], int(n_path[k]), pair) for k in cut])
    add(*_minor_core(edges, n, kept, cams & in_core, comp, size, tied, pair))
    conf = np.bincount(edges[kept & confirmed].ravel(), minlength=n)
    unconf = np.flatnonzero(cams & (deg > 1) & (conf == 0) & cycles_checked)
    add(unconf, [f"none of its {deg[k]} pairs is in a consistent cycle: unconfirmed" for k in unconf])
    if confirm_deg is not None and cycles_checked:
        cd = np.asarray(confirm_deg, float)
        add(*_loose_reasons(edges, np.flatnonzero(kept & confirmed & (cd > confirm_max_deg)), cd, cams, pair,
                            confirm_max_deg))
    if bridged is not None and (kept & bridged).any():
        _flag_bridged(edges, n, kept, kept & np.asarray(bridged, bool), cams, comp, pair, add)
    rej = np.bincount(edges[np.asarray(inconsistent, bool)].ravel(), minlength=n)
    disputed = np.flatnonzero(cams & (rej > 0))
    add(disputed, [f"{rej[k]} of its {rej[k] + deg[k]} pairs disagree with the others and were rejected"
                   for k in disputed])
    n_comp = len(np.unique(comp[cams]))
    n_cycles = int(kept.sum()) - int(cams.sum()) + n_comp
    messages = [NO_CYCLE] if n_cycles == 0 else []
    if n_cycles and cycles_checked and not (kept & confirmed).any():
        messages.append("the view graph has cycles but none is consistent: no pair is confirmed")
    return GraphFlags(flags, br, messages, n_cycles)
