"""The stage contract at the run level (issue 12, acceptance item 4).

Work is counted where it is done: each stage's kernel (SIFT per image, matching,
RANSAC and BA per pair, the view graph, each averaging solve) is wrapped by a
counter, and every record and output is compared byte for byte. So:

- a runtime option (``workers``, ``chunk_size``, progress) recomputes nothing;
- a result-affecting option recomputes exactly the stages downstream of it;
- a damaged cached result is recomputed by a plain re-run, with a warning, and
  nothing else is: the stages after it are still up to date.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline import run  # noqa: E402

STAGES = ("features", "matching", "two_view", "two_view_ba", "viewgraph", "averaging")
RECORDS = {"features": "work/features.record.json", "matching": "work/matching.record.json",
           "two_view": "work/two_view.record.json", "two_view_ba": "work/two_view_ba.record.json",
           "viewgraph": "viewgraph.record.json", "averaging": "rotations/irls-l0.5.record.json"}


@pytest.fixture
def work_done(monkeypatch) -> dict[str, int]:
    """``{stage: items computed}``, counted in each stage's kernel."""
    import pipeline.averaging.stage as avs
    import pipeline.frontend.feature_stage as fs
    import pipeline.frontend.matching_stage as ms
    import pipeline.geometry.ba_stage as ba
    import pipeline.geometry.two_view_stage as tv
    import pipeline.graph.stage as gs

    counts = dict.fromkeys(STAGES, 0)

    def count(stage: str, fn, size=lambda *a, **k: 1):
        def wrapped(*a, **k):
            counts[stage] += size(*a, **k)
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(fs, "_extract_task", count("features", fs._extract_task))
    monkeypatch.setattr(ms, "_match_chunk", count("matching", ms._match_chunk, lambda args: len(args[0])))
    monkeypatch.setattr(tv, "_estimate_chunk", count("two_view", tv._estimate_chunk, lambda tasks, **k: len(tasks)))
    monkeypatch.setattr(ba, "_refine_chunk", count("two_view_ba", ba._refine_chunk, lambda tasks, **k: len(tasks)))
    monkeypatch.setattr(gs.ViewGraphStage, "compute", count("viewgraph", gs.ViewGraphStage.compute))
    # the averaging stage's solves (the view-graph checks run IRLS too: that is the view graph's work)
    monkeypatch.setattr(avs.AveragingStage, "compute", count("averaging", avs.AveragingStage.compute))
    return counts


def _rerun(out: Path, tiny_scene: Path, tiny_config: Path, tmp_path: Path, **changes: dict) -> None:
    cfg = yaml.safe_load(tiny_config.read_text())
    for section, opts in changes.items():
        cfg.setdefault(section, {}).update(opts)
    path = tmp_path / "changed.yaml"
    path.write_text(yaml.safe_dump(cfg))
    run.main(tiny_scene, out, config=path, gt=tiny_scene / "cameras.txt", quiet=True, reference=False)


def _snapshot(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in ("metrics.json", "report.md")}  # these carry this run's timings


def _recomputed(before: dict[str, bytes], out: Path) -> set[str]:
    after = _snapshot(out)
    return {stage for stage, rec in RECORDS.items() if before.get(rec) != after.get(rec)}


def test_runtime_options_recompute_nothing(run_copy, tiny_scene, tiny_config, tmp_path, work_done):
    before = _snapshot(run_copy)
    _rerun(run_copy, tiny_scene, tiny_config, tmp_path, features={"workers": 3},
           matching={"workers": 3, "chunk_size": 2}, two_view={"workers": 2, "chunk_size": 1, "progress": True},
           two_view_ba={"workers": 2, "chunk_size": 3}, reference={"num_threads": 1})
    assert work_done == dict.fromkeys(STAGES, 0)
    assert _snapshot(run_copy) == before, "not one output or record was rewritten"


