"""pipeline.evaluation.report and .plots: the markdown tables, the PNG plots, the console table."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.evaluation.plots import spectral_layout
from pipeline.evaluation.report import ReportData, intrinsics_console, intrinsics_lines, metrics_table, write_report
from pipeline.frontend.intrinsics import focal_summary


def _summary(med: float, **extra) -> dict:
    return {"n_cameras": 8, "n_evaluated": 8, "median_deg": med, "mean_deg": med * 1.2, "rms_deg": med * 1.5,
            "max_deg": med * 3, "frobenius": 0.01, "pct_below": {"1": 100.0, "2": 100.0, "5": 100.0, "10": 100.0},
            **extra}


@pytest.fixture()
def data() -> ReportData:
    rng = np.random.default_rng(0)
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [1, 3]])
    return ReportData(
        metrics={"truth": {"irls-l0.5": _summary(0.1, time_s=0.02),
                           "sdp-cso3": _summary(0.12, time_s=0.5, certified=True, rank=3, gap=1e-7)},
                 "pycolmap": {"irls-l0.5": _summary(0.3)}},
        camera_errors={"truth": {"irls-l0.5": rng.random(4) * 0.2, "sdp-cso3": np.r_[rng.random(3), np.nan]}},
        edge_errors={"truth": {"ransac": rng.random(5) * 3, "ba": rng.random(5)}},
        histories={"irls-l0.5": [{"time_s": 0.01 * k, "cost": 1.0 / (k + 1)} for k in range(5)]},
        vg_edges=edges, vg_names=[f"v{k}.png" for k in range(4)],
        edge_values={"error_deg": rng.random(5)},
        notes=["view_9.png not registered by pycolmap: no verified match"],
        stages={"features": 1.0, "matching": 0.5},
    )


def test_write_report_writes_tables_and_plots(tmp_path, data):
    path = write_report(tmp_path, data)
    text = path.read_text()
    assert "## Against truth" in text and "## Against pycolmap" in text
    # one table row per method and reference
    assert text.count("| irls-l0.5 |") == 2 and text.count("| sdp-cso3 |") == 1
    assert "certified (rank 3" in text
    assert "not registered by pycolmap" in text
    for png in ("errors_truth.png", "edge_errors_truth.png", "convergence.png", "viewgraph_error_deg.png"):
        p = tmp_path / png
        assert p.is_file() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
        assert f"]({png})" in text
    assert "| **sum of the stages above** | 1.50 |" in text


def test_no_histories_no_convergence_plot(tmp_path, data):
    data.histories = {}
    text = write_report(tmp_path, data).read_text()
    assert "convergence" not in text and not (tmp_path / "convergence.png").exists()


def test_metrics_table_formats_missing_values():
    lines = metrics_table({"m": {"median_deg": float("nan"), "n_evaluated": 3, "certified": False}})
    assert lines[2].startswith("| m | 3 | – |")
    assert "NOT certified" in lines[2]


def test_spectral_layout_shape_and_separation():
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 0]])
    P = spectral_layout(5, edges)
    assert P.shape == (5, 2)
    # distinct cameras get distinct positions on a cycle
    d = np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(5)
    assert d.min() > 1e-3


def test_report_data_and_console_table():
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import report_data, summary_table
    from pipeline.reference import Reference

    names = [f"v{k}.png" for k in range(4)]
    R = np.broadcast_to(np.eye(3), (4, 3, 3))
    vg = ViewGraph.from_absolute(names, R, np.array([[0, 1], [1, 2], [2, 3], [0, 3]]))
    truth = Reference(names, R, centers=np.arange(12.0).reshape(4, 3), label="truth")
    pyc = Reference(names[:3], R[:3], label="pycolmap")
    sub = Reference(names[:3], R[:3], label="truth, pycolmap's 3 images")
    s = _summary(0.1)
    metrics = {"methods": {"irls-l0.5": {**s, "time_s": 0.5, "references": {"truth": s, sub.label: s, "pycolmap": s}}},
               "pycolmap": {**_summary(0.2), "n_registered": 3, "n_images": 4, "time_s": 3.0}}
    d = report_data(metrics, [truth, sub, pyc], {}, {"truth": {"ba": np.ones(4)}}, {}, vg, ["a note"], {"x": 1.0},
                    "title")
    assert list(d.metrics) == ["truth", sub.label, "pycolmap"]
    assert "pycolmap (incremental)" in d.metrics["truth"] and "pycolmap (incremental)" in d.metrics[sub.label]
    assert "pycolmap (incremental)" not in d.metrics["pycolmap"] and d.metrics["truth"]["irls-l0.5"]["time_s"] == 0.5
    assert set(d.edge_values) == {"error_vs_truth"} and d.positions.shape == (4, 3)
    d = report_data(metrics, [truth], {}, {}, {}, vg, [], {}, "title", plots_on=False)
    assert d.vg_edges is None and d.edge_values == {}
    table = summary_table(metrics)
    rows = [r.split() for r in table.splitlines()]
    assert rows[-1][:2] == ["pycolmap", "truth"] and table.endswith("3/4 reg.") and len(rows) == 2 + 3 + 1


def test_the_focal_line_gives_the_range_where_the_images_focal_lengths_differ():
    """Two cameras estimated from one folder (11 images of 3072 px at 2737 px, 16 of 640 px at 1537 px): one source,
    so one row, whose median alone (1537 px for all 27) would misstate the larger images' focal; the console line,
    as the report's table, gives the range."""
    K = np.tile(np.eye(3), (27, 1, 1))
    K[:11, 0, 0], K[11:, 0, 0] = 2737.4, 1537.2
    focal = [{"source": s} | v for s, v in focal_summary(K, ["estimated:profile+rotcons"] * 27).items()]
    line = intrinsics_console({"focal": focal})
    assert line == "focal: 1537.2 px (1537.2–2737.4) (estimated:profile+rotcons, 27 images)"
    assert "| 1537.2 (1537.2–2737.4) | 27 | estimated:profile+rotcons |" in intrinsics_lines({"focal": focal})
    K[:, 0, 0] = 560.0
    one = [{"source": "file:K.txt"} | v for v in focal_summary(K, ["file:K.txt"] * 27).values()]
    assert intrinsics_console({"focal": one}) == "focal: 560.0 px (file:K.txt, 27 images)"


