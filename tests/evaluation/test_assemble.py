"""pipeline.evaluation.assemble: what report.md, metrics.json and the console say of one run agree with each other.

Each test runs the evaluation, the report and metrics.json of a tiny run (4 cameras, rotation files written here,
the stages before stubbed), in a fraction of a second.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation import assemble
from pipeline.io.rotations import write_rotations
from pipeline.reference import Reference

NAMES = [f"v{k}.png" for k in range(4)]
EDGES = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [0, 2]])


def _strict(text: str) -> dict:
    """JSON as a strict reader reads it: NaN and Infinity are not JSON."""
    def bad(token: str) -> None:
        raise ValueError(f"{token} is not JSON")
    return json.loads(text, parse_constant=bad)


def _run(tmp_path: Path, monkeypatch, stats: dict[str, dict], intrinsics: dict | None = None, truth: bool = True,
         quiet: bool = False, left_out: dict[str, str] | None = None) -> tuple[str, dict, Path]:
    """Evaluate, report and write metrics.json for methods ``{label: stats}`` (each a small rotation error);
    returns report.md's text, metrics.json (read strictly) and the output folder."""
    rng = np.random.default_rng(1)
    R = so3.exp(rng.normal(size=(4, 3)))
    vg = ViewGraph.from_absolute(NAMES, R, EDGES)
    results = {}
    for k, (label, s) in enumerate(stats.items()):
        noisy = so3.exp(np.deg2rad(0.1 * (k + 1)) * rng.normal(size=(4, 3))) @ R
        path = write_rotations(tmp_path / "rotations" / f"{label}.txt", NAMES, noisy)
        results[label] = {"rotations": path, "stats": dict(s)}
    monkeypatch.setattr(assemble, "_intrinsics", lambda work: intrinsics or {})
    monkeypatch.setattr("pipeline.frontend.feature_stage.load_manifest", lambda work: {"names": list(NAMES)})
    plan = SimpleNamespace(out=tmp_path, work=tmp_path / "work", notes=["a note"], images=tmp_path / "images",
                           gt=None, K=None, quiet=quiet, truth=Reference(NAMES, R, label="truth") if truth else None,
                           run=SimpleNamespace(align="l2", plots=False, as_dict=lambda: {}))
    runner = SimpleNamespace(times={"features": 1.0}, reused={})
    ev = assemble.evaluate_run(plan, vg, results, None)
    assemble.write_report_md(plan, ev, [], results, vg, runner)
    path = assemble.write_metrics(plan, ev, vg, dict(left_out or {}), runner, 0.0)
    return (tmp_path / "report.md").read_text(), _strict(path.read_text()), tmp_path


def _report_notes(text: str) -> list[str]:
    notes = text.split("## Notes\n\n", 1)[1] if "## Notes" in text else ""
    return [ln[2:] for ln in notes.splitlines() if ln.startswith("- ")]


def test_metrics_json_is_strict_json_where_a_figure_is_not_a_number(tmp_path, monkeypatch) -> None:
    """A certificate's undefined eigenvalue and an estimate made from no pair are NaN in the stages' records:
    metrics.json writes them as null, which every JSON reader reads (NaN is not JSON)."""
    intr = {"focal": [{"source": "default", "n_images": 4, "median_px": 768.0, "min_px": 768.0, "max_px": 768.0}],
            "estimates": [{"n_images": 4, "focal": {"f": float("nan"), "sd_rel": float("inf"), "n_pairs": 0}}]}
    _, m, out = _run(tmp_path, monkeypatch, {"irls": {"certificate": {"lambda_nontrivial": float("nan")}}}, intr)
    assert m["methods"]["irls"]["certificate"]["lambda_nontrivial"] is None
    assert m["intrinsics"]["estimates"][0]["focal"] == {"f": None, "sd_rel": None, "n_pairs": 0}
    assert "NaN" not in (out / "metrics.json").read_text()


