"""The view-graph stage end to end: wrong but well-supported pairs injected into rendered scenes, a cycle-free graph.

Issue 13, acceptance 4: a static second object on a turntable and a repeated structure
make pairs that match well and are wrong; each is rejected or down-weighted, and every
reported camera is within 1° of the truth or flagged. A graph without cycles is flagged.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import CacheError
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.graph.flags import NO_CYCLE
from pipeline.graph.stage import load_graph_summary
from pipeline.io.rotations import read_rotations
from pipeline.run import main
from pipeline.synthetic.injected import render_repeated, render_turntable_with_static
from pipeline.synthetic.lowtex import write_scene
from pipeline.synthetic.render import SceneConfig, render_scene


def _run(tmp_path, folder, pairs: list[tuple[str, str]] | str, methods="irls, irls-h, sdp"):
    tmp_path.mkdir(exist_ok=True)
    pf = pairs
    if not isinstance(pairs, str):
        pf = tmp_path / "pairs.txt"
        pf.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    cfg = tmp_path / "config.yaml"
    cfg.write_text(f"matching:\n  pairs: {pf}\nrun:\n  plots: false\n  methods: [{methods}]\n")
    return json.loads(main(folder, tmp_path / "out", cfg, gt=folder / "cameras.txt", reference=False,
                           quiet=True).read_text())


@pytest.mark.slow
@pytest.mark.parametrize("render", [render_turntable_with_static, render_repeated], ids=["static", "repeated"])
def test_injected_wrong_pairs_are_rejected_and_no_camera_is_silently_off(tmp_path, render):
    scene = render()
    folder = tmp_path / "scene"
    write_scene(scene, folder)
    n = scene.names
    injected = [(n[a], n[b]) for a, b in scene.info["injected"]]
    assert len(injected) >= 3
    m = _run(tmp_path, folder, [(n[a], n[b]) for a, b in scene.true_pairs] + injected)
    fate = {tuple(p["pair"]): p for p in load_graph_summary(tmp_path / "out")["pairs"]}
    ba_rows = [p for p in fate.values() if "confirmed" in p]  # the pairs of the BA graph: how closely each is checked
    assert all((p["confirm_deg"] is not None) == (p["status"] == "kept" and p["confirmed"]) for p in ba_rows)
    assert any(p["confirm_deg"] is not None for p in ba_rows) and all(
        0 <= p["confirm_deg"] <= 15 for p in ba_rows if p["confirm_deg"] is not None)  # a cycle's or a path's bound
    vg = ViewGraph.load(tmp_path / "out" / "viewgraph.npz")
    measured = {(vg.names[i], vg.names[j]): (R, scene.R[n.index(vg.names[j])] @ scene.R[n.index(vg.names[i])].T)
                for (i, j), R in zip(vg.edges, vg.R_rel)}
    n_kept_right = 0
    for pair in injected:
        p = fate[pair]
        if p["status"] != "kept":
            assert p["reason"], pair
            continue
        # kept: either its rotation is the true one (the zero-motion test removed the static matches and the
        # object's own matches gave the true motion: no longer a wrong pair), or it has negligible weight
        if rotation_errors_deg(measured[pair][0][None], measured[pair][1][None])[0] < 2.0:
            n_kept_right += 1
            continue
        for label in m["methods"]:
            low = {(e["i"], e["j"]): e["relative_weight"] for e in m["methods"][label]["most_downweighted_edges"]}
            assert low.get(pair, 1.0) < 0.05, (pair, label)
    assert n_kept_right < len(injected), "every injected pair was kept: the scene no longer injects anything wrong"
    flagged = set(m["evidence"]["flags"])
    for label, err in _errors(tmp_path, scene, m).items():
        off = {x for x, e in err.items() if e > 1.0}
        assert off <= flagged, (label, {x: err[x] for x in off - flagged})
        assert np.median(list(err.values())) < 0.5 and len(err) >= 12, label


def _errors(run: Path, scene, m: dict) -> dict[str, dict[str, float]]:
    """Each method's error against the truth (degrees), per camera."""
    out = {}
    for label in m["methods"]:
        names, R = read_rotations(run / "out" / "rotations" / f"{label}.txt")
        out[label] = dict(zip(names, rotation_errors_deg(R, scene.R[[scene.names.index(x) for x in names]])))
    return out


