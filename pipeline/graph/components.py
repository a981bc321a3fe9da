"""Connected components of a view graph: why each image outside the largest one is left out, and the other
components solved in folders of their own (OUT/component-k/, each in its own frame)."""

from __future__ import annotations

import re
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.graph.flags import NO_CYCLE

__all__ = ["left_out_reasons", "other_components", "write_component", "remove_stale_components", "COMPONENT_DIR"]

#: The folder of the k-th component (k >= 2) in OUT.
COMPONENT_DIR = "component-{k}"


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


def other_components(kept: ViewGraph, max_components: int, min_images: int) -> list[np.ndarray]:
    """Camera indices (into ``kept``) of the components after the largest that are solved: at least ``min_images``
    images each, largest first, up to ``max_components`` components in all (the largest included)."""
    labels = kept.components()
    sizes = np.bincount(labels)
    take = [c for c in range(1, sizes.size) if sizes[c] >= min_images][:max(max_components - 1, 0)]
    return [np.flatnonzero(labels == c) for c in take]


def write_component(folder: Path, k: int, sub: ViewGraph, summary: dict[str, Any], graph_file: str,
                    summary_file: str) -> tuple[list[Path], dict[str, Any]]:
    """Write the k-th component's view graph and its summary (the main summary's format, for its cameras) into
    ``folder/component-k/``; returns the paths and the entry the main summary lists it by."""
    d = Path(folder) / COMPONENT_DIR.format(k=k)
    d.mkdir(parents=True, exist_ok=True)
    names = set(sub.names)
    n_cycles = max(sub.n_edges - sub.n_cameras + 1, 0)  # independent cycles of a connected graph
    s = {"n_images": summary["n_images"], "n_cameras": sub.n_cameras, "n_edges": sub.n_edges,
         "names": list(sub.names), "left_out": {}, "flags": {n: w for n, w in summary["flags"].items() if n in names},
         "messages": [NO_CYCLE] if n_cycles == 0 else [], "n_cycles": n_cycles, "component": k,
         "checks": summary["checks"], "pairs": [r for r in summary["pairs"] if set(r.get("pair", [])) <= names]}
    paths = [sub.save(d / graph_file), write_json(d / summary_file, s)]
    return paths, {"component": k, "folder": d.name, "n_cameras": sub.n_cameras, "n_edges": sub.n_edges,
                   "names": list(sub.names)}


def remove_stale_components(folder: Path, keep: int) -> None:
    """Remove the ``component-k`` folders of an earlier run with k > ``keep`` (its components are gone)."""
    for d in Path(folder).glob("component-*"):
        m = re.fullmatch(r"component-(\d+)", d.name)
        if d.is_dir() and m and int(m.group(1)) > keep and (d / "viewgraph.json").is_file():  # ours, not a user's
            shutil.rmtree(d)