def test_the_intrinsics_say_a_note_shared_by_several_cameras_once_with_a_count():
    """Ten one-image cameras, none with a usable pair: the section said "- focal: 0 usable pairs < min_pairs=3" and
    the same of the radial term ten times each."""
    nan = float("nan")
    one = {"n_images": 1, "focal": {"f": nan, "n_pairs": 0, "note": "0 usable pairs < min_pairs=3", "determined": True},
           "radial": {"n_pairs": 0, "note": "0 usable pairs < min_pairs=3"}}
    weak = {"n_images": 16, "focal": {"f": 1537.2, "n_pairs": 27, "sd_rel": 0.374, "determined": False,
                                      "note": "focal poorly determined: leaving one image out moves it by 37.4%"},
            "radial": {"n_pairs": 29, "note": ""}}
    focal = [{"source": "default", "n_images": 10, "median_px": 1738.2, "min_px": 1311.6, "max_px": 2596.8}]
    lines = intrinsics_lines({"focal": focal, "estimates": [dict(one) for _ in range(10)] + [weak]})
    notes = [ln for ln in lines if ln.startswith("- ")]
    assert notes == ["- focal of 10 cameras (10 images): not estimated: 0 usable pairs < min_pairs=3",
                     "- radial of 10 cameras (10 images): not estimated: 0 usable pairs < min_pairs=3",
                     "- focal of 1 camera (16 images): 1537.2 px from 27 pairs, jackknife sd 37.4%: focal poorly "
                     "determined: leaving one image out moves it by 37.4%"]
    # an estimate made from no pair is not "determined": the console says how many cameras kept their start value
    line = intrinsics_console({"focal": focal, "estimates": [dict(one) for _ in range(10)] + [weak]})
    assert line.endswith("POORLY DETERMINED for 1 camera group(s) (jackknife sd 37.4%); NOT ESTIMATED for 10 "
                         "image(s) (the default guess 1.2·max(w, h) kept)")