@pytest.mark.slow
def test_a_cycle_free_graph_says_its_result_cannot_be_verified(tmp_path):
    folder = tmp_path / "scene"
    render_scene(n_views=4, seed=3, out=folder, config=SceneConfig(width=320, height=240, focal=280.0,
                                                                   texture_px_per_unit=150.0))
    m = _run(tmp_path, folder, "sequential:1", methods="irls, sdp")
    ev = m["evidence"]
    assert ev["messages"][0] == NO_CYCLE and ev["n_cycles"] == 0
    assert set(ev["flags"]) == {f"view_{k:03d}.png" for k in range(4)}  # every camera: single pair or bridge
    assert all(any("single pair" in w or "bridge pair" in w for w in v) for v in ev["flags"].values())
    report = (tmp_path / "out" / "report.md").read_text()
    assert "cannot be verified" in report and "it does not check that those pairs are right" in report
    s = load_graph_summary(tmp_path / "out")
    assert s["n_cycles"] == 0 and s["n_bridges"] == 3
    assert all(p["confirm_deg"] is None for p in s["pairs"] if "confirmed" in p)  # nothing confirms a pair of a tree
    (tmp_path / "out" / "viewgraph.json").write_text("{not json")
    with pytest.raises(CacheError, match="viewgraph.json"):
        load_graph_summary(tmp_path / "out")


def test_command_help():
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "pipeline.viewgraph", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--min-inliers" in r.stdout and "--work" in r.stdout


def test_command_without_a_front_end_fails_in_one_line(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "pipeline.viewgraph", "--work", str(tmp_path), "--out", str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("error:"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "two_view" in r.stderr


def test_the_other_components_are_chosen_largest_first_and_stale_ones_removed(tmp_path):
    """other_components: every component after the largest with at least min_images images, largest first, up to
    max_components in all; remove_stale_components removes only this stage's folders of components now gone."""
    from pipeline.graph.components import other_components, remove_stale_components

    def chain(start: int, n: int) -> list[tuple[int, int]]:
        return [(start + k, start + k + 1) for k in range(n - 1)]

    sizes = (6, 2, 5, 3, 4)  # components of these many cameras, 20 cameras in all
    starts = np.cumsum((0,) + sizes[:-1])
    edges = np.array([e for s, n in zip(starts, sizes) for e in chain(int(s), n)])
    names = [f"c{k:02d}" for k in range(20)]
    vg = ViewGraph.from_absolute(names, np.tile(np.eye(3), (20, 1, 1)), edges)
    got = other_components(vg, max_components=8, min_images=3)
    assert [sorted(vg.names[i] for i in c) for c in got] == [names[8:13], names[16:20], names[13:16]]
    assert len(other_components(vg, max_components=2, min_images=3)) == 1  # the largest and the next one
    assert other_components(vg, max_components=1, min_images=3) == []
    assert len(other_components(vg, max_components=8, min_images=2)) == 4  # the pair too
    for k in (2, 3, 4):
        (tmp_path / f"component-{k}").mkdir()
        (tmp_path / f"component-{k}" / "viewgraph.json").write_text("{}")
    (tmp_path / "component-5").mkdir()  # not this stage's: no summary in it
    remove_stale_components(tmp_path, keep=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["component-2", "component-5"]
    # a component written with its images' flags and pairs; a chain (no cycle) says its result cannot be checked
    from pipeline.graph.components import write_component

    main = {"n_images": 20, "flags": {"c08": ["x"], "c00": ["y"]}, "checks": {},
            "pairs": [{"pair": ["c08", "c09"]}, {"pair": ["c00", "c01"]}, {"pair": ["c12", "c13"]}]}  # in, out, across
    paths, entry = write_component(tmp_path, 2, vg.subgraph(got[0])[0], main, "viewgraph.npz", "viewgraph.json")
    summary = load_graph_summary(tmp_path / "component-2")
    assert entry["folder"] == "component-2" and summary["names"] == names[8:13] == entry["names"]
    assert summary["flags"] == {"c08": ["x"]} and [r["pair"] for r in summary["pairs"]] == [["c08", "c09"]]
    assert summary["n_cycles"] == 0 and summary["messages"] == [NO_CYCLE] and summary["component"] == 2
    assert list(ViewGraph.load(paths[0]).names) == names[8:13]
