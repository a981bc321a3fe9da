"""Tests of run.py: the whole chain, stage-by-stage equivalence, resuming, interruption."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline.core.errors import ConfigError, PipelineError  # noqa: E402
from pipeline.io.rotations import read_rotations  # noqa: E402
from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SMALL = SceneConfig(width=320, height=240, focal=280.0, supersample=1)




from pipeline import run  # noqa: E402


@pytest.fixture(scope="session")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene")
    render_scene(6, 0, out, config=SMALL)
    return out


@pytest.fixture(scope="session")
def full_run(scene, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("full")
    run.main(scene, out, gt=scene / "cameras.txt", quiet=True)
    return out


@pytest.mark.slow
def test_full_run_metrics_and_report(full_run):
    m = json.loads((full_run / "metrics.json").read_text())
    assert set(m) >= {"methods", "edges", "pycolmap", "stages"}
    from pipeline.averaging.colmap_ra import have_pycolmap  # issue 15: COLMAP's averaging runs beside ours

    colmap = {"colmap-ra"} if have_pycolmap() else set()
    # H present, N=6 <= sdp_max_n; the refinement of the recommended start, on by default
    assert set(m["methods"]) == {"irls-l0.5", "irls-h-l0.5", "sdp-cso3", "irls-h-l0.5+refine"} | colmap
    irls = m["methods"]["irls-l0.5"]
    assert irls["reference"] == "truth" and irls["n_evaluated"] == 6
    assert irls["median_deg"] < 0.3, irls
    assert set(irls["references"]) == {"truth", "pycolmap", "glomap"}
    for k in ("mean_deg", "rms_deg", "max_deg", "frobenius", "pct_below", "time_s"):
        assert k in irls
    assert m["methods"]["irls-h-l0.5"]["median_deg"] < 0.3
    assert m["methods"]["irls-l0.5"]["error_vs_time"][-1]["final"]  # calibrated IRLS-H has no single iteration path
    sdp = m["methods"]["sdp-cso3"]
    assert "certified" in sdp and "rank" in sdp and sdp["median_deg"] < 0.5
    for tag in ("ransac", "ba"):
        e = m["edges"][tag]
        assert set(e) >= {"median_deg", "mean_deg", "rms_deg", "pct_above"}
        assert set(e["pct_above"]) == {"10", "30", "60", "90"}
    assert m["pairs"]["selector"] == "exhaustive" and m["pairs"]["auto"]  # 6 images <= exhaustive_max_images
    assert m["pairs"]["n_pairs"] == m["pairs"]["n_exhaustive"] == 15 and m["pairs"]["fraction"] == 1.0
    p = m["pycolmap"]
    assert p["n_registered"] == 6 and p["median_deg"] < 0.5 and p["time_s"] > 0
    g = m["peers"]["glomap"]  # GLOMAP scored as the incremental peer: against the truth and against it
    assert g["n_registered"] == 6 and g["median_deg"] < 0.5 and g["time_s"] > 0
    assert g["references"]["pycolmap"]["n_evaluated"] == 6 and m["peers"]["pycolmap"]["references"]["glomap"]
    r = m["methods"]["irls-h-l0.5+refine"]
    assert r["status"] == "ok" and r["n_refined"] == 6 and r["median_deg"] < 0.3 and r["sigma_median_deg"] > 0
    assert set(r["references"]) == {"truth", "pycolmap", "glomap"}
    assert set(m["stages"]) >= {"features", "matching", "two_view", "two_view_ba", "viewgraph", "averaging",
                                "refine", "reference", "global_reference", "evaluation", "report"}
    text = (full_run / "report.md").read_text()
    assert "## Against truth" in text and "## Against pycolmap" in text and "## Against glomap" in text
    assert "## Refinement (irls-h-l0.5+refine)" in text and "| pycolmap (global, GLOMAP) |" in text
    for png in ("errors_truth.png", "edge_errors_truth.png", "errors_pycolmap.png"):
        assert (full_run / png).is_file(), png
    assert list(full_run.glob("viewgraph_*.png"))


@pytest.mark.slow
def test_every_json_file_of_a_run_is_strict_json(full_run, strict_json):
    """jq, JavaScript, Go and serde refuse NaN and Infinity: every JSON file of a run (metrics.json, the stages'
    records and stats, the front end's manifests) is strict JSON, a figure that is not finite written as null (here
    at least one: IRLS-ℓ½'s verified certificate has no non-trivial eigenvalue to give, NaN in memory)."""
    files = sorted(full_run.rglob("*.json"))
    assert {"metrics.json", "rotations/irls-l0.5.json", "work/cameras.json", "work/features.record.json"} <= {
        str(f.relative_to(full_run)) for f in files}
    bad = []
    for f in files:
        try:
            strict_json(f.read_text(encoding="utf-8"))
        except ValueError as exc:
            bad.append(f"{f.relative_to(full_run)}: {exc}")
    assert not bad, bad
    stats = json.loads((full_run / "rotations" / "irls-l0.5.json").read_text())
    assert stats["certificate"]["verdict"] == "verified" and stats["certificate"]["lambda_nontrivial"] is None


@pytest.mark.slow
def test_stage_scripts_give_the_same_result(scene, full_run, tmp_path):
    """features → matching → two_view → two_view_ba → viewgraph → average by their commands equals run.py."""
    work = tmp_path / "work"
    py = sys.executable
    cmds = [
        [py, "-m", "pipeline.features", "--images", str(scene), "--work", str(work)],
        [py, "-m", "pipeline.matching", "--work", str(work)],
        [py, "-m", "pipeline.two_view", "--work", str(work)],
        [py, "-m", "pipeline.two_view_ba", "--work", str(work)],
        [py, "-m", "pipeline.viewgraph", "--work", str(work), "--out", str(tmp_path)],
        [py, "-m", "pipeline.average", str(tmp_path / "viewgraph.npz"), "--method", "irls", "--loss", "l0.5",
         "--out", str(tmp_path / "irls.txt")],
    ]
    for c in cmds:
        r = subprocess.run(c + ["-q"], capture_output=True, text=True)
        assert r.returncode == 0, (c, r.stderr)
    n1, R1 = read_rotations(tmp_path / "irls.txt")
    n2, R2 = read_rotations(full_run / "rotations" / "irls-l0.5.txt")
    assert list(n1) == list(n2)
    np.testing.assert_allclose(R1, R2, atol=1e-8)


@pytest.mark.slow
def test_second_run_reuses_every_stage(scene, full_run, monkeypatch):
    import pycolmap

    from pipeline.averaging import solve as average
    from pipeline.frontend import feature_stage
    from pipeline.geometry.ba_stage import TwoViewBAStage

    calls = {"sift": 0, "ba": 0, "avg": 0, "colmap": 0}

    def count(key, fn):
        def wrapped(*a, **k):
            calls[key] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(feature_stage, "extract_sift_adaptive", count("sift", feature_stage.extract_sift_adaptive))
    monkeypatch.setattr(TwoViewBAStage, "compute", count("ba", TwoViewBAStage.compute))
    monkeypatch.setattr(average, "average", count("avg", average.average))
    monkeypatch.setattr(pycolmap, "extract_features", count("colmap", pycolmap.extract_features))
    monkeypatch.setattr(pycolmap, "incremental_mapping", count("colmap", pycolmap.incremental_mapping))
    monkeypatch.setattr(pycolmap, "global_mapping", count("colmap", pycolmap.global_mapping))
    monkeypatch.setattr(pycolmap, "run_global_positioning", count("colmap", pycolmap.run_global_positioning))
    before = json.loads((full_run / "metrics.json").read_text())
    run.main(scene, full_run, gt=scene / "cameras.txt", quiet=True)
    assert calls == {"sift": 0, "ba": 0, "avg": 0, "colmap": 0}
    after = json.loads((full_run / "metrics.json").read_text())
    for stage in ("features", "matching", "two_view", "two_view_ba", "averaging", "refine", "reference",
                  "global_reference"):
        assert after["stages_reused"][stage], stage  # the averaging methods, the refinement and GLOMAP too
    assert after["methods"]["irls-h-l0.5+refine"]["median_deg"] == before["methods"]["irls-h-l0.5+refine"]["median_deg"]
    assert after["methods"]["irls-l0.5"]["median_deg"] == before["methods"]["irls-l0.5"]["median_deg"]


@pytest.mark.slow
@pytest.mark.parametrize("where", ["features", "two_view_ba"])
def test_interrupted_then_rerun_equals_uninterrupted(scene, full_run, fast_config, tmp_path, monkeypatch, where):
    from pipeline.frontend import feature_stage
    from pipeline.geometry.ba_stage import TwoViewBAStage

    out = tmp_path / "out"
    if where == "features":
        real = feature_stage.extract_sift_adaptive
        n = {"k": 0}

        def flaky(*a, **k):  # Ctrl-C after 3 images were extracted and cached
            n["k"] += 1
            if n["k"] > 3:
                raise KeyboardInterrupt
            return real(*a, **k)

        monkeypatch.setattr(feature_stage, "extract_sift_adaptive", flaky)
    else:
        def interrupted(*a, **k):
            raise KeyboardInterrupt

        monkeypatch.setattr(TwoViewBAStage, "compute", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run.main(scene, out, config=fast_config, gt=scene / "cameras.txt", quiet=True, reference=False)
    monkeypatch.undo()
    real = feature_stage.extract_sift_adaptive
    calls = {"sift": 0}

    def counted(*a, **k):
        calls["sift"] += 1
        return real(*a, **k)

    monkeypatch.setattr(feature_stage, "extract_sift_adaptive", counted)
    run.main(scene, out, config=fast_config, gt=scene / "cameras.txt", quiet=True, reference=False)
    n_images = len(read_rotations(full_run / "rotations" / "irls-l0.5.txt")[0])
    # the re-run resumes: only the images not extracted before the interrupt (none after it reached the BA)
    assert calls["sift"] == (n_images - 3 if where == "features" else 0), (calls, n_images)
    for label in ("irls-l0.5", "irls-h-l0.5", "sdp-cso3"):
        n1, R1 = read_rotations(out / "rotations" / f"{label}.txt")
        n2, R2 = read_rotations(full_run / "rotations" / f"{label}.txt")
        assert list(n1) == list(n2)
        np.testing.assert_allclose(R1, R2, atol=1e-6)


@pytest.mark.slow
def test_reference_failure_keeps_our_result(scene, full_run, tmp_path, monkeypatch):
    import shutil

    from pipeline.reference.incremental import IncrementalReferenceStage

    out = tmp_path / "out"
    shutil.copytree(full_run, out)
    shutil.rmtree(out / "reference")

    def broken(*a, **k):
        raise RuntimeError("pycolmap crashed")

    monkeypatch.setattr(IncrementalReferenceStage, "compute", broken)
    m = json.loads(run.main(scene, out, gt=scene / "cameras.txt", quiet=True).read_text())
    assert m["methods"]["irls-l0.5"]["median_deg"] < 0.3
    assert set(m["methods"]["irls-l0.5"]["references"]) == {"truth", "glomap"}  # GLOMAP does not depend on it
    assert any("pycolmap reference failed: pycolmap crashed" in n for n in m["notes"])


@pytest.mark.slow
def test_a_step_that_does_not_run_says_so_and_why(scene, full_run, tmp_path, capsys):
    """The console's numbers jumped ([5/13] to [7/13]: loop closure, which exhaustive pairs leave out; [9/13] to
    [12/13] with --no-reference): nothing told a step left out from one that failed silently."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(full_run, out)
    capsys.readouterr()

    def steps(**kw) -> list[str]:  # the progress lines of a re-run (every stage reused)
        run.main(scene, out, gt=scene / "cameras.txt", **kw)
        err = capsys.readouterr().err.splitlines()
        assert {int(ln[1:ln.index("/")]) for ln in err if ln.startswith("[")} == set(range(1, 14))  # none skipped
        return [ln for ln in err if "not run" in ln]

    assert steps(reference=False) == [
        "[6/13] loop closure: not run (exhaustive pairs: 6 images, pairs=auto is exhaustive up to 50)",
        "[10/13] pycolmap reference: not run (--no-reference)",
        "[11/13] pycolmap global (GLOMAP): not run (--no-reference)"]
    cfg = tmp_path / "c.yaml"
    cfg.write_text("run:\n  plots: false\n  refine: false\n  global_reference: false\n")
    assert steps(config=cfg)[1:] == ["[9/13] refine (pycolmap): not run (run.refine: false)",
                                     "[11/13] pycolmap global (GLOMAP): not run (run.global_reference: false)"]
    m = json.loads(run.main(scene, out, config=cfg, gt=scene / "cameras.txt", reference=False, quiet=True).read_text())
    assert "not run" not in capsys.readouterr().err  # -q: warnings only
    assert m["steps_not_run"] == {"loop_closure": "exhaustive pairs: 6 images, pairs=auto is exhaustive up to 50",
                                  "refine": "run.refine: false", "reference": "--no-reference",
                                  "global_reference": "--no-reference"}  # metrics.json says it too
    assert ("Not run: loop_closure (exhaustive pairs: 6 images, pairs=auto is exhaustive up to 50); refine (run.refine: "
            "false); reference (--no-reference); global_reference (--no-reference).") in (out / "report.md").read_text()


def test_bad_config_key(tmp_path, scene):
    p = tmp_path / "bad.yaml"
    p.write_text("run:\n  no_such_key: 1\n")
    with pytest.raises(PipelineError, match="unknown key"):
        run.main(scene, tmp_path / "out", config=p, quiet=True)
    for bad in ("retrieval:0", "retrieval:x", "sequential:0", "no_such_selector"):
        p.write_text(f"matching:\n  pairs: {bad}\n")
        with pytest.raises(ConfigError, match="pairs="):  # found up front, before any stage
            run.main(scene, tmp_path / "out", config=p, quiet=True)
    p.write_text("nonsense_stage:\n  a: 1\n")
    with pytest.raises(PipelineError, match="unknown section"):
        run.main(scene, tmp_path / "out", config=p, quiet=True)




def test_a_default_method_left_out_is_said_on_the_console(run_copy, tiny_scene, tmp_path, capsys):
    """Over run.sdp_max_n cameras the default SDP-cSO(3) does not run: the report's notes said so, the console (which
    names every step that does not run) said nothing, and its table simply had no SDP row."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("run:\n  plots: false\n  refine: false\n  reference: false\n  sdp_max_n: 3\n"
                   "features:\n  workers: 1\nmatching:\n  workers: 1\ntwo_view:\n  workers: 1\ntwo_view_ba:\n  workers: 1\n")
    capsys.readouterr()
    run.main(tiny_scene, run_copy, config=cfg, gt=tiny_scene / "cameras.txt")
    err = capsys.readouterr().err.splitlines()
    assert "[8/13] SDP-cSO(3) not run by default: N=6 > run.sdp_max_n=3" in err, err


def test_an_interrupted_rerun_leaves_no_report_of_the_run_before(run_copy, tiny_scene, tiny_config, tmp_path,
                                                                 monkeypatch):
    """A re-run with another averaging option, stopped by Ctrl-C after the averaging: rotations/irls-l0.5.txt was the
    new run's (0.0178° from the truth) while report.md and metrics.json still gave the run before's figures
    (0.014°) for it."""
    from pipeline.averaging.stage import AveragingStage

    cfg = tmp_path / "c.yaml"
    cfg.write_text(tiny_config.read_text() + "averaging:\n  refine: false\n")
    real = AveragingStage.run

    def then_interrupted(self, *a, **k):
        real(self, *a, **k)
        raise KeyboardInterrupt

    monkeypatch.setattr(AveragingStage, "run", then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        run.main(tiny_scene, run_copy, config=cfg, gt=tiny_scene / "cameras.txt", quiet=True, reference=False)
    assert not (run_copy / "report.md").exists() and not (run_copy / "metrics.json").exists()
    monkeypatch.undo()
    run.main(tiny_scene, run_copy, config=cfg, gt=tiny_scene / "cameras.txt", quiet=True, reference=False)
    assert (run_copy / "report.md").is_file() and (run_copy / "metrics.json").is_file()
