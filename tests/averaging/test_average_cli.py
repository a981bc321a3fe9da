"""The averaging stage: main() and ``python -m pipeline.average``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.averaging.cli import main, main_cli
from pipeline.averaging.solve import average
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.core.viewgraph import ViewGraph


@pytest.fixture(scope="module")
def graph_file(tmp_path_factory):
    rng = np.random.default_rng(0)
    n = 12
    R = so3.random_rotations(n, rng)
    iu = np.array(np.triu_indices(n, 1)).T
    e = iu[(rng.random(len(iu)) < 0.6) | ((iu[:, 1] - iu[:, 0]) == 1)]
    vg = ViewGraph.from_absolute([f"img{i:02d}.jpg" for i in range(n)], R, e)
    Rrel = so3.exp(np.deg2rad(1.0) * rng.standard_normal((vg.n_edges, 3))) @ vg.R_rel
    vg = ViewGraph(vg.names, vg.edges, Rrel, inliers=rng.integers(20, 200, vg.n_edges))
    path = tmp_path_factory.mktemp("g") / "vg.npz"
    vg.save(path)
    return path, R, vg


def _err(R_est, R):
    G = so3.chordal_mean(np.swapaxes(R, 1, 2) @ R_est)
    return np.rad2deg(so3.angle_between(R_est, R @ G))


@pytest.mark.parametrize("method", ["irls", "l1", "weiszfeld"])
def test_cli_writes_rotations_and_stats(graph_file, tmp_path, method):
    path, R, vg = graph_file
    out, js = tmp_path / "rot.txt", tmp_path / "stats.json"
    rc = main_cli([str(path), "--method", method, "--out", str(out), "--json", str(js), "-q"])
    assert rc == 0
    names, Rest = read_rotations(out)
    assert names == vg.names
    assert _err(Rest, R).max() < 1.6  # every method moves well off its spanning-tree start (2.94° worst here)
    stats = json.loads(js.read_text())
    for key in ("time_s", "iterations", "n_cameras", "n_edges"):
        assert key in stats
    assert stats["n_cameras"] == 12 and stats["n_edges"] == vg.n_edges


def test_main_resumes_and_overwrites(graph_file, tmp_path):
    path, _, _ = graph_file
    out = tmp_path / "rot.txt"
    main(path, out, method="irls", loss="huber")
    mtime = out.stat().st_mtime_ns
    main(path, out, method="irls", loss="huber")
    assert out.stat().st_mtime_ns == mtime  # skipped: same configuration
    main(path, out, method="irls", loss="cauchy")
    assert out.stat().st_mtime_ns != mtime  # a new configuration recomputes
    mtime = out.stat().st_mtime_ns
    main(path, out, overwrite=True, method="irls", loss="cauchy")
    assert out.stat().st_mtime_ns != mtime


def test_init_from_file(graph_file, tmp_path):
    path, R, vg = graph_file
    init = tmp_path / "init.txt"
    write_rotations(init, vg.names, R)
    out = tmp_path / "rot.txt"
    rc = main_cli([str(path), "--init", str(init), "--l1-iterations", "0", "--out", str(out), "-q"])
    assert rc == 0
    _, Rest = read_rotations(out)
    assert _err(Rest, R).max() < 1.6  # every method moves well off its spanning-tree start (2.94° worst here)
    # the file's rotations are the start: with no iteration at all they come back (a start that is not the truth,
    # so that neither the default tree start nor the solution could pass for it)
    R0 = R @ so3.exp(np.deg2rad(5.0) * np.random.default_rng(3).standard_normal((len(R), 3)))
    write_rotations(init, vg.names, R0)
    out0 = tmp_path / "rot0.txt"
    rc = main_cli([str(path), "--init", str(init), "--l1-iterations", "0", "--max-iterations", "0", "--no-refine",
                   "--no-certify", "--out", str(out0), "-q"])
    assert rc == 0
    _, R_back = read_rotations(out0)
    assert _err(R_back, R0).max() < 1e-6 and _err(R_back, R).max() > 2.0


def test_cli_bad_loss_one_line_error(graph_file, tmp_path, capsys):
    path, _, _ = graph_file
    rc = main_cli([str(path), "--loss", "hubber", "--out", str(tmp_path / "r.txt")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("error: unknown loss 'hubber'") and "\n" not in err


def test_cli_missing_input(tmp_path, capsys):
    rc = main_cli([str(tmp_path / "none.npz"), "--out", str(tmp_path / "r.txt")])
    assert rc == 2
    assert "does not exist" in capsys.readouterr().err


def test_cli_init_file_missing_cameras(graph_file, tmp_path, capsys):
    path, R, vg = graph_file
    init = tmp_path / "init.txt"
    write_rotations(init, vg.names[:5], R[:5])
    rc = main_cli([str(path), "--init", str(init), "--out", str(tmp_path / "r.txt")])
    assert rc == 2
    assert "lacks initial rotations for 7 camera(s)" in capsys.readouterr().err


def test_cli_disconnected_reports_dropped(tmp_path):
    rng = np.random.default_rng(1)
    R = so3.random_rotations(6, rng)
    vg = ViewGraph.from_absolute(list("abcdef"), R, [[0, 1], [1, 2], [0, 2], [3, 4]], allow_isolated=True)
    p = tmp_path / "d.npz"
    vg.save(p)
    out, js = tmp_path / "r.txt", tmp_path / "s.json"
    assert main_cli([str(p), "--out", str(out), "--json", str(js), "-q"]) == 0
    names, _ = read_rotations(out)
    assert names == ["a", "b", "c"]
    assert json.loads(js.read_text())["dropped_names"] == ["d", "e", "f"]
    assert "dropped" in out.read_text().splitlines()[0]


def test_average_maps_user_init_of_full_graph(graph_file):
    _, R, vg = graph_file
    res = average(vg, init=R, l1_iterations=0)
    assert _err(res.R, R).max() < 3.0
    R0 = R @ so3.exp(np.deg2rad(5.0) * np.random.default_rng(4).standard_normal((len(R), 3)))
    res0 = average(vg, init=R0, l1_iterations=0, max_iterations=0, refine=False, certify=False)
    assert _err(res0.R, R0).max() < 1e-6 and _err(res0.R, R).max() > 2.0  # the user's start, mapped, is used
