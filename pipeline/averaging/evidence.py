"""Every rotation carries its evidence: the edges that support it and what the certificate proves.

For each camera of a result: its edges in the solved graph, the edges the method kept
(the rest it rejected as outliers, or left a negligible weight), the share of its edge
weight on kept edges, and a verdict on its support:

- ``"redundant"``: two or more kept edges (an error in one shows in the others), and at least
  :data:`MINORITY_SHARE` of its edges;
- ``"minority"``: two or more kept edges, but fewer than :data:`MINORITY_SHARE` of its edges:
  most of its pairs disagree with the rotation (a camera matched mostly wrong, such as one the
  IRLS rescue moved to where its few right pairs agree: :mod:`pipeline.averaging.rescue`);
- ``"single edge"``: exactly one kept edge: the rotation is that edge's, unchecked;
- ``"rejected edges only"``: no kept edge: the rotation rests on rejected or
  low-weight evidence alone.

With them, the method's certificate statement (or why there is none): what it proves is
optimality for a cost on an edge set, never accuracy. Pure functions; vectorized.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.averaging.result import AveragingResult
from pipeline.core.names import positions
from pipeline.core.viewgraph import ViewGraph

__all__ = ["MINORITY_SHARE", "camera_evidence", "certificate_statement"]

#: Below this share of a camera's edges kept, its support is a "minority" (the rescue's suspect threshold).
MINORITY_SHARE = 0.25


def certificate_statement(res: AveragingResult) -> tuple[str, Any]:
    """The result's certificate statement and verdict, or a note that it has none."""
    cert = res.stats.get("certificate")
    if isinstance(cert, dict) and cert.get("statement"):
        return str(cert["statement"]), cert.get("verdict", cert.get("certified"))
    if "certified" in res.stats:
        return (("certified" if res.stats["certified"] else "NOT certified") + " (SDP on every edge: optimality "
                "for the least-squares cost on all edges, outliers included)"), bool(res.stats["certified"])
    return f"no certificate: {res.method} is a local method and reports none", None


def camera_evidence(vg: ViewGraph, res: AveragingResult) -> dict[str, Any]:
    """Per-camera support of ``res`` (module docstring), JSON-ready.

    Args:
        vg: the graph ``res.edge_index`` indexes (the input view graph).
        res: the result (``names`` the solved cameras, ``edge_index``, ``kept``, ``weights``).

    Returns:
        ``{"statement", "verdict", "edge_selection", "n_single_edge", "n_rejected_only", "n_minority",
        "cameras": [{"name", "n_edges", "n_kept", "kept_weight_share", "support"}]}``.
    """
    statement, verdict = certificate_statement(res)
    local = positions(res.names, vg.names, missing=-1)
    idx = np.arange(vg.n_edges) if res.edge_index is None else np.asarray(res.edge_index, dtype=np.int64)
    e = local[vg.edges[idx]]
    n = len(res.names)
    kept = np.ones(idx.size, bool) if res.kept is None else np.asarray(res.kept, dtype=bool)
    w = np.ones(idx.size) if res.weights is None else np.maximum(np.asarray(res.weights, dtype=np.float64), 0.0)
    ok = (e >= 0).all(axis=1)
    e, kept, w = e[ok], kept[ok], w[ok]
    ends = e.ravel()
    deg = np.bincount(ends, minlength=n)
    n_kept = np.bincount(ends, weights=np.repeat(kept, 2).astype(float), minlength=n).astype(int)
    w_all = np.bincount(ends, weights=np.repeat(w, 2), minlength=n)
    w_kept = np.bincount(ends, weights=np.repeat(w * kept, 2), minlength=n)
    share = np.where(w_all > 0, w_kept / np.where(w_all > 0, w_all, 1.0), 0.0)
    support = np.where(n_kept >= 2, np.where(n_kept >= MINORITY_SHARE * deg, "redundant", "minority"),
                       np.where(n_kept == 1, "single edge", "rejected edges only"))
    return {
        "statement": statement, "verdict": verdict,
        "edge_selection": "the method's kept edges" if res.kept is not None else "none reported (every edge counts)",
        "n_single_edge": int(np.sum(n_kept == 1)), "n_rejected_only": int(np.sum(n_kept == 0)),
        "n_minority": int(np.sum(support == "minority")),
        "cameras": [{"name": name, "n_edges": int(d), "n_kept": int(k), "kept_weight_share": round(float(s), 6),
                     "support": str(sup)} for name, d, k, s, sup in zip(res.names, deg, n_kept, share, support)],
    }
