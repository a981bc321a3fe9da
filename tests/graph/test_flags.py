"""pipeline.graph.flags: cameras resting on unchecked evidence are flagged with the reason; a tree says so."""

from __future__ import annotations

import numpy as np

from pipeline.graph.flags import NO_CYCLE, graph_flags, two_edge_blocks, bridges

NAMES = [f"c{k}" for k in range(10)]


def test_a_tree_cannot_be_verified():
    E = np.array([[0, 1], [1, 2], [1, 3]])
    ones = np.ones(3, bool)
    fl = graph_flags(E, 4, ones, np.zeros(3, bool), np.zeros(3, bool), NAMES)
    assert fl.n_cycles == 0 and fl.messages == [NO_CYCLE] and fl.bridge.all()
    # the leaves rest on a single pair; the hub's block is a lone camera too
    assert "rests on a single pair (c0, c1)" in fl.cameras[0][0]
    assert set(fl.cameras) == {0, 1, 2, 3}
    assert any("single pair" in w for w in fl.cameras[3])


def test_triangle_with_a_tail_and_a_dangling_pair():
    # triangle 0-1-2 (confirmed), bridge 2-3, square 3-4-5-6 (unconfirmed), bridge 6-7 (single pair)
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [3, 6], [6, 7]])
    kept = np.ones(len(E), bool)
    conf = np.array([1, 1, 1, 0, 0, 0, 0, 0, 0], bool)
    rej = np.zeros(len(E), bool)
    fl = graph_flags(E, 8, kept, conf, rej, NAMES)
    assert fl.n_cycles == 2 and not fl.messages
    assert bridges(E, 8).tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 1]
    blocks = two_edge_blocks(E, 8, kept, fl.bridge)
    assert len(set(blocks[[3, 4, 5, 6]])) == 1 and blocks[3] != blocks[0]
    # the square's block is the core (4 cameras > 3): the triangle hangs on bridge (2, 3)
    for k in (0, 1, 2):
        assert any("bridge pair (c2, c3)" in w for w in fl.cameras[k])
        assert not any("unconfirmed" in w for w in fl.cameras[k])
    for k in (3, 4, 5, 6):
        assert any("none of its" in w and "unconfirmed" in w for w in fl.cameras[k])
        assert not any("bridge" in w for w in fl.cameras[k])
    assert fl.cameras[7] == ["rests on a single pair (c6, c7): nothing checks it"]


def test_bridges_in_series_are_all_named():
    """A camera two bridges away from the core was said to rest on the first one alone, though an error in either
    moves it."""
    # core triangle 0-1-2 (the lowest label of the equal blocks), bridge 2-3, triangle 3-4-5, bridge 5-6, camera 6
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [3, 5], [5, 6]])
    kept = np.ones(len(E), bool)
    fl = graph_flags(E, 7, kept, kept & ~bridges(E, 7), np.zeros(len(E), bool), NAMES)
    assert fl.cameras[6] == ["rests on a single pair (c5, c6): nothing checks it",
                             "joined to the rest only through the bridge pairs (c5, c6) and (c2, c3) in series: an "
                             "error in any of them cannot be detected"]
    for k in (3, 4, 5):
        assert fl.cameras[k] == ["joined to the rest only through the bridge pair (c2, c3): an error in that pair "
                                 "cannot be detected"]
    # 4 of the 7 cameras hang off the core through the bridge (2, 3): an error in it moves the core, in the frame
    # of the whole, more than the cameras beyond (test_a_core_on_the_smaller_side_of_a_bridge_takes_most_of_its_error)
    for k in (0, 1, 2):
        assert fl.cameras[k] == ["4 of the 7 cameras of its component hang off its block (the largest that cycles "
                                 "join, 3 cameras) through the bridge pair (c2, c3): aligned as a whole, an error in "
                                 "that pair moves this block more than the cameras beyond it, and nothing can detect "
                                 "it"]
    # a tail of five bridges: three are named, and how many more
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [6, 7]])
    fl = graph_flags(E, 8, np.ones(8, bool), np.array([1, 1, 1, 0, 0, 0, 0, 0], bool), np.zeros(8, bool), NAMES)
    assert fl.cameras[7][1] == ("joined to the rest only through the bridge pairs (c6, c7), (c5, c6), (c4, c5) and 2 "
                                "more in series: an error in any of them cannot be detected")
    assert fl.cameras[5][0].startswith("joined to the rest only through the bridge pairs (c4, c5), (c3, c4) and "
                                       "(c2, c3) in series")


