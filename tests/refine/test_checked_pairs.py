"""pipeline.refine.stage._checked_pairs: the pairs matched as index keys give the same graph as the name-pair set
looked up per edge (the definition here), on random graphs, summaries and edge cases."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import CacheError
from pipeline.core.viewgraph import ViewGraph
from pipeline.graph.stage import SUMMARY, load_graph_summary
from pipeline.refine.stage import _checked_pairs


def _reference(vg, graph, weak=True):
    """The selection before: a set of kept name pairs, each edge looked up in both orientations."""
    if graph is None or not Path(graph).is_file():
        return vg
    g = ViewGraph.load(graph, allow_isolated=True)
    kept = {(g.names[a], g.names[b]) for a, b in g.edges.tolist()}
    if weak and (Path(graph).parent / SUMMARY).is_file():
        rows = load_graph_summary(Path(graph).parent).get("pairs", [])
        try:
            kept |= {(str(r["pair"][0]), str(r["pair"][1])) for r in rows
                     if r.get("tracks") is True and r.get("status") == "rejected"}
        except (TypeError, KeyError, IndexError, AttributeError):
            raise CacheError("malformed pairs") from None
    keep = np.array([(vg.names[a], vg.names[b]) in kept or (vg.names[b], vg.names[a]) in kept
                     for a, b in vg.edges.tolist()], bool)
    return ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], H=vg.H[keep],
                     inliers=None if vg.inliers is None else vg.inliers[keep],
                     stats={k: np.asarray(v)[keep] for k, v in vg.stats.items()}, allow_isolated=True)


def _ba_graph(rng, n, p):
    E = np.stack(np.triu_indices(n, 1), 1)
    E = E[rng.random(len(E)) < p]
    M = len(E)
    return ViewGraph([f"im{k:03d}.jpg" for k in range(n)], E, so3.random_rotations(M, rng),
                     H=np.tile(np.eye(3), (M, 1, 1)) * rng.uniform(1, 2, (M, 1, 1)), inliers=rng.integers(20, 900, M),
                     stats={"t": rng.standard_normal((M, 3)), "ba_rms_px": rng.uniform(0, 1, M)}, allow_isolated=True)


def _write(folder: Path, vg, kept_share, rng, rows=None, drop_names=0, extra_names=0):
    """The checked graph (a random share of vg's pairs, its cameras shuffled, some of vg's missing and some others
    added) and its summary (rejected rows, some with tracks, some naming cameras vg does not have)."""
    folder.mkdir()
    k = rng.random(vg.n_edges) < kept_share
    names = [n for n in vg.names if rng.random() >= drop_names / max(len(vg.names), 1)] + [
        f"other{k}.jpg" for k in range(extra_names)]
    names = [names[i] for i in rng.permutation(len(names))]
    pos = {n: i for i, n in enumerate(names)}
    e = [(pos[vg.names[a]], pos[vg.names[b]]) for a, b in vg.edges[k].tolist()
         if vg.names[a] in pos and vg.names[b] in pos]
    if extra_names >= 2:
        e.append((pos["other0.jpg"], pos["other1.jpg"]))
    E = np.sort(np.array(e, np.int64).reshape(-1, 2), axis=1)
    ViewGraph(names, E, so3.random_rotations(len(E), rng), allow_isolated=True).save(folder / "viewgraph.npz")
    if rows is None:
        rows = [{"pair": [vg.names[a], vg.names[b]][::int(rng.choice([1, -1]))], "status": "rejected",
                 "step": "acceptance", "tracks": bool(rng.random() < 0.5)} for a, b in vg.edges[~k].tolist()]
        rows += [{"pair": ["other3.jpg", vg.names[0]], "status": "rejected", "tracks": True}] if vg.names else []
        rows += [{"pair": [vg.names[a], vg.names[b]], "status": "kept", "tracks": True} for a, b in
                 vg.edges[k][:3].tolist()]
    (folder / SUMMARY).write_text(json.dumps({"names": names, "left_out": {}, "n_cameras": len(names),
                                              "n_edges": len(E), "pairs": rows}))
    return folder / "viewgraph.npz"


def _same(vg, path, weak=True):
    got, want = _checked_pairs(vg, path, weak), _reference(vg, path, weak)
    assert got.names == want.names
    for f in ("edges", "R_rel", "H", "inliers"):
        assert np.array_equal(getattr(got, f), getattr(want, f)), f
    assert got.stats.keys() == want.stats.keys() and all(np.array_equal(got.stats[s], want.stats[s]) for s in got.stats)
    return got


@pytest.mark.parametrize("seed", range(8))
def test_random_graphs_and_summaries(tmp_path, seed):
    rng = np.random.default_rng(seed)
    vg = _ba_graph(rng, int(rng.integers(2, 30)), rng.uniform(0.1, 0.9))
    path = _write(tmp_path / "out", vg, rng.uniform(0, 1), rng, drop_names=int(rng.integers(0, 4)),
                  extra_names=int(rng.integers(0, 4)))
    for weak in (True, False):
        _same(vg, path, weak)


def test_edge_cases(tmp_path):
    rng = np.random.default_rng(1)
    vg = _ba_graph(rng, 6, 0.6)
    assert _checked_pairs(vg, None) is vg and _checked_pairs(vg, tmp_path / "absent.npz") is vg
    _same(vg, _write(tmp_path / "nothing", vg, 0.0, rng, rows=[]))  # nothing kept, no weak rows
    _same(vg, _write(tmp_path / "all", vg, 1.0, rng))
    one = _ba_graph(rng, 2, 1.0)  # one pair, kept reversed (the checked graph's cameras are shuffled)
    _same(one, _write(tmp_path / "one", one, 1.0, rng))
    weak_only = [{"pair": [vg.names[b], vg.names[a]], "status": "rejected", "tracks": True}
                 for a, b in vg.edges.tolist()] * 2  # every pair twice, reversed
    assert _same(vg, _write(tmp_path / "dup", vg, 0.0, rng, rows=weak_only)).n_edges == vg.n_edges
    empty = ViewGraph(vg.names, np.zeros((0, 2), np.int64), np.zeros((0, 3, 3)), H=np.zeros((0, 3, 3)),
                      allow_isolated=True)
    _same(empty, _write(tmp_path / "empty", empty, 1.0, rng))


@pytest.mark.parametrize("row", [{"pair": [], "status": "rejected", "tracks": True}, ["a", "b"],
                                 {"status": "rejected", "tracks": True}])
def test_malformed_rows_are_still_an_error(tmp_path, row):
    rng = np.random.default_rng(2)
    vg = _ba_graph(rng, 5, 0.8)
    path = _write(tmp_path / "bad", vg, 0.5, rng, rows=[row])
    with pytest.raises(CacheError):
        _checked_pairs(vg, path)
