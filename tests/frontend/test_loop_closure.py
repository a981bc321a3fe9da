"""Loop closure: hop distances, the choice of pairs on an open ring, and the two rounds of the front end."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse.csgraph import shortest_path

from pipeline import features
from pipeline.core import so3
from pipeline.frontend.camera_estimate import CamerasConfig
from pipeline.frontend.loop_closure import (_adjacency, hop_distances, loop_candidates, saturated_candidates,
                                            transitive_candidates)
from pipeline.frontend.loop_stage import FrontEnd, LoopClosureConfig, LoopClosureStage, loop_note, run_front_end
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.matching_stage import load_matches
from pipeline.geometry.ba_stage import load_ba_viewgraph
from pipeline.geometry.ba_solver import BAConfig
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.stage import read_record
from pipeline.synthetic.large import render_large
from pipeline.synthetic.large_layouts import LargeSceneConfig

REPO = Path(__file__).resolve().parents[2]


def test_hop_distances_match_all_pairs_shortest_paths():
    rng = np.random.default_rng(0)
    n = 40
    E = np.unique(np.sort(rng.integers(0, 30, (45, 2)), axis=1), axis=0)  # images 30-39 isolated
    E = E[E[:, 0] != E[:, 1]]
    P = np.unique(np.sort(rng.integers(0, n, (300, 2)), axis=1), axis=0)
    P = P[P[:, 0] != P[:, 1]]
    D = shortest_path(_adjacency(E, n), unweighted=True, directed=False)
    np.testing.assert_array_equal(hop_distances(E, n, P), D[P[:, 0], P[:, 1]])
    assert np.isinf(hop_distances(E, n, P)).any() and np.isfinite(hop_distances(E, n, P)).any()


def ring(n: int, span: int = 2, gap: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of a ring of n views within ``span`` steps, and the ring's rotations (yaw 360/n° per view);
    with ``gap`` no pair crosses between views gap and gap + 1 (an open ring)."""
    a = np.repeat(np.arange(n), span)
    b = (a + np.tile(np.arange(1, span + 1), n)) % n
    P = np.unique(np.sort(np.stack([a, b], 1), axis=1), axis=0)
    if gap is not None:
        pos = (np.arange(n) - gap - 1) % n  # position along the open chain, the gap at its ends
        P = P[np.abs(pos[P[:, 0]] - pos[P[:, 1]]) <= span]
    R = so3.exp(np.outer(np.radians(360.0 / n * np.arange(n)), [0, 1, 0]))
    return P, R