def test_a_focal_superseded_by_the_view_graph_calibration_is_not_called_unestimated():
    """fountain (internet): each one-image camera's own estimate had no pair, and pycolmap's view-graph calibration
    gave every image its focal (source estimated:view-graph); "not estimated" and "start focal kept" were false."""
    sup = ("superseded by per-image focal lengths (pycolmap's view-graph calibration): the pairs' rotations are "
           "significantly more consistent with them")
    one = {"n_images": 1, "focal": {"f": None, "n_pairs": 0, "note": sup, "group_note": "0 usable pairs < min_pairs=3"}}
    intr = {"focal": [{"source": "estimated:view-graph", "n_images": 10, "median_px": 1579.3, "min_px": 960.8,
                       "max_px": 2448.0}], "estimates": [dict(one) for _ in range(10)]}
    notes = [ln for ln in intrinsics_lines(intr) if ln.startswith("- ")]
    assert notes[0] == (f"- focal of 10 cameras (10 images): {sup} (each camera's own estimate: 0 usable pairs < "
                        "min_pairs=3)") and len(notes) == 2
    assert intrinsics_console(intr) == "focal: 1579.3 px (960.8–2448.0) (estimated:view-graph, 10 images)"
    # how well determined: the calibration gives no uncertainty, and the report says so (the benchmark measured one
    # image's focal 31% off the truth)
    assert notes[1] == "- focal of 10 images from the view-graph calibration: no uncertainty is estimated for it"


def test_an_estimate_whose_sd_is_not_finite_is_said_without_one_when_read_back_from_cameras_json(tmp_path):
    """A focal fixed by pairs that leaving one image out cuts below min_pairs has an infinite jackknife sd: cameras.json
    (strict JSON) holds null for it, and the console line (which raised TypeError on it), the report and
    metrics.json's messages say that estimate without an sd."""
    from pipeline.core.atomic import write_json
    from pipeline.evaluation.assemble import _weak_focal_messages

    est = [{"n_images": n, "focal": {"f": 900.0, "n_pairs": 4, "sd_rel": sd, "determined": False, "note": ""}}
           for n, sd in ((3, float("inf")), (5, 0.2))]
    focal = [{"source": "estimated:profile+rotcons", "n_images": 8, "median_px": 900.0, "min_px": 900.0,
              "max_px": 900.0}]
    intr = json.loads(write_json(tmp_path / "cameras.json", {"focal": focal, "estimates": est}).read_text())
    assert intr["estimates"][0]["focal"]["sd_rel"] is None
    assert intrinsics_console(intr).endswith("POORLY DETERMINED for 2 camera group(s) (jackknife sd –, 20.0%)")
    assert "- focal of 1 camera (3 images): 900.0 px from 4 pairs" in intrinsics_lines(intr)
    assert [m.split(":")[0] for m in _weak_focal_messages(intr)] == [
        "the focal length of 3 image(s) is poorly determined (900.0 px)",
        "the focal length of 5 image(s) is poorly determined (900.0 px, jackknife sd 20.0%)"]


SDP_CERT = {"certified": True, "rank": 3, "gap": 5.4e-08, "gap_vs_resolution": 0.009, "kappa": 0.01, "n_kept": 13,
            "n_rejected": 0, "statement": "globally optimal for the anisotropic cost with irls-h's final precisions on "
                                          "13 of 13 edges; it proves optimality for that cost on that edge set, not "
                                          "accuracy"}
IRLS_CERT = {"verdict": "verified", "n_edges": 50, "n_weighted_edges": 48, "rel_gap_bound": 0.003,
             "statement": "verified: globally optimal for the final reweighted least-squares cost of IRLS-l0.5 on 48 "
                          "of 50 edges; it proves optimality for that cost on that edge set, not accuracy"}


def test_a_certificate_says_on_which_edges_and_its_statement_names_the_cost():
    """The cell said "certified (rank 3, gap 5.4e-08)": no edge set, no cost, and a gap relative to a constant offset
    of the cost (1.7e6 on castle) where the verdict rests on 0.009× the cost's resolution; IRLS's verified
    certificates were not shown at all."""
    rows = {"sdp-cso3": _summary(0.1, certified=True, rank=3, gap=5.4e-08, certificate=SDP_CERT),
            "irls-l0.5": _summary(0.1, certificate=IRLS_CERT), "colmap-ra": _summary(0.2)}
    cells = {ln.split(" | ")[0][2:]: ln.split(" | ")[-1] for ln in metrics_table(rows)[2:]}
    assert cells["sdp-cso3"] == "certified on 13 of 13 edges (rank 3, gap 0.009× the cost's resolution) † |"
    assert cells["irls-l0.5"] == "verified on 48 of 50 edges † |"  # its gap: in its statement, rounded there
    assert cells["colmap-ra"] == " |"
    data = ReportData(metrics={"truth": rows},
                      certificates={"sdp-cso3": SDP_CERT["statement"], "irls-l0.5": IRLS_CERT["statement"]})
    text = write_report_text(data)
    sec = text.split("## Certificates\n", 1)[1].split("\n## ", 1)[0]
    assert f"| sdp-cso3 | {SDP_CERT['statement']} |" in sec and f"| irls-l0.5 | {IRLS_CERT['statement']} |" in sec
    from pipeline.evaluation.report import summary_table
    table = summary_table({"methods": {k: {**v, "references": {"truth": v}} for k, v in rows.items()}})
    assert "certified on 13/13 edges †" in table and "verified on 48/50 edges †" in table


