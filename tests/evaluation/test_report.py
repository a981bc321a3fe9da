"""pipeline.evaluation.report and .plots: the markdown tables, the PNG plots, the console table."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.plots import spectral_layout
from pipeline.evaluation.report import ReportData, metrics_table, write_report


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
    assert "| **total** | 1.50 |" in text


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