@pytest.mark.slow
@pytest.mark.parametrize("section,option,first", [
    ("matching", {"ratio": 0.75}, "matching"),
    ("two_view", {"threshold_px": 1.5}, "two_view"),
    ("two_view_ba", {"loss": "huber"}, "two_view_ba"),
    ("averaging", {"alpha_deg": 4.0}, "averaging"),
], ids=["matching.ratio", "two_view.threshold_px", "two_view_ba.loss", "averaging.alpha_deg"])
def test_an_option_recomputes_exactly_the_stages_after_it(run_copy, baseline, tiny_scene, tiny_config, tmp_path,
                                                          work_done, section, option, first):
    before = _snapshot(run_copy)
    _rerun(run_copy, tiny_scene, tiny_config, tmp_path, **{section: option})
    downstream = set(STAGES[STAGES.index(first):])
    assert _recomputed(before, run_copy) == downstream
    n_pairs = 15  # 6 views, every pair matched
    expected = {"features": 0, "matching": n_pairs if first == "matching" else 0}
    for stage in STAGES[2:]:
        if stage not in downstream:
            expected[stage] = 0
    got = {k: v for k, v in work_done.items() if k in expected}
    assert got == expected, work_done
    for stage in downstream - {"matching"}:
        assert work_done[stage] > 0, (stage, work_done)
    if first == "matching":
        assert work_done["two_view"] == n_pairs  # every pair's matches changed


# (file in OUT, damage, the stage whose result it is)
DAMAGES = [
    ("rotations/irls-l0.5.txt", "cut-to-2-cameras", "averaging"),
    ("viewgraph.npz", "truncate", "viewgraph"),
    ("work/viewgraph.npz", "truncate", "two_view_ba"),
    ("work/two_view.npz", "truncate", "two_view"),
    ("work/two_view_corr.npz", "garble", "two_view"),
    ("work/matches/chunk-*.npz", "truncate", "matching"),
    ("work/matches.json", "garble", "matching"),
    ("work/features/chunk-*.npz", "garble", "features"),
    ("work/features/index.json", "garble", "features"),
    ("work/two_view_ba.record.json", "garble", "two_view_ba"),
]


def _damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "truncate":
        del data[len(data) // 2:]
    elif how == "garble":  # same size: only the content can tell
        mid = len(data) // 2
        data[mid:mid + 8] = b"\x00\xff" * 4
    else:
        lines = data.decode().splitlines()
        cams = [ln for ln in lines if not ln.startswith("#")]
        data = bytearray("\n".join([ln for ln in lines if ln.startswith("#")] + cams[:2]).encode() + b"\n")
    path.write_bytes(bytes(data))


@pytest.mark.slow
@pytest.mark.parametrize("rel,how,stage", DAMAGES, ids=[f"{r}-{h}" for r, h, _ in DAMAGES])
def test_a_damaged_result_is_recomputed_alone_by_a_plain_rerun(run_copy, baseline, tiny_scene, tiny_config, tmp_path,
                                                                 work_done, caplog, rel, how, stage):
    path = sorted(run_copy.glob(rel))[0]
    _damage(path, how)
    before = _snapshot(run_copy)
    with caplog.at_level(logging.WARNING):
        _rerun(run_copy, tiny_scene, tiny_config, tmp_path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert warnings and all("\n" not in w for w in warnings) and any(path.name in w for w in warnings), warnings
    assert _recomputed(before, run_copy) == {stage}, "the damaged stage, and only it, runs again"
    per_item = {"features", "matching", "two_view", "two_view_ba"}
    if stage in per_item and "chunk-" not in path.name:
        assert work_done[stage] == 0, "its items came from the item store"
    if "chunk-" in path.name:
        assert work_done[stage] > 0, "the damaged chunk's items are computed again, not read"
    repaired, reference = path.read_bytes(), (baseline / path.relative_to(run_copy)).read_bytes()
    if path.suffix == ".json" and (path.name.endswith(".record.json") or path.name == "matches.json"):
        json.loads(repaired)  # these carry this run's counts and timings: valid again, not byte-equal
    else:
        assert repaired == reference, f"{rel} is written again as the undamaged run wrote it"
    assert sum(v for k, v in work_done.items() if k != stage) == 0, work_done
    for rel_out in ("rotations/irls-l0.5.txt", "viewgraph.npz", "work/viewgraph.npz"):
        assert (run_copy / rel_out).read_bytes() == (baseline / rel_out).read_bytes(), rel_out
    np.testing.assert_equal(sorted(p.name for p in run_copy.rglob("*")), sorted(p.name for p in baseline.rglob("*")))