def write_report_text(data: ReportData) -> str:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        return write_report(Path(d), data).read_text()


def test_a_predicted_sigma_is_not_shown_as_an_accuracy():
    """fountain: the refined row's "σ pred °" 0.0022 beside a measured median error of 0.027° (12×); castle: a camera
    not refined (its rotation chained from a neighbour) showed the model's σ as if it were its own."""
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import report_data
    from pipeline.reference import Reference

    names = [f"v{k}.png" for k in range(4)]
    R = np.broadcast_to(np.eye(3), (4, 3, 3))
    vg = ViewGraph.from_absolute(names, R, np.array([[0, 1], [1, 2], [2, 3], [0, 3]]))
    s = _summary(0.027)
    refine = {**s, "method": "refine", "status": "partial", "n_refined": 3, "n_cameras": 4, "sigma_median_deg": 0.0022,
              "uncertainty_deg": {"v0.png": 0.002, "v1.png": 0.0022, "v2.png": 0.0025, "v3.png": 0.0021},
              "kept_averaged": {"v3.png": "chained from refined neighbours"}, "references": {"truth": s}}
    metrics = {"methods": {"x+refine": refine}}
    errs = {"truth": {"x+refine": np.array([0.027, 0.001, 0.03, 2.0])}}
    d = report_data(metrics, [Reference(names, R, label="truth")], errs, {}, {}, vg, [], {}, "t", plots_on=False)
    text = write_report_text(d)
    table = text.split("## Against truth", 1)[1].split("\n## ", 1)[0]
    assert "σ pred" not in table and "| BA σ ° ‡ |" in table.splitlines()[2]
    assert "‡ BA σ: a precision under pycolmap's model, not an accuracy; measured median error 12× it." in table
    sec = text.split("## Refinement (x+refine)", 1)[1]
    assert "| v3.png | 2.0000 | – | – | chained from refined neighbours |" in sec
    assert "2 of 3 refined cameras are more than 3σ off against truth" in sec


def test_the_refinement_section_gives_the_refinements_warnings():
    """castle (internet): "0027.jpg: refined rotation 13.73° from the averaged one ...", "the focal length of 3
    camera(s) is weakly determined" and "1 of 13 pairs ... not used" were in metrics.json only."""
    from pipeline.evaluation.report import _refine_sections

    warns = ["1 of 13 pairs disagree with the averaged rotations by more than 5.0° and are not used",
             "0027.jpg: refined rotation 13.73° from the averaged one (> max_change_deg = 5.0°)",
             "0026.jpg: 0 3D points in the final model (< 20)"]
    m = {"method": "refine", "status": "partial", "uncertainty_deg": {"0026.jpg": 0.25, "0027.jpg": 1.2},
         "kept_averaged": {"0026.jpg": "0 3D points in the final model (< 20)"}, "warnings": warns}
    sec = _refine_sections({"methods": {"x+refine": m}}, [], {})["Refinement (x+refine)"]
    assert f"- {warns[0]}" in sec and f"- {warns[1]}" in sec
    assert not any(ln.startswith("- 0026.jpg") for ln in sec)  # said in its row ("not refined: why")


