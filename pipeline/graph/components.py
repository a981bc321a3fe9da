"""Connected components of a view graph and why each image outside the largest one is left out."""

from __future__ import annotations

from collections import Counter

import numpy as np

from pipeline.core.viewgraph import ViewGraph

__all__ = ["left_out_reasons"]


def left_out_reasons(vg_all: ViewGraph, rejected: list[dict]) -> dict[str, str]:
    """``{name: why}`` for each camera outside the largest connected component of ``vg_all``.

    Args:
        vg_all: the view graph of every image (isolated cameras allowed).
        rejected: the two-view stage's rejected pairs (``{"names": [a, b], "reason": ...}``).
    """
    labels = vg_all.components()
    deg = vg_all.degrees()
    sizes = np.bincount(labels)
    by_image: dict[str, list[str]] = {}
    for r in rejected:
        for nm in r.get("names", []):
            by_image.setdefault(str(nm), []).append(str(r.get("reason", "?")))
    reasons: dict[str, str] = {}
    for k in np.flatnonzero(labels != 0):  # one line per left-out image
        nm = vg_all.names[k]
        if deg[k] == 0:
            why = by_image.get(nm, [])
            common = ", ".join(f"{w} ×{c}" for w, c in Counter(w.split(" (")[0] for w in why).most_common(3))
            reasons[nm] = (f"no accepted image pair ({len(why)} pair(s) rejected: {common})"
                           if why else "no accepted image pair (no match with any image)")
        else:
            others = [vg_all.names[j] for j in np.flatnonzero(labels == labels[k]) if j != k]
            reasons[nm] = (f"in another connected component of {sizes[labels[k]]} images "
                           f"(with {', '.join(others[:5])}{'...' if len(others) > 5 else ''}), not linked to the largest")
    return reasons
