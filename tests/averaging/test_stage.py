"""The averaging stage under the stage contract: reuse, recompute on a changed input, heal a damaged cache."""

from __future__ import annotations

import json
import logging
import os

import numpy as np
import pytest

from pipeline.averaging import solve
from pipeline.averaging.cli import main, main_cli
from pipeline.averaging.registry import parse_method
from pipeline.averaging.stage import AveragingStage, run_averaging
from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.stage import fingerprint_of, output_digest


@pytest.fixture
def six(tmp_path):
    """A view graph of 6 cameras (1° noise) saved as .npz, and its true rotations."""
    rng = np.random.default_rng(5)
    R = so3.random_rotations(6, rng)
    e = np.array([(i, j) for i in range(6) for j in range(i + 1, 6)])
    vg = ViewGraph.from_absolute([f"cam{i}.jpg" for i in range(6)], R, e)
    vg = ViewGraph(vg.names, vg.edges, so3.exp(np.deg2rad(1.0) * rng.standard_normal((vg.n_edges, 3))) @ vg.R_rel,
                   inliers=rng.integers(50, 100, vg.n_edges))
    path = tmp_path / "viewgraph.npz"
    vg.save(path)
    return path, vg


@pytest.fixture
def calls(monkeypatch):
    n = {"average": 0}
    real = solve.average

    def counted(*a, **k):
        n["average"] += 1
        return real(*a, **k)

    monkeypatch.setattr(solve, "average", counted)
    return n


def _run(folder, token, vg_path, overwrite=False):
    return run_averaging(folder, parse_method(token), vg_path, overwrite)