def test_the_camera_counts_say_of_how_many_images():
    """castle (internet), 10 images: our methods scored 8 (the view graph's largest component), pycolmap 9, GLOMAP
    10; "cams 8" beside "cams 10" did not say that two images were not solved at all."""
    from pipeline.evaluation.report import summary_table

    rows = {"irls-l0.5": _summary(10.5) | {"n_evaluated": 8}, "pycolmap (global, GLOMAP)": _summary(14.2) | {
        "n_evaluated": 10}}
    text = write_report_text(ReportData(metrics={"truth": rows}, n_images=10))
    head = text.split("## Against truth", 1)[1].split("\n")[2]
    assert head.startswith("| method | cams of 10 |")
    s = _summary(10.5) | {"n_evaluated": 8}
    table = summary_table({"methods": {"irls-l0.5": {**s, "references": {"truth": s}}}, "input": {"n_images": 10}})
    assert table.splitlines()[0].split()[:3] == ["method", "reference", "cams/10"]
    assert table.splitlines()[2].split()[:3] == ["irls-l0.5", "truth", "8"]


def test_without_a_reference_the_report_still_lists_the_methods():
    """A run with no truth and no pycolmap peer: report.md had no table of the methods at all (their cameras, time,
    certificate, the refinement's status were on the console only), and the refinement's σ stood alone."""
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import report_data

    names = [f"v{k}.png" for k in range(4)]
    vg = ViewGraph.from_absolute(names, np.broadcast_to(np.eye(3), (4, 3, 3)), np.array([[0, 1], [1, 2], [2, 3],
                                                                                         [0, 3]]))
    refine = {"method": "refine", "status": "ok", "n_refined": 4, "n_cameras": 4, "time_s": 0.72,
              "sigma_median_deg": 0.009, "uncertainty_deg": {n: 0.009 for n in names}, "references": {}}
    metrics = {"methods": {"sdp-cso3": {"n_cameras": 4, "time_s": 0.07, "certified": True, "certificate": SDP_CERT,
                                        "references": {}}, "x+refine": refine}}
    text = write_report_text(report_data(metrics, [], {}, {}, {}, vg, [], {}, "t", plots_on=False))
    table = text.split("## Methods (no reference: no errors)", 1)[1].split("\n## ", 1)[0]
    assert "| sdp-cso3 | 4 | – |" in table and "certified on 13 of 13 edges" in table and "0.07" in table
    assert "| x+refine | 4 | – |" in table and "refine ok (4/4 refined)" in table
    assert "not an accuracy" in text.split("## Refinement (x+refine)", 1)[1]


def test_the_stages_sum_is_not_called_the_runs_total(tmp_path, data):
    """temple: the table's "total" 28.60 s was the sum of the stages before the report, while metrics.json's
    total_s (37.67 s) is the whole run's wall time."""
    text = write_report(tmp_path, data).read_text()
    assert "**total**" not in text
    assert "the whole run's wall time is metrics.json's total_s" in text.split("## Stages", 1)[1].split("\n## ", 1)[0]


def test_a_peers_time_says_what_it_counts():
    """fountain: GLOMAP's row said 62.81 s and the stages table 22.87 s: the row counts pycolmap's extraction and
    matching (40 s, the incremental peer's database) too, which the report did not say."""
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import report_data
    from pipeline.reference import Reference

    names = [f"v{k}.png" for k in range(4)]
    R = np.broadcast_to(np.eye(3), (4, 3, 3))
    vg = ViewGraph.from_absolute(names, R, np.array([[0, 1], [1, 2], [2, 3], [0, 3]]))
    s = _summary(0.03)
    times = {"extract_s": 31.25, "match_s": 8.75, "map_s": 22.82, "total_s": 62.82}
    metrics = {"methods": {"irls-l0.5": {**s, "time_s": 0.1, "references": {"truth": s}}},
               "peers": {"glomap": {**s, "time_s": 62.82, "times": times, "n_registered": 4, "n_images": 4}}}
    d = report_data(metrics, [Reference(names, R, label="truth")], {}, {}, {}, vg, [], {}, "t", plots_on=False)
    table = write_report_text(d).split("## Against truth", 1)[1].split("\n## ", 1)[0]
    assert ("time s of a pycolmap row, from the images: pycolmap (global, GLOMAP) 31.25 s extraction + 8.75 s "
            "matching + 22.82 s mapping") in table


def test_a_row_that_scored_fewer_cameras_says_why():
    """A method that solved fewer cameras than the view graph's (its solved component) and cameras the reference
    lacks: the row showed the smaller count and no reason."""
    rows = {"irls-l0.5": _summary(0.1) | {"n_evaluated": 5, "n_cameras": 6, "n_dropped": 2,
                                          "dropped_names": ["a.png", "b.png"], "not_in_reference": ["c.png"]}}
    cell = metrics_table(rows, 8)[2].split(" | ")[-1]
    assert cell == "2 camera(s) outside its solved component (a.png, b.png); 1 not in the reference (c.png) |"