def ranked(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Each view's m nearest views around the ring, nearest first, with a similarity that falls with distance."""
    d = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    d = np.minimum(d, n - d).astype(float)
    np.fill_diagonal(d, np.inf)
    nb = np.argsort(d, axis=1, kind="stable")[:, :m]
    return nb, 1.0 / (1.0 + np.take_along_axis(d, nb, axis=1))


def test_the_junction_of_an_open_ring_is_closed_first():
    n = 60
    verified, R = ring(n, span=2, gap=29)  # no verified pair crosses between 29 and 30
    matched = verified
    nb, sim = ranked(n, 8)
    c = loop_candidates(n, matched, verified, nb, sim, R, min_hops=5, budget=6)
    P = c["pairs"]
    assert tuple(P[0]) == (29, 30)  # the longest loop: the whole ring
    assert c["hops"][0] == np.ceil((n - 1) / 2)
    assert not np.isin(P[:, 0] * n + P[:, 1], matched[:, 0] * n + matched[:, 1]).any()
    # the other pairs across the junction come within min_hops through (29, 30): one pair, not the budget
    assert len(P) == 1
    # with more ranked neighbours, pairs farther from the junction are taken too, spread along it
    n = 120
    verified, R = ring(n, span=2, gap=59)
    nb, sim = ranked(n, 24)
    c = loop_candidates(n, verified, verified, nb, sim, R, min_hops=5, budget=6)
    P = c["pairs"]
    assert tuple(P[0]) == (59, 60) and len(P) == 6 and (c["hops"][:-1] >= c["hops"][1:]).all()
    across = (P[:, 0] <= 59) & (P[:, 1] >= 60)
    assert across.sum() >= 3 and (c["hops"][across] > 40).all() and (c["hops"][~across] < 10).all()
    for j in range(len(P) - 1):  # none brought within min_hops by a pair taken before it (as if it verified)
        Dj = shortest_path(_adjacency(np.r_[verified, P[j:j + 1]], n), unweighted=True, directed=False)
        assert (Dj[P[j + 1:, 0], P[j + 1:, 1]] >= 5).all()
    # with the ring closed (no gap) nothing is far apart: no pair is taken
    n = 60
    nb, sim = ranked(n, 8)
    closed, R = ring(n, span=2)
    assert len(loop_candidates(n, closed, closed, nb, sim, R, min_hops=5, budget=6)["pairs"]) == 0


def test_rotations_rule_out_pairs_looking_apart():
    n = 60
    verified, R = ring(n, span=2, gap=29)
    nb, sim = ranked(n, 8)
    R2 = R.copy()
    R2[30] = so3.exp(np.array([0.0, np.pi, 0.0])) @ R[30]  # view 30 turned around: not a pair for 29
    c = loop_candidates(n, verified, verified, nb, sim, R2, min_hops=5, budget=6)
    assert (29, 30) not in set(map(tuple, c["pairs"].tolist())) and c["n_apart"] >= 1
    R2[30] = np.nan  # unsolved: no angle, nothing ruled out
    c = loop_candidates(n, verified, verified, nb, sim, R2, min_hops=5, budget=6)
    assert tuple(c["pairs"][0]) == (29, 30) and np.isnan(c["angle_deg"][0])
    assert len(loop_candidates(n, verified, verified, nb, sim, R, budget=0)["pairs"]) == 0


def test_the_angle_is_between_viewing_directions_so_a_serpentine_survey_keeps_its_cross_lane_pairs():
    """A survey flown as a serpentine: views looking straight down, neighbouring lanes flown in opposite headings.
    Two views over the same ground from neighbouring lanes differ by a half turn about their optical axes, yet
    overlap; the angle test compares viewing directions, so it keeps them and still rules out views looking apart."""
    n = 60
    verified, R_ring = ring(n, span=2, gap=29)
    nb, sim = ranked(n, 8)
    down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # cam_from_world of a nadir view, heading +x
    R = np.stack([so3.exp(np.array([0.0, 0.0, np.pi * (k % 2)])) @ down for k in range(n)])  # rolls 0 and 180°
    c = loop_candidates(n, verified, verified, nb, sim, R, min_hops=5, budget=6)
    assert tuple(c["pairs"][0]) == (29, 30) and c["n_apart"] == 0 and np.allclose(c["angle_deg"], 0.0, atol=1e-4)
    assert so3.angle_between(R[30] @ R[29].T, np.eye(3)) > 3.1  # a relative rotation of a half turn
    R[30] = so3.exp(np.array([np.radians(100.0), 0.0, 0.0])) @ R[30]  # view 30 tilted 100°: looks away from 29
    c = loop_candidates(n, verified, verified, nb, sim, R, min_hops=5, budget=6)
    assert (29, 30) not in set(map(tuple, c["pairs"].tolist())) and c["n_apart"] >= 1
    # on the ring (upright views turning about their vertical) the angle is that of the turn
    c = loop_candidates(n, verified, verified, nb, sim, R_ring, min_hops=5, budget=6)
    d = np.minimum(np.abs(np.diff(c["pairs"], axis=1)).ravel(), n - np.abs(np.diff(c["pairs"], axis=1)).ravel())
    np.testing.assert_allclose(c["angle_deg"], 6.0 * d)


def test_pairs_across_components_come_first():
    n = 40
    a, _ = ring(20, span=2)
    verified = np.r_[a, a + 20]  # two separate rings
    nb = np.stack([(np.arange(n) + 20) % n, (np.arange(n) + 1) % n], axis=1)  # each view's twin first
    sim = np.tile([0.5, 0.4], (n, 1))
    c = loop_candidates(n, verified, verified, nb, sim, None, min_hops=5, budget=3)
    assert c["n_across"] == 3 and np.isinf(c["hops"]).all()
    assert (c["pairs"][:, 1] - c["pairs"][:, 0] == 20).all()


def test_images_whose_lower_ranked_candidates_verified_get_their_next_ranked_ones():
    n, k = 48, 8
    overlap, R = ring(n, span=7)  # each view overlaps 14 others (a turntable ring), k = 8 finds 8
    nb, sim = ranked(n, 4 * k)
    top = np.unique(np.sort(np.stack([np.repeat(np.arange(n), k), nb[:, :k].ravel()], 1), axis=1), axis=0)
    verified = top[np.isin(top @ [n, 1], overlap @ [n, 1])]
    c = saturated_candidates(n, k, top, verified, nb, sim, R, max_angle_deg=65.0, budget=10_000)
    assert c["saturated"].all() and c["n_saturated"] == n  # ranks 4-7 are 3-4 steps away: all verified
    d = np.abs(c["pairs"][:, 1] - c["pairs"][:, 0])
    d = np.minimum(d, n - d)
    # the next k ranked of each view are 5-8 steps away, none matched before; 8 steps (60°) is within 65°
    assert set(d.tolist()) == {5, 6, 7, 8} and len(c["pairs"]) == 4 * n
    assert not np.isin(c["pairs"] @ [n, 1], top @ [n, 1]).any()
    assert (np.diff(c["similarity"]) <= 0).all()  # most similar first
    # rotations rule out pairs looking apart (7 and 8 steps: 52.5° and 60°)
    c50 = saturated_candidates(n, k, top, verified, nb, sim, R, max_angle_deg=50.0, budget=10_000)
    assert set(np.minimum(np.abs(np.diff(c50["pairs"], axis=1)), n - np.abs(np.diff(c50["pairs"], axis=1)))
               .ravel().tolist()) == {5, 6} and c50["n_apart"] == 10 * n  # 7 to 16 steps
    # beyond the next k ranks where the rotations say the views can overlap; without rotations the next k only
    def steps(P: np.ndarray) -> set:
        d = np.abs(P[:, 1] - P[:, 0])
        return set(np.minimum(d, n - d).tolist())

    assert steps(saturated_candidates(n, k, top, verified, nb, sim, R, max_angle_deg=80.0,
                                      budget=10_000)["pairs"]) == set(range(5, 11))  # up to 75°
    no_r = saturated_candidates(n, k, top, verified, nb, sim, None, budget=10_000)
    assert steps(no_r["pairs"]) == {5, 6, 7, 8} and np.isnan(no_r["angle_deg"]).all()
    R_unsolved = R.copy()
    R_unsolved[0] = np.nan  # view 0 unsolved: its pairs have no angle, so its next k ranks only
    cu = saturated_candidates(n, k, top, verified, nb, sim, R_unsolved, max_angle_deg=80.0, budget=10_000)
    assert steps(cu["pairs"][(cu["pairs"] == 0).any(axis=1)]) == {5, 6, 7, 8}
    assert steps(cu["pairs"][~(cu["pairs"] == 0).any(axis=1)]) == set(range(5, 11))
    # the budget keeps the most similar
    c5 = saturated_candidates(n, k, top, verified, nb, sim, R, max_angle_deg=65.0, budget=5)
    assert len(c5["pairs"]) == 5 and np.all(c5["similarity"] == c["similarity"][:5])
    # a view whose lower-ranked candidates failed is not saturated (nor those for which it is one of them)
    d0 = np.minimum(top[:, 1] - top[:, 0], n - (top[:, 1] - top[:, 0]))
    fail0 = (top == 0).any(axis=1) & (d0 >= 3)
    c0 = saturated_candidates(n, k, top, verified[~np.isin(verified @ [n, 1], top[fail0] @ [n, 1])], nb, sim, R,
                              budget=10_000)
    assert not c0["saturated"][[0, 3, 4, n - 3, n - 4]].any() and c0["n_saturated"] == n - 5
    assert c0["saturated"][c0["pairs"]].any(axis=1).all()  # every pair is a saturated view's
    # where many matched pairs failed, the collection's overlap does not exceed k: nothing is added, even for the
    # views whose own candidates all verified
    far = np.stack([np.arange(n // 2), np.arange(n // 2) + n // 2], 1)  # opposite views: matched, not verified
    cf = saturated_candidates(n, k, np.r_[top, far], verified, nb, sim, R, budget=10_000)
    assert cf["verified_share"] < 0.95 and cf["n_saturated"] == 0 and len(cf["pairs"]) == 0
    assert c["verified_share"] == 1.0
    # a view that overlaps fewer than k others is not saturated: nothing is added
    verified3 = top[np.isin(top @ [n, 1], ring(n, span=3)[0] @ [n, 1])]  # ranks 6-7 (4 steps) fail
    c3 = saturated_candidates(n, k, top, verified3, nb, sim, R, budget=10_000)
    assert c3["n_saturated"] == 0 and len(c3["pairs"]) == 0


def _inliers(rng: np.random.Generator, E: np.ndarray, n_kp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random inlier keypoint lists of the edges E (one-to-one within a pair): offsets, keypoints in a and in b."""
    per = rng.integers(0, 40, len(E))
    ka = np.concatenate([rng.choice(n_kp, k, replace=False) for k in per])
    kb = np.concatenate([rng.choice(n_kp, k, replace=False) for k in per])
    return np.r_[0, np.cumsum(per)], ka, kb


def test_transitive_correspondences_count_the_keypoints_that_chain_two_images():
    rng = np.random.default_rng(3)
    n, n_kp = 14, 60
    E = np.unique(np.sort(rng.integers(0, n, (40, 2)), axis=1), axis=0)
    E = E[E[:, 0] != E[:, 1]]
    off, ka, kb = _inliers(rng, E, n_kp)
    # brute force: per image b, the keypoints of b matched into each other image; a pair (a, c) counts the
    # keypoints of any b matched into both
    into: dict[tuple[int, int], set[int]] = {}
    for e, (i, j) in enumerate(E):
        into.setdefault((j, i), set()).update(kb[off[e]:off[e + 1]].tolist())  # keypoints of j matched into i
        into.setdefault((i, j), set()).update(ka[off[e]:off[e + 1]].tolist())
    want = {}
    for a in range(n):
        for c in range(a + 1, n):
            t = sum(len(into.get((b, a), set()) & into.get((b, c), set())) for b in range(n))
            if t:
                want[(a, c)] = t
    matched = E[::2]
    got = transitive_candidates(n, matched, E, off, ka, kb, min_count=1, budget=10_000)
    mk = set(map(tuple, matched.tolist()))
    assert {tuple(p): int(c) for p, c in zip(got["pairs"].tolist(), got["count"])} == \
        {p: t for p, t in want.items() if p not in mk}
    assert got["n_candidates"] == got["n_eligible"] == len(got["pairs"]) > 10
    assert np.all(np.diff(got["count"]) <= 0)  # the most chained first
    # the gate and the budget
    gated = transitive_candidates(n, matched, E, off, ka, kb, min_count=8, budget=10_000)
    assert gated["count"].min() >= 8 and gated["n_eligible"] == len(gated["pairs"]) == sum(
        t >= 8 for p, t in want.items() if p not in mk) > 0
    top = transitive_candidates(n, matched, E, off, ka, kb, min_count=1, budget=5)
    np.testing.assert_array_equal(top["pairs"], got["pairs"][:5])
    # no verified pairs: nothing chains
    none = transitive_candidates(n, matched, E[:0], np.zeros(1, int), ka[:0], kb[:0], min_count=1, budget=10)
    assert len(none["pairs"]) == 0 and none["n_candidates"] == 0


def test_a_keypoint_matched_along_a_chain_makes_its_ends_a_transitive_pair():
    # a ring of views each verified with its two next: a keypoint seen by views 0-3 chains (0, 3) through 1 and 2
    n = 10
    E, _ = ring(n, span=2)
    tracks = [np.arange(s, s + 4) % n for s in range(n)]  # track s: one keypoint in views s … s+3
    kp = {(t, v): 100 * t for t in range(n) for v in tracks[t]}
    rows = []
    for e, (i, j) in enumerate(E):
        for t in range(n):
            if (t, i) in kp and (t, j) in kp:
                rows.append((e, kp[(t, i)] + i, kp[(t, j)] + j))
    rows = np.array(sorted(rows))
    off = np.searchsorted(rows[:, 0], np.arange(len(E) + 1))
    got = transitive_candidates(n, E, E, off, rows[:, 1], rows[:, 2], min_count=1, budget=100)
    d = np.abs(got["pairs"][:, 0] - got["pairs"][:, 1])
    assert set(np.minimum(d, n - d).tolist()) == {3}  # every pair three views apart, once
    assert len(got["pairs"]) == n and (got["count"] == 2).all()  # its keypoints in views 1 and 2


# ---------------------------------------------------------------------- the rounds in a WORK folder
SCENE = LargeSceneConfig(layout="ring", n_views=24, width=320, height=240, focal=280.0, points_per_view=800,
                         supersample=1)


def front(**loop: object) -> FrontEnd:
    quiet = {"progress": False}
    return FrontEnd(MatchingConfig(pairs="retrieval:3"), CamerasConfig(**quiet), TwoViewConfig(**quiet),
                    BAConfig(**quiet), LoopClosureConfig(**{"min_hops": 3, "max_fraction": 0.5, **loop}), False)


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("loop")
    render_large(SCENE, tmp / "scene", seed=0)
    features.main(tmp / "scene", tmp / "work", K_path=tmp / "scene" / "K.txt", progress=False)
    return tmp / "work"


def summary(work: Path, name: str) -> dict:
    rec = read_record(work, name)
    assert rec is not None
    return rec.summary


def test_two_rounds_then_a_rerun_reuses_both(work: Path):
    calls: list[tuple[str, bool, bool]] = []

    def run(stage, overwrite, again):
        rec = stage.run(overwrite)
        calls.append((stage.name, again, rec.reused))
        return rec

    run_front_end(work, front(), run)
    assert [c[:2] for c in calls] == [("matching", False), ("cameras", False), ("two_view", False),
                                      ("two_view_ba", False), ("loop_closure", False), ("matching", True),
                                      ("cameras", True), ("two_view", True), ("two_view_ba", True)]
    lc = json.loads((work / "loop_closure.json").read_text())
    n_first, n_added, n_tr = lc["n_first"], lc["n_added"], lc["n_transitive"]
    assert 0 < n_added <= 0.5 * n_first and len(lc["added"]) == n_added
    assert all(a["hops"] is None or a["hops"] >= 3 for a in lc["added"])
    assert 0 < n_tr <= 0.25 * n_first and len(lc["transitive"]) == n_tr
    assert all(a["count"] >= 15 for a in lc["transitive"])
    pairs = load_matches(work).pairs
    assert len(pairs) == n_first + n_added + n_tr and len(np.unique(pairs, axis=0)) == len(pairs)
    # the second round computed only the added pairs; the cameras are the first round's
    assert summary(work, "matching")["n_computed"] == n_added + n_tr
    assert summary(work, "two_view")["n_computed"] == n_added + n_tr
    assert calls[6][2]  # cameras reused in the second round
    assert summary(work, "matching")["pairs"]["loop_closure"] == {"n_first": n_first, "n_added": n_added,
                                                                   "n_saturated": 0, "n_extended": 0,
                                                                   "n_transitive": n_tr}  # k given
    assert summary(work, "matching")["base"] == lc["base"]

    calls.clear()
    run_front_end(work, front(), run)  # a re-run: the loop closure is current, the first round is not run again
    assert [c[0] for c in calls] == ["loop_closure", "matching", "cameras", "two_view", "two_view_ba"]
    assert all(c[2] for c in calls) and not any(c[1] for c in calls)


def test_the_next_ranked_pairs_of_saturated_images_are_matched_in_the_second_round(work: Path, tmp_path: Path):
    w = tmp_path / "work"
    shutil.copytree(work, w)
    done = load_matches(w).pairs  # pairs computed already (a round before this test's)
    fe = dataclasses.replace(front(saturated_share=0.0), matching=MatchingConfig(pairs="retrieval"))  # k chosen
    run_front_end(w, fe)
    lc = json.loads((w / "loop_closure.json").read_text())
    idx = {nm: i for i, nm in enumerate(lc["names"])}
    n = len(idx)
    k = summary(w, "matching")["pairs"]["k"]
    ext = np.array([sorted((idx[a["pair"][0]], idx[a["pair"][1]])) for a in lc["extended"]]).reshape(-1, 2)
    # every image is saturated at share 0: each one's next k ranked neighbours not matched yet, within 60°
    assert lc["n_saturated"] == n and len(ext) == lc["n_extended"] > 0
    assert all(a["angle_deg"] is None or a["angle_deg"] <= 60.0 for a in lc["extended"])
    pairs = load_matches(w).pairs
    assert np.isin(ext @ [n, 1], pairs @ [n, 1]).all()  # matched in the second round
    assert len(pairs) == len(np.unique(np.r_[np.asarray(lc["pairs"])], axis=0)) == lc["n_first"] + lc["n_added"] + \
        lc["n_extended"] + lc["n_transitive"]
    second = np.array([sorted((idx[a["pair"][0]], idx[a["pair"][1]]))
                       for key in ("added", "extended", "transitive") for a in lc[key]]).reshape(-1, 2)
    assert len(second) == lc["n_added"] + lc["n_extended"] + lc["n_transitive"] and lc["n_transitive"] > 0
    # the second round computed its pairs but those an earlier round of this WORK had computed
    assert summary(w, "two_view")["n_computed"] == np.isin(second @ [n, 1], done @ [n, 1], invert=True).sum() > 0
    assert summary(w, "matching")["pairs"]["loop_closure"]["n_extended"] == len(ext)
    assert f"{len(ext)} next-ranked pairs of the {n} images" in loop_note(w)
    # a k the user gave is kept as given
    fe_k = dataclasses.replace(front(saturated_share=0.0), matching=MatchingConfig(pairs=f"retrieval:{k}"))
    run_front_end(w, fe_k)
    assert json.loads((w / "loop_closure.json").read_text())["n_extended"] == 0


def test_a_damaged_loop_result_is_recomputed_with_the_same_pairs(work: Path):
    run_front_end(work, front())
    before = load_matches(work).pairs
    (work / "loop_closure.json").write_text("{not json")
    ranked = work / "retrieval.npz"
    data = bytearray(ranked.read_bytes())
    data[len(data) // 2:len(data) // 2 + 8] = b"\x00\xff" * 4  # same size: only its content can tell
    ranked.write_bytes(bytes(data))
    calls: list[str] = []
    run_front_end(work, front(), lambda st, ow, again: calls.append(st.name) or st.run(ow))
    assert calls[:5] == ["matching", "cameras", "two_view", "two_view_ba", "loop_closure"]  # the first round again
    np.testing.assert_array_equal(load_matches(work).pairs, before)
    assert json.loads((work / "loop_closure.json").read_text())["format"] == "rotavg-loop-closure"
    assert ranked.read_bytes() != bytes(data)  # the first round's matching ran again: the ranking was recomputed
    note = loop_note(work)
    assert note is not None and note.startswith("loop closure: ") and "verified" in note


def test_sequential_pairs_of_a_ring_are_closed_at_its_ends(work: Path):
    # a ring captured in order: sequential pairs leave it open between its last and first views
    fe = dataclasses.replace(front(), matching=MatchingConfig(pairs="sequential:2"))
    run_front_end(work, fe)
    lc = json.loads((work / "loop_closure.json").read_text())
    names = lc["names"]
    first = names.index("view_000.png"), names.index("view_023.png")
    assert lc["added"][0]["hops"] >= 10  # the longest loop first: across the ends of the chain
    edges = load_ba_viewgraph(work).edges
    ends = (np.isin(edges[:, 0], first[:1] + (1, 2)) & np.isin(edges[:, 1], (21, 22) + first[1:]))
    assert ends.any(), "a verified pair closes the ring"
    assert summary(work, "matching")["pairs"]["ranked"] is True


def test_no_loop_round_with_exhaustive_pairs_or_when_disabled(work: Path):
    for fe in (front(enabled=False), dataclasses.replace(front(), matching=MatchingConfig(pairs="exhaustive"))):
        calls: list[str] = []
        run_front_end(work, fe, lambda st, ow, again: calls.append(st.name) or st.run(ow))
        assert calls == ["matching", "cameras", "two_view", "two_view_ba"]
        assert not LoopClosureStage(work, fe).applies()
    proc = subprocess.run([sys.executable, "-m", "pipeline.loop_closure", "--work", str(work), "--no-enabled"],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2 and "no loop-closure round" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "(exhaustive pairs: 24 images" in proc.stderr, proc.stderr  # why this WORK has none, as run.py says it
    proc = subprocess.run([sys.executable, "-m", "pipeline.loop_closure", "--work", str(work)], capture_output=True,
                          text=True, cwd=REPO)  # the stage alone with its defaults on this WORK: exhaustive pairs
    assert proc.returncode == 2 and "(exhaustive pairs: " in proc.stderr and "pairs=auto is exhaustive up to 50" in \
        proc.stderr, proc.stderr


def test_the_front_end_says_why_it_has_no_loop_round(work: Path):
    """run.py's console went from [5/13] to [7/13] with no word of the loop-closure step it left out."""
    fronts = {"exhaustive pairs": dataclasses.replace(front(), matching=MatchingConfig(pairs="exhaustive")),
              "exhaustive pairs: 24 images, pairs=auto is exhaustive up to 50": dataclasses.replace(
                  front(), matching=MatchingConfig(pairs="auto")),
              "loop_closure.enabled: false": front(enabled=False), None: front()}
    for why, fe in fronts.items():
        said: list[tuple[str, str]] = []
        run_front_end(work, fe, lambda st, ow, again: None, skip=lambda st, w: said.append((st.name, w)))
        assert said == ([] if why is None else [("loop_closure", why)]), why
        assert LoopClosureStage(work, fe).why_not() == why


def test_run_py_reports_the_loop_round(work: Path, tmp_path: Path):
    from pipeline import run  # noqa: PLC0415

    cfg = tmp_path / "c.yaml"
    cfg.write_text("run:\n  plots: false\n  refine: false\n  reference: false\nmatching:\n  pairs: retrieval:3\n"
                   "loop_closure:\n  min_hops: 3\n  max_fraction: 0.5\n")
    scene = work.parent / "scene"
    metrics = json.loads(run.main(scene, tmp_path / "out", cfg, ["irls"], gt=scene / "cameras.txt",
                                  K=scene / "K.txt", quiet=True).read_text())
    lc = json.loads((tmp_path / "out" / "work" / "loop_closure.json").read_text())
    assert metrics["pairs"]["loop_closure"] == {"n_first": lc["n_first"], "n_added": lc["n_added"],
                                                "n_saturated": 0, "n_extended": 0, "n_transitive": lc["n_transitive"]}
    assert metrics["pairs"]["n_pairs"] == lc["n_first"] + lc["n_added"] + lc["n_transitive"]
    assert "loop_closure" in metrics["stages"]
    report = (tmp_path / "out" / "report.md").read_text()
    assert f"loop closure: {lc['n_added']} pairs added to the first round's {lc['n_first']}" in report
    chained = f"{lc['n_transitive']} pairs whose images the verified pairs' inliers chain"
    assert lc["n_transitive"] > 0 and chained in report