def test_a_core_on_the_smaller_side_of_a_bridge_takes_most_of_its_error():
    """Why such a core is flagged: with every pair exact but the bridge (2, 3), off by δ, the averaged rotations
    aligned to the truth (ℓ2, over all cameras, as any evaluation aligns them) put δ·r/N on the c cameras on one
    side and δ·c/N on the r beyond: the core triangle (c = 3 of N = 7) is further off than the cameras it holds."""
    from pipeline.averaging import average
    from pipeline.core import so3
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.metrics import rotation_errors_deg

    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6]])
    R = so3.random_rotations(7, np.random.default_rng(0))
    vg = ViewGraph.from_absolute(NAMES[:7], R, E)
    bridge = int(np.flatnonzero((vg.edges == [2, 3]).all(1))[0])
    delta = 2.0
    R_rel = vg.R_rel.copy()
    R_rel[bridge] = so3.exp(np.deg2rad(delta) * np.array([0.0, 0.0, 1.0])) @ R_rel[bridge]
    res = average(ViewGraph.from_edges(vg.names, vg.edges, R_rel), "irls")
    e = rotation_errors_deg(res.R, R)
    np.testing.assert_allclose(e[:3], delta * 4 / 7, rtol=0.02)
    np.testing.assert_allclose(e[3:], delta * 3 / 7, rtol=0.02)
    fl = graph_flags(vg.edges, 7, np.ones(len(E), bool), ~bridges(vg.edges, 7), np.zeros(len(E), bool), NAMES)
    assert all(any("4 of the 7 cameras" in w for w in fl.cameras[k]) for k in (0, 1, 2))

    def core_flagged(E: np.ndarray, n: int) -> set[int]:
        E = np.asarray(E)
        fl = graph_flags(E, n, np.ones(len(E), bool), ~bridges(E, n), np.zeros(len(E), bool), NAMES)
        return {k for k, ws in fl.cameras.items() if any("hang off its block" in w for w in ws)}

    # a square core with 3 beyond (4 of 7): the larger side of its bridge, not flagged for it
    assert core_flagged([[0, 1], [1, 2], [2, 3], [0, 3], [3, 4], [4, 5], [5, 6]], 7) == set()
    # a triangle with two tails of 2 (3 of 7, but no bridge has more than 2 beyond it): not flagged either
    assert core_flagged([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [0, 5], [5, 6]], 7) == set()
    # one tail of 4 beyond a triangle and a pendant elsewhere: 4 of 8 is not more than half
    assert core_flagged([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [0, 7]], 8) == set()
    # a tail of 5 beyond it (5 of 9): flagged, and only the core's cameras carry that reason, naming the tail's bridge
    # (not the pendant's)
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [6, 7], [0, 8]])
    assert core_flagged(E, 9) == {0, 1, 2}
    fl = graph_flags(E, 9, np.ones(len(E), bool), ~bridges(E, 9), np.zeros(len(E), bool), NAMES)
    assert "5 of the 9 cameras of its component hang off its block (the largest that cycles join, 3 cameras) " \
           "through the bridge pair (c2, c3)" in fl.cameras[0][0]
    # two components at once: each core judged on its own (the second, 0-8 above shifted by 9, flagged; the first a
    # square of 4 with 3 beyond, not)
    E2 = np.r_[[[0, 1], [1, 2], [2, 3], [0, 3], [3, 4], [4, 5], [5, 6]], E + 9]
    names = [f"c{k}" for k in range(18)]
    fl = graph_flags(E2, 18, np.ones(len(E2), bool), ~bridges(E2, 18), np.zeros(len(E2), bool), names)
    flagged = {k for k, ws in fl.cameras.items() if any("hang off its block" in w for w in ws)}
    assert flagged == {9, 10, 11} and "through the bridge pair (c11, c12)" in fl.cameras[9][0]