def test_what_a_certificate_proves_is_said_once_not_under_every_table():
    """temple with the peers: the two-line certificate note was printed under each of the four tables."""
    from pipeline.evaluation.flags import CERTIFICATE_NOTE

    rows = {"sdp-cso3": _summary(0.1, certified=True, rank=3, certificate=SDP_CERT)}
    data = ReportData(metrics={"truth": rows, "pycolmap": rows, "glomap": rows},
                      certificates={"sdp-cso3": SDP_CERT["statement"]})
    text = write_report_text(data)
    low = text.lower()
    assert low.count(CERTIFICATE_NOTE) == 1 and CERTIFICATE_NOTE in low.split("## certificates", 1)[1]
    assert text.count('† for which cost and edges, and what it does not prove: "Certificates".') == 3


def test_a_table_against_a_peer_says_how_far_the_peer_itself_is_from_the_truth():
    """castle (internet): pycolmap's model was 8.8° (median) from the truth; the table "Against pycolmap" scored our
    methods against it with nothing to say that it is no truth."""
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import report_data
    from pipeline.reference import Reference

    names = [f"v{k}.png" for k in range(4)]
    R = np.broadcast_to(np.eye(3), (4, 3, 3))
    vg = ViewGraph.from_absolute(names, R, np.array([[0, 1], [1, 2], [2, 3], [0, 3]]))
    s = _summary(0.5)
    metrics = {"methods": {"irls-l0.5": {**s, "references": {"truth": s, "pycolmap": s}}},
               "peers": {"pycolmap": {**_summary(8.832) | {"n_evaluated": 3}, "n_registered": 3, "n_images": 4}}}
    refs = [Reference(names, R, label="truth"), Reference(names[:3], R[:3], label="pycolmap")]
    text = write_report_text(report_data(metrics, refs, {}, {}, {}, vg, [], {}, "t", plots_on=False))
    sec = text.split("## Against pycolmap", 1)[1]
    assert sec.startswith("\n\nA reference, not the truth: pycolmap (incremental) is itself 8.832° (median) from the "
                          "truth on its 3 images.\n")


def test_a_peers_time_is_explained_once():
    """temple with the peers: the same line of the peers' times was printed under each of the four tables."""
    times = {"extract_s": 7.3, "match_s": 2.59, "map_s": 1.34}
    row = _summary(0.25) | {"time_s": 11.23, "times": times}
    data = ReportData(metrics={r: {"irls-l0.5": _summary(0.5), "pycolmap (incremental)": row}
                               for r in ("truth", "truth, pycolmap's 13 images", "glomap")})
    assert write_report_text(data).count("time s of a pycolmap row") == 1


def test_a_peers_row_beside_ours_is_named_by_one_function_in_the_report_and_on_the_console():
    """GLOMAP's row beside our methods' was named by two rules, the console table's ("pycolmap-glomap") and
    report.md's ("pycolmap (global, GLOMAP)"), each in its own module."""
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.report import peer_row, report_data, summary_table
    from pipeline.reference import Reference

    names = [f"v{k}.png" for k in range(4)]
    R = np.broadcast_to(np.eye(3), (4, 3, 3))
    vg = ViewGraph.from_absolute(names, R, np.array([[0, 1], [1, 2], [2, 3], [0, 3]]))
    s = _summary(0.1)
    labels = ("pycolmap", "glomap", "other")
    metrics = {"methods": {"irls-l0.5": {**s, "references": {"truth": s}}},
               "peers": {p: {**_summary(0.2), "n_registered": 4, "n_images": 4} for p in labels}}
    d = report_data(metrics, [Reference(names, R, label="truth")], {}, {}, {}, vg, [], {}, "t", plots_on=False)
    assert list(d.metrics["truth"])[1:] == [peer_row(p) for p in labels] == [
        "pycolmap (incremental)", "pycolmap (global, GLOMAP)", "pycolmap (other)"]
    rows = [r.split()[0] for r in summary_table(metrics).splitlines()[3:]]
    assert rows == [peer_row(p, short=True) for p in labels] == ["pycolmap", "pycolmap-glomap", "pycolmap-other"]
