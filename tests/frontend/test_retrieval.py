"""Retrieval pair selection: recall of the truly overlapping pairs on a rendered street, the selectors, ``auto``."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from pipeline import features, matching
from pipeline.core.errors import ConfigError
from pipeline.frontend.features import extract_sift
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.pairs import choose_pairs, parse_selector, select_pairs
from pipeline.frontend.retrieval import choose_k, knn_pairs, pair_recall, retrieve_pairs
from pipeline.stage import read_record
from pipeline.synthetic.large import render_large, true_pairs
from pipeline.synthetic.large_layouts import LargeSceneConfig
from pipeline.synthetic.render import SceneConfig, render_scene

# 28 views along a street at 400 px: 61 of 378 pairs truly overlap (16 %)
STREET = LargeSceneConfig(layout="street", n_views=28, width=400, height=300, focal=350.0, points_per_view=1500,
                          supersample=1)


@pytest.fixture(scope="module")
def street():
    s = render_large(STREET, None, seed=0)
    kps = [extract_sift(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in s["images"]]
    return s, kps


def test_retrieval_finds_the_overlapping_pairs(street):
    s, kps = street
    truth = true_pairs(s["overlap"], STREET.overlap_threshold)
    n = STREET.n_views
    assert 0.05 < len(truth) / (n * (n - 1) / 2) < 0.3  # not every pair overlaps
    descs, resp = [k.descriptors for k in kps], [k.responses for k in kps]
    res = retrieve_pairs(descs, responses=resp)
    r = pair_recall(res["pairs"], truth, n)
    assert res["k"] == choose_k(n) == 8
    assert r["recall"] >= 0.95 and r["fraction_matched"] <= 0.40, r
    P = res["pairs"]
    hits = {tuple(t) for t in truth.tolist()} & {tuple(q) for q in P.tolist()}  # both counted here, by hand
    assert r["recall"] == len(hits) / len(truth) and r["fraction_matched"] == len(P) / (n * (n - 1) / 2)
    assert P.dtype == np.int64 and (P[:, 0] < P[:, 1]).all() and len(np.unique(P, axis=0)) == len(P)
    assert (np.lexsort(P.T[::-1]) == np.arange(len(P))).all()  # sorted
    again = retrieve_pairs(descs, responses=resp)  # deterministic: same seed, same pairs
    np.testing.assert_array_equal(again["pairs"], P)


def test_knn_pairs_symmetric_union():
    S = np.array([[-np.inf, 0.9, 0.1, 0.0], [0.9, -np.inf, 0.2, 0.1], [0.1, 0.2, -np.inf, 0.8],
                  [0.0, 0.1, 0.8, -np.inf]])
    assert knn_pairs(S, 1).tolist() == [[0, 1], [2, 3]]
    assert knn_pairs(S, 5).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]  # K >= N-1: all pairs
    assert len(knn_pairs(S, 0)) == 0
    assert pair_recall(np.array([[0, 1]]), np.array([[0, 1], [2, 3]]), 4)["recall"] == 0.5


@pytest.mark.parametrize("spec, parsed", [("auto", ("auto", None)), ("retrieval", ("retrieval", None)),
                                          ("retrieval:12", ("retrieval", 12)), (" retrieval:3 ", ("retrieval", 3)),
                                          ("exhaustive", ("exhaustive", None)), ("sequential:2", ("sequential", 2))])
def test_parse_selector(spec, parsed):
    assert parse_selector(spec) == parsed


@pytest.mark.parametrize("spec", ["retrieval:0", "retrieval:x", "retrieval:-3", "retrieval:", "retrieval:1.5"])
def test_bad_retrieval_spec(spec):
    with pytest.raises(ConfigError, match="retrieval:K with K >= 1"):
        parse_selector(spec)


def test_auto_switches_at_the_threshold():
    names = [f"im{i}.png" for i in range(6)]
    rng = np.random.default_rng(0)
    descs = [rng.integers(0, 255, (200, 128), dtype=np.uint8) for _ in names]
    calls = []

    def load():
        calls.append(1)
        return descs, [np.ones(200) for _ in names]

    P, info = choose_pairs("auto", names, load, exhaustive_max_images=6)
    assert info["selector"] == "exhaustive" and info["auto"] and len(P) == 15 and not calls  # no descriptors read
    P, info = choose_pairs("auto", names, load, exhaustive_max_images=5)
    assert info["selector"] == "retrieval" and info["k"] == 5 and calls  # K = min(choose_k, N - 1)
    assert info["n_exhaustive"] == 15 and info["n_pairs"] == len(P) and info["fraction"] == len(P) / 15
    P, info = choose_pairs("retrieval:2", names, load, exhaustive_max_images=100)
    assert info["selector"] == "retrieval" and info["k"] == 2 and "auto" not in info and len(P) <= 12
    with pytest.raises(ConfigError, match="choose_pairs"):
        select_pairs("auto", names)


def test_matching_stage_records_the_choice(tmp_path, caplog):
    scene = render_scene(n_views=4, seed=3, out=tmp_path / "img", config=SceneConfig(width=240, height=180,
                                                                                      focal=210.0))
    work = tmp_path / "w"
    features.main(scene.out, work, progress=False)
    cfg = MatchingConfig(exhaustive_max_images=3)
    with caplog.at_level("INFO", logger="pipeline.frontend.matching_stage"):
        matching.main(work, cfg, progress=False)
    assert any("matching pairs: retrieval K=3: 6 of 6 pairs" in r.getMessage() for r in caplog.records)
    rec = read_record(work, "matching")
    assert rec.summary["pairs"]["selector"] == "retrieval" and rec.summary["pairs"]["k"] == 3
    assert json.loads((work / "matches.json").read_text())["selection"]["n_exhaustive"] == 6
    matching.main(work, MatchingConfig(), progress=False)  # 4 <= 40: exhaustive
    assert read_record(work, "matching").summary["pairs"]["selector"] == "exhaustive"
    assert json.loads((work / "matches.json").read_text())["n_computed"] == 0  # the same 6 pairs: reused
    matching.main(work, MatchingConfig(pairs="sequential:1"), progress=False)
    assert json.loads((work / "matches.json").read_text())["selection"]["k"] == 1
    shutil.rmtree(tmp_path / "img")