def test_rejected_pairs_and_the_cameras_considered():
    E = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [2, 3], [1, 3], [3, 4]])
    kept = np.array([1, 1, 1, 1, 1, 0, 0], bool)
    rej = np.array([0, 0, 0, 0, 0, 1, 1], bool)
    fl = graph_flags(E, 5, kept, kept.copy(), rej, NAMES)
    assert "1 of its 3 pairs disagree" in fl.cameras[1][0]
    assert any("2 of its 4 pairs disagree" in w for w in fl.cameras[3])
    assert 4 not in fl.cameras  # no kept pair: not solved, reported as left out by the stage
    fl = graph_flags(E, 5, kept, kept.copy(), rej, NAMES, cameras=np.array([1, 1, 1, 0, 0], bool))
    assert set(fl.cameras) == {1} and fl.n_cycles == 1
    fl = graph_flags(E, 5, kept, np.zeros(7, bool), rej, NAMES, cycles_checked=False)
    assert not any("unconfirmed" in w for v in fl.cameras.values() for w in v) and not fl.messages


def test_a_camera_with_a_pair_confirmed_only_by_cycles_that_close_wide_is_flagged_naming_it():
    # two triangles sharing camera 2: 0-1-2 confirmed at 0.4°, 2-3-4 only at 6.3° and 7.0°
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [2, 4]])
    kept = np.ones(6, bool)
    cd = np.array([0.4, 0.4, 0.4, 6.3, 7.0, 6.3])
    fl = graph_flags(E, 5, kept, kept.copy(), np.zeros(6, bool), NAMES, confirm_deg=cd, confirm_max_deg=5.0)
    assert set(fl.cameras) == {2, 3, 4}  # camera 2 too: two of its pairs are loose, though one of 0-1-2 is tight
    assert fl.cameras[3] == ["2 of its pairs (c2, c3), (c3, c4) are confirmed only loosely (the tightest cycle "
                             "through each closes at 6.3°, 7.0°, > 5°): such a pair may be degrees off and pull "
                             "this rotation"]
    assert fl.cameras[2][0].startswith("2 of its pairs (c2, c3), (c2, c4) are")
    # at a wider tolerance, or without the figures, nothing is flagged; one loose pair is named alone
    assert not graph_flags(E, 5, kept, kept.copy(), np.zeros(6, bool), NAMES, confirm_deg=cd,
                           confirm_max_deg=7.5).cameras
    assert not graph_flags(E, 5, kept, kept.copy(), np.zeros(6, bool), NAMES).cameras
    fl = graph_flags(E, 5, kept, kept.copy(), np.zeros(6, bool), NAMES, confirm_deg=cd, confirm_max_deg=6.5)
    assert set(fl.cameras) == {3, 4} and fl.cameras[4] == [
        "its pair (c3, c4) is confirmed only loosely (the tightest cycle through it closes at 7.0°, > 6.5°): such a "
        "pair may be degrees off and pull this rotation"]
    # an unconfirmed pair is not "loosely confirmed": its cameras keep their own reason
    conf = np.array([1, 1, 1, 0, 0, 0], bool)
    fl = graph_flags(E, 5, kept, conf, np.zeros(6, bool), NAMES, confirm_deg=np.where(conf, cd, np.inf))
    assert all("loosely" not in w for v in fl.cameras.values() for w in v)
    assert all(any("unconfirmed" in w for w in fl.cameras[k]) for k in (3, 4))
    # the pairs of the cameras asked about only: (3, 4) is not one, so camera 3 is flagged for its lone pair alone
    fl = graph_flags(E, 5, kept, kept.copy(), np.zeros(6, bool), NAMES, cameras=np.array([1, 1, 1, 1, 0], bool),
                     confirm_deg=cd, confirm_max_deg=6.5)
    assert set(fl.cameras) == {3} and not any("loosely" in w for w in fl.cameras[3])


