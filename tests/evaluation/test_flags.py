"""The run's evidence: cameras the methods disagree on, and cameras whose focal length is only a guess, are flagged."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.evaluation.flags import DISAGREEMENT_DEG, GUESSED_FOCAL, method_disagreement, run_evidence
from pipeline.run import main


def _graph(names: list[str]) -> dict:
    return {"names": names, "flags": {}, "messages": [], "left_out": {}, "pairs": [], "n_cycles": 3}


def test_a_camera_the_methods_disagree_on_by_more_than_a_degree_is_flagged() -> None:
    rng = np.random.default_rng(0)
    names = [f"c{k}" for k in range(6)]
    R = so3.exp(rng.normal(size=(6, 3)))
    other = R.copy()
    other[2] = so3.exp(np.deg2rad([0.0, 1.5, 0.0])) @ R[2]  # 1.5° off: one of the two is wrong there
    other[4] = so3.exp(np.deg2rad([0.0, 0.0, 0.5])) @ R[4]  # 0.5°: within what an unflagged camera claims
    dis = method_disagreement({"a": (names, R), "b": (names, other)})
    assert dis["c2"][0] == pytest.approx(1.5, abs=0.05) and dis["c4"][0] == pytest.approx(0.5, abs=0.05)
    ev = run_evidence(_graph(names), {}, dis)
    assert DISAGREEMENT_DEG == 1.0 and set(ev["flags"]) == {"c2"}
    assert "disagree by 1.5°" in ev["flags"]["c2"][0] and ev["cameras"]["c4"]["status"] == "checked"


def test_a_guessed_focal_flags_its_camera() -> None:
    ev = run_evidence(_graph(["a", "b", "c"]), {}, {}, guessed_focal=["b", "not-in-the-graph"])
    assert ev["flags"] == {"b": [GUESSED_FOCAL]} and ev["n_flagged"] == 1
    assert ev["cameras"]["b"]["status"] == "flagged" and "not-in-the-graph" not in ev["cameras"]



def test_an_image_left_out_of_the_view_graph_that_a_refinement_placed_is_flagged_with_both_reasons() -> None:
    g = dict(_graph(["a", "b", "c"]), left_out={"d": "no accepted image pair", "e": "no accepted image pair"})
    ev = run_evidence(g, {}, {}, placed={"d": "placed by the refinement alone (x+refine)"})
    assert ev["flags"] == {"d": ["no accepted image pair", "placed by the refinement alone (x+refine)"]}
    assert ev["n_flagged"] == 1 and ev["cameras"]["d"]["status"] == "flagged"
    assert ev["cameras"]["e"] == {"status": "left out", "flags": ["no accepted image pair"]}
    assert ev["left_out"] == g["left_out"]  # the view graph's own verdict is kept as it was


@pytest.mark.slow
def test_a_run_whose_focal_lengths_stay_guessed_flags_every_camera(tiny_scene: Path, tiny_config: Path,
                                                                    tmp_path: Path, capsys) -> None:
    images = tmp_path / "images"
    images.mkdir()
    for p in tiny_scene.glob("*.png"):  # no cameras.txt beside them, and PNGs carry no EXIF
        shutil.copy(p, images / p.name)
    cfg = tmp_path / "guess.yaml"
    cfg.write_text(tiny_config.read_text() + "cameras:\n  estimate_focal: false\n")
    m = json.loads(main(images, tmp_path / "out", cfg, gt=tiny_scene / "cameras.txt", reference=False,
                        quiet=True).read_text())
    assert [f["source"] for f in m["intrinsics"]["focal"]] == ["default"]
    ev = m["evidence"]
    assert ev["n_flagged"] == len(ev["cameras"]) > 0
    assert all(GUESSED_FOCAL in c["flags"] for c in ev["cameras"].values())
    assert any("kept the default focal guess" in n for n in m["notes"])
    err = capsys.readouterr().err  # quiet (-q: warnings only) still says which cameras are flagged, and why
    assert f"{ev['n_flagged']} camera(s) flagged" in err and all(n in err for n in ev["cameras"])
    assert err.count("default guess") == 1  # shared by every camera: said once, with their names


def test_a_reason_shared_by_several_cameras_is_said_once() -> None:
    """castle (internet): the 230-character default-focal reason was repeated on each of the 8 flagged cameras, in
    the report and on the console."""
    from pipeline.evaluation.flags import evidence_console, evidence_markdown

    names = [f"c{k}.jpg" for k in range(5)]
    ev = run_evidence(_graph(names), {}, {"c1.jpg": (3.8, "a vs b")}, guessed_focal=names)
    md, con = "\n".join(evidence_markdown(ev)), evidence_console(ev)
    for text in (md, con):
        assert text.count(GUESSED_FOCAL) == 1 and "disagree by 3.8°" in text
        assert all(n in text for n in names)
    assert "| c0.jpg, c1.jpg, c2.jpg, c3.jpg, c4.jpg (5) | " + GUESSED_FOCAL + " |" in md
    assert "| c1.jpg | the methods disagree by 3.8° on it (a vs b): at least one is wrong there |" in md
    assert ev["flags"]["c1.jpg"] == ["the methods disagree by 3.8° on it (a vs b): at least one is wrong there",
                                     GUESSED_FOCAL]  # metrics.json keeps every camera's every reason
    two = run_evidence(_graph(names), {}, {"c1.jpg": (3.8, "a vs b"), "c2.jpg": (3.8, "a vs b")})
    assert "| c1.jpg | the methods disagree by 3.8°" in "\n".join(evidence_markdown(two))  # two alike: each its row


def test_the_report_says_every_rotation_is_checked_only_when_every_camera_has_a_confirmed_pair() -> None:
    """With no flag and no message, "Every camera's rotation is checked by a cycle of consistent pairs" was said
    whatever viewgraph.json says of the pairs (a graph whose cycles were not tested confirms none)."""
    from pipeline.evaluation.flags import evidence_markdown

    names = ["a", "b", "c"]
    pairs = [{"pair": [x, y], "status": "kept", "confirmed": False} for x, y in (("a", "b"), ("b", "c"), ("a", "c"))]
    md = "\n".join(evidence_markdown(run_evidence(dict(_graph(names), pairs=pairs), {})))
    assert "Every camera's rotation is checked" not in md
    assert "0 of 3 cameras have a pair that a consistent cycle confirms" in md
    for p in pairs:
        p["confirmed"] = True
    md = "\n".join(evidence_markdown(run_evidence(dict(_graph(names), pairs=pairs), {})))
    assert "Every camera's rotation is checked by a cycle of consistent pairs." in md


@pytest.mark.slow
@pytest.mark.parametrize("method, second", [("irls-h", "irls-l0.5"), ("irls", "colmap-ra")])
def test_a_run_of_one_method_without_a_refinement_gets_a_second_opinion_for_the_disagreement_flag(
        run_copy: Path, tiny_scene: Path, tiny_config: Path, tmp_path: Path, method: str, second: str) -> None:
    cfg = tmp_path / "one.yaml"
    base = tiny_config.read_text().replace("methods: [irls]", f"methods: [{method}]")
    cfg.write_text(base.replace("run:\n", "run:\n  refine: false\n"))
    m = json.loads(main(tiny_scene, run_copy, cfg, gt=tiny_scene / "cameras.txt", reference=False,
                        quiet=True).read_text())
    assert len(m["methods"]) == 2 and second in m["methods"]
    assert any(f"{second} was run as a second opinion" in n for n in m["notes"])
    cams = m["evidence"]["cameras"]
    assert cams and all("methods_disagree_deg" in c for c in cams.values())  # the flag has two sets to compare
    off = tmp_path / "off.yaml"
    off.write_text(cfg.read_text().replace("run:\n", "run:\n  second_opinion: false\n"))
    m = json.loads(main(tiny_scene, run_copy, off, gt=tiny_scene / "cameras.txt", reference=False,
                        quiet=True).read_text())
    assert len(m["methods"]) == 1 and not any("second opinion" in n for n in m["notes"])
    assert not any("methods_disagree_deg" in c for c in m["evidence"]["cameras"].values())