def test_outputs_record_and_reuse(six, tmp_path, calls):
    path, vg = six
    out = tmp_path / "rotations"
    res = _run(out, "irls", path)
    assert calls["average"] == 1 and not res["record"].reused
    assert sorted(p.name for p in out.iterdir()) == ["irls-l0.5.json", "irls-l0.5.record.json", "irls-l0.5.txt"]
    assert res["stats"]["n_cameras"] == 6 and res["stats"]["options"]["loss"] == "l0.5"
    assert oct((out / "irls-l0.5.txt").stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    mtime = (out / "irls-l0.5.txt").stat().st_mtime_ns
    again = _run(out, "irls", path)
    assert calls["average"] == 1 and again["record"].reused and again["stats"] == res["stats"]
    assert (out / "irls-l0.5.txt").stat().st_mtime_ns == mtime
    _run(out, "irls", path, overwrite=True)
    assert calls["average"] == 2


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_each_method_has_its_own_record(six, tmp_path, calls):
    path, _ = six
    out = tmp_path / "rotations"
    for token in ("irls", "irls-huber", "weiszfeld", "l1"):
        _run(out, token, path)
    assert calls["average"] == 4
    for token in ("irls", "irls-huber", "weiszfeld", "l1"):
        assert _run(out, token, path)["record"].reused
    assert calls["average"] == 4


def test_result_options_and_inputs_recompute_runtime_options_do_not(six, tmp_path, calls):
    path, vg = six
    out = tmp_path / "rotations"
    _run(out, "irls", path)
    run_averaging(out, parse_method("irls", options={"alpha_deg": 4.0}), path)  # same label, new option
    assert calls["average"] == 2
    # the view graph's content is the input: a new graph recomputes, a rewritten identical one does not
    vg.save(path)
    _run(out, "irls", path)  # back to alpha_deg 5 → recompute once
    assert calls["average"] == 3
    _run(out, "irls", path)
    assert calls["average"] == 3
    ViewGraph(vg.names, vg.edges, vg.R_rel[::-1].copy(), inliers=vg.inliers).save(path)
    _run(out, "irls", path)
    assert calls["average"] == 4
    # a runtime option (the SDP solver's log) never enters the fingerprint
    a = AveragingStage(out, parse_method("sdp-cso3-iso"), path)
    b = AveragingStage(out, parse_method("sdp-cso3-iso", options={"solver_log": True}), path)
    c = AveragingStage(out, parse_method("sdp-cso3-iso", options={"eps_rel": 1e-7}), path)
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()


def _cut_same_size(path, keep: int) -> None:
    """Keep the first ``keep`` cameras and pad with a comment to the original byte size (a size check passes)."""
    names, R = read_rotations(path)
    size = path.stat().st_size
    write_rotations(path, names[:keep], R[:keep])
    pad = size - path.stat().st_size
    assert pad > 3
    with open(path, "a") as f:
        f.write("#" + "x" * (pad - 2) + "\n")
    assert path.stat().st_size == size


@pytest.mark.parametrize("damage", ["cut", "cut-same-size", "garbled", "not-a-rotation", "stats-cut", "record",
                                    "record-missing-output", "renamed-camera"])
def test_a_damaged_cache_is_recomputed_with_one_warning(six, tmp_path, calls, caplog, damage):
    path, vg = six
    out = tmp_path / "rotations"
    _run(out, "irls", path)
    rot, js, rec = out / "irls-l0.5.txt", out / "irls-l0.5.json", out / "irls-l0.5.record.json"
    text = rot.read_text()
    R_before = read_rotations(rot)[1]
    if damage == "cut":  # the case: a rotations file cut to 2 of 6 cameras
        rot.write_text("\n".join(text.splitlines()[:-4]) + "\n")
    elif damage == "cut-same-size":
        _cut_same_size(rot, 2)
    elif damage == "garbled":
        rot.write_bytes(bytes(range(256)) * (len(text) // 256) + b"\xff" * (len(text) % 256))
    elif damage == "not-a-rotation":
        rot.write_text(text.replace(" 0.", " 7.", 1) if " 0." in text else text.replace(" -0.", " -7.", 1))
    elif damage == "stats-cut":
        js.write_text(js.read_text()[:40])
    elif damage == "record":
        rec.write_text(rec.read_text()[:30])
    elif damage == "record-missing-output":
        js.unlink()
    elif damage == "renamed-camera":
        rot.write_text(text.replace("cam3.jpg", "cam9.jpg"))
    with caplog.at_level(logging.WARNING):
        again = _run(out, "irls", path)
    assert calls["average"] == 2, "a damaged cache must be recomputed, never reused"
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0].getMessage(), [r.getMessage() for r in warnings]
    assert "recomputing" in warnings[0].getMessage()
    names, R = read_rotations(again["rotations"])
    assert names == vg.names
    np.testing.assert_array_equal(R, R_before)  # the same result as before the damage
    assert again["stats"]["n_cameras"] == 6
    assert _run(out, "irls", path)["record"].reused  # healed


def test_same_size_cut_is_caught_by_its_checksum_and_by_verify(six, tmp_path, caplog):
    path, _ = six
    out = tmp_path / "rotations"
    _run(out, "irls", path)
    _cut_same_size(out / "irls-l0.5.txt", 2)
    with caplog.at_level(logging.WARNING):
        _run(out, "irls", path)
    assert "irls-l0.5.txt has changed since it was written (its CRC-32 is not the one recorded)" in caplog.text
    # and where the record's checksum agrees with the damaged file (written so by hand), verify still sees it
    _cut_same_size(out / "irls-l0.5.txt", 2)
    rec_path = out / "irls-l0.5.record.json"
    rec = json.loads(rec_path.read_text())
    rec["digests"]["irls-l0.5.txt"] = output_digest(out / "irls-l0.5.txt")
    rec_path.write_text(json.dumps(rec))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _run(out, "irls", path)
    assert "holds 2 camera(s) but the solved component" in caplog.text


def test_a_result_cached_with_nan_tokens_by_an_older_version_is_still_reused(six, tmp_path, calls):
    """Before its JSON was strict, the stage wrote a figure that is not finite as a NaN token (a certificate's
    undefined eigenvalue): such a cached result, recorded by that version (sizes and checksums of those bytes), is
    intact and reused, and its stats read back with NaN."""
    path, _ = six
    out = tmp_path / "rotations"
    _run(out, "irls", path)
    js, rec_path = out / "irls-l0.5.json", out / "irls-l0.5.record.json"
    stats = json.loads(js.read_text())
    stats.setdefault("certificate", {})["lambda_nontrivial"] = float("nan")
    js.write_text(json.dumps(stats, indent=2) + "\n")  # as the older writer wrote it
    assert '"lambda_nontrivial": NaN' in js.read_text()
    rec = json.loads(rec_path.read_text())
    rec["outputs"][js.name], rec["digests"][js.name] = js.stat().st_size, output_digest(js)
    rec_path.write_text(json.dumps(rec, indent=2) + "\n")
    again = _run(out, "irls", path)
    assert again["record"].reused and calls["average"] == 1
    assert np.isnan(again["stats"]["certificate"]["lambda_nontrivial"])


def test_disconnected_graph_solved_component_is_what_verify_expects(tmp_path, calls):
    R = so3.random_rotations(6, np.random.default_rng(1))
    vg = ViewGraph.from_absolute(list("abcdef"), R, [[0, 1], [1, 2], [0, 2], [3, 4]], allow_isolated=True)
    p = tmp_path / "d.npz"
    vg.save(p)
    res = _run(tmp_path / "rot", "irls", p)
    assert read_rotations(res["rotations"])[0] == ["a", "b", "c"] and res["stats"]["dropped_names"] == ["d", "e", "f"]
    assert _run(tmp_path / "rot", "irls", p)["record"].reused and calls["average"] == 1


def test_upstream_record_is_the_input(six, tmp_path):
    path, _ = six
    stage = AveragingStage(tmp_path / "rot", parse_method("irls"), path, upstream=("viewgraph", tmp_path, None))
    with pytest.raises(InputFileError, match="has no result of the 'viewgraph' stage"):
        stage.inputs()
    from pipeline.core.atomic import write_json

    write_json(tmp_path / "viewgraph.record.json", {"format": "rotavg-stage-record", "stage": "viewgraph",
                                                    "version": 1, "fingerprint": "abc", "inputs": {},
                                                    "outputs": {}})
    assert stage.inputs() == {"viewgraph": "abc"}
    assert stage.fingerprint() == fingerprint_of(
        fingerprint_of("averaging", AveragingStage.version, parse_method("irls").config.fingerprint(),
                       [("viewgraph", "abc")]), "irls")


# ------------------------------------------------------------------ the command
def test_command_reuses_and_heals_too(six, tmp_path, calls, capsys):
    path, vg = six
    out = tmp_path / "r.txt"
    assert main_cli([str(path), "--out", str(out), "-q"]) == 0
    assert main_cli([str(path), "--out", str(out), "-q"]) == 0
    assert calls["average"] == 1
    _cut_same_size(out, 2)
    assert main_cli([str(path), "--out", str(out), "-q"]) == 0
    assert calls["average"] == 2 and read_rotations(out)[0] == vg.names
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("r.")) == ["r.json", "r.record.json", "r.txt"]


def test_command_init_file_is_an_input(six, tmp_path, calls):
    path, vg = six
    R0 = read_rotations(_run(tmp_path / "a", "l1", path)["rotations"])[1]
    init = tmp_path / "init.txt"
    write_rotations(init, vg.names, R0)
    out = tmp_path / "r.txt"
    main(path, out, init=init, l1_iterations=0)
    main(path, out, init=init, l1_iterations=0)
    assert calls["average"] == 2  # l1 once, irls once
    write_rotations(init, vg.names, R0 @ so3.exp(np.full((6, 3), 0.01)))
    main(path, out, init=init, l1_iterations=0)
    assert calls["average"] == 3


def test_command_reads_yaml_options_and_flags_override_them(six, tmp_path):
    path, _ = six
    cfg = tmp_path / "c.yaml"
    cfg.write_text("averaging:\n  alpha_deg: 3\n  irls:\n    loss: huber\nsdp:\n  eps_abs: 1.0e-6\n")
    out = tmp_path / "r.txt"
    assert main_cli([str(path), "--config", str(cfg), "--out", str(out), "-q"]) == 0
    stats = json.loads(out.with_suffix(".json").read_text())
    assert stats["options"]["loss"] == "huber" and stats["options"]["alpha_deg"] == 3.0
    assert main_cli([str(path), "--config", str(cfg), "--loss", "cauchy", "--out", str(out), "-q"]) == 0
    assert json.loads(out.with_suffix(".json").read_text())["options"]["loss"] == "cauchy"


@pytest.mark.parametrize("argv, message", [
    (["--config", "BAD"], "error: [averaging]: unknown key(s) ['alpah_deg']; allowed keys are ["),
    (["--method", "sdp", "--loss", "l2"], "error: [averaging.sdp]: unknown key(s) ['loss']; allowed keys are ["),
    (["--method", "sdp-so4"], "error: unknown method 'sdp-so4': unknown SDP variant 'so4'"),
    (["--max-iterations", "many"], "error: [averaging.irls] max_iterations='many' but expected an integer"),
    (["--method", "sdp", "--init", "INIT"], "error: method 'sdp' takes no start; drop --init"),
    (["--out", "r.json"], "error: --out"),
])
def test_command_errors_are_one_line(six, tmp_path, capsys, argv, message):
    path, vg = six
    bad = tmp_path / "bad.yaml"
    bad.write_text("averaging:\n  alpah_deg: 3\n")
    init = tmp_path / "init.txt"
    write_rotations(init, vg.names, so3.random_rotations(6, np.random.default_rng(0)))
    argv = [str(bad) if a == "BAD" else str(init) if a == "INIT" else a for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "r.txt")]
    assert main_cli([str(path), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(message) and "\n" not in err, err
    assert not (tmp_path / "r.txt").exists()