def test_a_scene_whose_cycles_close_wider_than_its_pairs_claim_says_so():
    from pipeline.graph.checks import ViewGraphConfig
    from pipeline.graph.stage import overconfidence_message

    cfg = ViewGraphConfig()  # h_inflation 3: κ up to 3 is what the checks assume
    assert overconfidence_message(1.0, cfg) == overconfidence_message(9.0, cfg) == []
    assert overconfidence_message(None, cfg) == overconfidence_message(float("nan"), cfg) == []
    (msg,) = overconfidence_message(16.0, cfg)
    assert msg.startswith("the pairs' short cycles close 4.0× wider than their two-view precisions (H) claim, beyond "
                          "the 3× the checks assume") and "(to at most 10°)" in msg
    assert overconfidence_message(16.0, ViewGraphConfig(h_inflation=4.5)) == []


TAIL = [[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6]]  # a triangle and a tail of 4: 4 of 7


def _minor(E, n, cameras=None):
    E = np.asarray(E)
    fl = graph_flags(E, n, np.ones(len(E), bool), ~bridges(E, n), np.zeros(len(E), bool), NAMES, cameras=cameras)
    return {k: w for k, ws in fl.cameras.items() for w in ws if "hang off its block" in w}


def test_the_named_bridge_is_the_one_into_the_largest_piece_not_the_first_listed():
    E = [[0, 8], [0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [6, 7]]  # the pendant's pair listed first
    flagged = _minor(E, 9)
    assert set(flagged) == {0, 1, 2} and "through the bridge pair (c2, c3)" in flagged[0]


def test_the_cameras_considered_decide_the_sides_of_a_bridge():
    assert set(_minor(TAIL, 7)) == {0, 1, 2}
    assert _minor(TAIL, 7, cameras=np.array([1, 1, 1, 1, 1, 1, 0], bool)) == {}  # 3 of 6: not more than half
    # a tail of 5 (5 of 8) cut at its first camera: the triangle is a component of its own, nothing hangs off it
    long_tail = TAIL + [[6, 7]]
    assert set(_minor(long_tail, 8)) == {0, 1, 2}
    assert not set(_minor(long_tail, 8, cameras=np.array([1, 1, 1, 0, 1, 1, 1, 1], bool))) & {0, 1, 2}
    # a triangle 0-1-7 and a 5-cycle 0-1-4-3-2 through its pair (0, 1), c6 off 4, c5 off 2: without c3 the
    # two halves of the 5-cycle (2, 5 and 4, 6) hang off the triangle apart, 2 of 7 each
    E = [[0, 1], [0, 2], [0, 7], [1, 4], [1, 7], [2, 3], [2, 5], [3, 4], [4, 6]]
    assert _minor(E, 8, cameras=np.array([1, 1, 1, 0, 1, 1, 1, 1], bool)) == {}


def test_a_forest_has_no_core_to_flag():
    """A tree's 'core' is an arbitrary single camera (the lowest label): no block is joined by cycles."""
    for E in ([[0, 1], [1, 2], [2, 3]], [[0, 1], [1, 2], [1, 3]], [[0, 3], [1, 3], [2, 3]]):
        assert _minor(E, 4) == {}, E
    # the tail cut off by the cameras considered is a tree of its own
    assert _minor(TAIL, 7, cameras=np.array([1, 1, 1, 0, 1, 1, 1], bool)) == {}


def _blocks_joined_by_bridges(sizes, rng):
    """Cycles of the given sizes (1: a lone camera) joined into a tree by one random bridge each; the edges and the
    bridges' indices."""
    E, first = [], []
    for s in sizes:
        c0 = first[-1] + sizes[len(first) - 1] if first else 0
        first.append(c0)
        E += [[c0 + k, c0 + (k + 1) % s] for k in range(s)] if s > 2 else []
    bridge_at = []
    for b in range(1, len(sizes)):
        a = int(rng.integers(b))
        bridge_at.append(len(E))
        E.append([first[a] + int(rng.integers(sizes[a])), first[b] + int(rng.integers(sizes[b]))])
    return np.array(E), np.array(bridge_at, np.int64), first[-1] + sizes[-1]


def _flagged_names(E, n, bridged=None, perm=None, order=None):
    perm = np.arange(n) if perm is None else perm
    order = np.arange(len(E)) if order is None else order
    names = [""] * n
    for k in range(n):
        names[perm[k]] = f"c{k}"
    Ep = np.sort(perm[E], axis=1)[order]
    kept = np.ones(len(E), bool)
    fl = graph_flags(Ep, n, kept, ~bridges(Ep, n), np.zeros(len(E), bool), names,
                     bridged=None if bridged is None else bridged[order])
    return {names[k] for k in fl.cameras}


def test_which_cameras_are_flagged_does_not_depend_on_their_labels():
    """Which of equally large blocks was the core (the reference the others hang off, unflagged) went by the lowest
    label, so relabelling the cameras of one graph flagged different ones: every such block is flagged now."""
    # two triangles joined by a bridge: each takes half of its error, whichever is listed first
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [3, 5]])
    assert _flagged_names(E, 6) == {f"c{k}" for k in range(6)}
    fl = graph_flags(E, 6, np.ones(7, bool), ~bridges(E, 6), np.zeros(7, bool), NAMES)
    assert fl.cameras[0] == ["its block is one of 2 equally large ones that cycles join in its component (3 cameras "
                             "each), joined only through bridges (from this one, (c2, c3)): no block is the reference "
                             "the others hang off, and an error in such a pair moves this block and cannot be "
                             "detected"]
    # a 4-cycle and a triangle: the 4-cycle is the reference, whatever the labels
    E4 = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [5, 6], [3, 6]])
    rng = np.random.default_rng(0)
    for _ in range(5):
        assert _flagged_names(E4, 7, perm=rng.permutation(7)) == {"c0", "c1", "c2"}
    # random trees of cycles, with ties, relabelled and their pairs listed in another order
    n_tied = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        sizes = rng.choice([1, 3, 3, 4, 5], size=int(rng.integers(2, 7)))
        E, at, n = _blocks_joined_by_bridges(list(sizes), rng)
        bridged = np.zeros(len(E), bool)
        bridged[at[rng.random(len(at)) < 0.3]] = True
        want = _flagged_names(E, n, bridged)
        n_tied += int(np.sum(sizes == sizes.max()) > 1 and sizes.max() > 1)
        for _ in range(3):
            got = _flagged_names(E, n, bridged, rng.permutation(n), rng.permutation(len(E)))
            assert got == want, (seed, sizes.tolist())
    assert n_tied >= 15