def test_the_report_has_every_note_of_metrics_json(tmp_path, monkeypatch) -> None:
    """The note that the focal lengths stayed the default guess was added after report.md was written: in
    metrics.json only."""
    per = {n: {"source": "default"} for n in NAMES}
    intr = {"focal": [{"source": "default", "n_images": 4, "median_px": 768.0, "min_px": 768.0, "max_px": 768.0}],
            "per_image": per}
    text, m, _ = _run(tmp_path, monkeypatch, {"irls": {}}, intr)
    assert any("default focal guess" in n for n in m["notes"])
    assert _report_notes(text) == m["notes"]


def test_a_poorly_determined_focal_is_evidence_against_the_rotations(tmp_path, monkeypatch) -> None:
    """temple without K: the focal estimated from the view graph had a jackknife sd of 37%; the intrinsics said so,
    but "Evidence" flagged only cameras with other reasons and, had there been none, would have said every
    rotation is checked."""
    graph = {"names": NAMES, "flags": {}, "messages": [], "left_out": {}, "pairs": [], "n_cycles": 2}
    monkeypatch.setattr("pipeline.graph.stage.load_graph_summary", lambda out: graph)
    intr = {"focal": [{"source": "estimated:profile+rotcons", "n_images": 4, "median_px": 1537.2, "min_px": 1537.2,
                       "max_px": 1537.2}],
            "estimates": [{"n_images": 4, "focal": {"f": 1537.2, "sd_rel": 0.374, "determined": False, "n_pairs": 5}}]}
    text, m, _ = _run(tmp_path, monkeypatch, {"irls": {}}, intr)
    msg = ("the focal length of 4 image(s) is poorly determined (1537.2 px, jackknife sd 37.4%): the averaged "
           "rotations rest on it and may be off by degrees with no inconsistency to show it")
    assert m["evidence"]["messages"] == [msg]
    ev = text.split("## Evidence behind the rotations", 1)[1].split("\n## ", 1)[0]
    assert f"**{msg}.**" in ev and "Every camera's rotation is checked" not in ev


def test_every_figure_of_metrics_json_has_its_unit_in_its_key_or_in_units(tmp_path, monkeypatch) -> None:
    """stages {"features": 4.13}, pct_below {"1": 62.5}, frobenius, mahalanobis: figures without a unit in their key,
    and no place in metrics.json that says it."""
    _, m, _ = _run(tmp_path, monkeypatch, {"irls": {}, "sdp": {}})
    units = m["units"]
    missing = set()

    def walk(o, key: str, parent: str) -> None:
        if isinstance(o, dict):
            for k, v in o.items():
                walk(v, str(k), key)
        elif isinstance(o, list):
            for v in o:
                walk(v, key, parent)
        elif isinstance(o, (int, float)) and not isinstance(o, bool) and parent != "units":
            if not (re.search(r"(_deg|_s|_px)$", key) or key.startswith("n_") or key in units or parent in units):
                missing.add(f"{parent}.{key}")

    walk({k: v for k, v in m.items() if k != "input"}, "", "")
    assert not missing
    assert {"stages", "pct_below", "pct_above", "frobenius", "mahalanobis"} <= set(units)
    assert "not an accuracy" in units["sigma_median_deg"]  # a predicted σ: said what it is where its unit is


def test_an_image_the_refinement_placed_is_not_called_unsolved(tmp_path, monkeypatch, capsys) -> None:
    """An image the view graph left out and the refinement placed: the console said it was not solved in this
    frame, and metrics.json's left_out_why gave only the view graph's reason, while the refined row scored it."""
    why = "placed by the refinement alone, from its 2 pair(s) the refined rotation confirms it"
    left = {"v9.png": "no accepted image pair", "v8.png": "no accepted image pair"}
    _, m, _ = _run(tmp_path, monkeypatch, {"x+refine": {"placed": {"v9.png": why}}}, left_out=left)
    out = capsys.readouterr().out
    (line,) = [ln for ln in out.splitlines() if "not solved" in ln]
    assert line.startswith("WARNING: 1 image(s) not solved in this frame: v8.png ")
    assert "v9.png" not in line and f"v9.png: {why} (x+refine)" in out
    assert m["input"]["left_out_why"]["v9.png"] == f"no accepted image pair; {why} (x+refine)"