def test_pairs_kept_to_join_a_part_are_judged_in_their_own_component():
    """The largest part left without the bridged pairs was taken over the whole graph, so a second component with no
    such pair was flagged whole, 'joined to the rest only through 0 pair(s)'."""
    # component 1: a triangle, a bridged pair, a bow tie of five; component 2: a triangle off a 5-camera block
    E = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [3, 5], [5, 14], [14, 15], [5, 15],
                  [6, 7], [7, 8], [6, 8], [8, 9], [9, 10], [10, 11], [9, 11], [11, 12], [12, 13], [9, 13]])
    bridged = np.zeros(len(E), bool)
    bridged[3] = True
    names = [f"c{k}" for k in range(16)]
    fl = graph_flags(E, 16, np.ones(len(E), bool), ~bridges(E, 16), np.zeros(len(E), bool), names, bridged=bridged)
    assert set(fl.cameras) == {0, 1, 2, 6, 7, 8}
    assert all(any("kept so that its part of the graph is not lost: (c2, c3)" in w for w in fl.cameras[k])
               for k in (0, 1, 2))
    # two equal parts joined by a bridged pair: neither is the reference
    E2 = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5], [3, 5]])
    b2 = np.zeros(7, bool)
    b2[3] = True
    fl = graph_flags(E2, 6, np.ones(7, bool), ~bridges(E2, 6), np.zeros(7, bool), NAMES, bridged=b2)
    assert all(any("kept so that its part" in w for w in fl.cameras[k]) for k in range(6))
