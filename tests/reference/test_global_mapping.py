"""pipeline.reference.global_mapping: pycolmap's global SfM (GLOMAP) as a peer, beside the incremental reference."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline import reference  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import summarize  # noqa: E402
from pipeline.reference import global_mapping as glomap  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

SMALL = SceneConfig(width=320, height=240, focal=280.0, supersample=1)


@pytest.fixture(scope="session")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("glomap_scene")
    render_scene(6, 0, out, config=SMALL)
    return out


@pytest.fixture(scope="session")
def peers(scene, tmp_path_factory) -> Path:
    """The incremental reference, then GLOMAP on its database (as run.py runs them)."""
    out = tmp_path_factory.mktemp("peers")
    reference.main(scene, out / "reference", progress=False)
    glomap.main(scene, out / "reference-global", database_dir=out / "reference", progress=False)
    return out


def _tables(db: Path) -> list[str]:
    con = sqlite3.connect(db)
    try:
        return [hashlib.sha1(repr(con.execute(f"SELECT * FROM {t}").fetchall()).encode()).hexdigest()
                for t in ("cameras", "images", "keypoints", "matches", "two_view_geometries")]
    finally:
        con.close()


@pytest.mark.slow
def test_glomap_registers_every_image_with_the_known_K_fixed(scene, peers):
    import pycolmap

    res = glomap.load_global_reference(peers / "reference-global")
    s = res.info
    assert res.label == "glomap" and s["n_registered"] == 6 and s["unregistered"] == {}
    assert s["known_K"] is True and s["mapping"] == "global mapping (GLOMAP)"
    truth = read_reference(scene / "cameras.txt")
    R_ref, mask = match_reference(res.names, truth.names, truth.R)
    assert summarize(res.R, R_ref, mask)["median_deg"] < 0.5
    cams = list(pycolmap.Reconstruction(peers / "reference-global" / "model").cameras.values())
    np.testing.assert_allclose(cams[0].params, [280.0, 280.0, truth.K[0][0, 2] + 0.5, truth.K[0][1, 2] + 0.5],
                               atol=1e-9)


@pytest.mark.slow
def test_shares_the_incremental_database_and_never_writes_it(scene, peers, tmp_path, monkeypatch):
    import pycolmap

    inc, glo = reference.load_reference(peers / "reference"), glomap.load_global_reference(peers / "reference-global")
    assert glo.info["times"]["extract_s"] == inc.info["times"]["extract_s"]  # the same database, timed once
    assert not list((peers / "reference-global").glob("database-*"))
    db = next((peers / "reference").glob("database-*.db"))
    before = _tables(db)

    def boom(*a, **k):
        raise AssertionError("the shared database was rebuilt")

    monkeypatch.setattr(pycolmap, "extract_features", boom)
    out = tmp_path / "glo2"  # a new GLOMAP result from the same database: mapping only
    s = glomap.load_global_reference(glomap.main(scene, out, database_dir=peers / "reference", progress=False))
    assert s.info["n_registered"] == 6 and _tables(db) == before
    monkeypatch.setattr(pycolmap, "global_mapping", boom)
    glomap.main(scene, out, database_dir=peers / "reference", progress=False)  # intact result: reused


def test_a_cpu_build_of_pycolmap_maps_without_asking_for_a_gpu():
    """On a pycolmap built without CUDA, GLOMAP's global positioning and bundle adjustment run on the CPU either way;
    asked for the GPU they say so in two warnings on every run (``run.py -q`` printed them). With CUDA, the GPU
    options are left as pycolmap sets them."""
    import types

    import pycolmap

    for has_cuda in (False, True):
        seen: dict[str, object] = {}
        pc = types.SimpleNamespace(GlobalPipelineOptions=pycolmap.GlobalPipelineOptions, has_cuda=has_cuda,
                                   global_mapping=lambda db, images, out, opts: seen.update(opts=opts) or {})
        stage = types.SimpleNamespace(common_options=lambda o: o, fixed_intrinsics=lambda: False, images=Path("."))
        glomap.GlobalReferenceStage.map(stage, pc, Path("db"), Path("out"))
        mapper = seen["opts"].mapper
        default = pycolmap.GlobalPipelineOptions().mapper
        gpu = (mapper.global_positioning.use_gpu, mapper.bundle_adjustment.ceres.use_gpu)
        assert gpu == ((default.global_positioning.use_gpu, default.bundle_adjustment.ceres.use_gpu) if has_cuda
                       else (False, False))


def test_config_shares_the_database_options():
    rc = reference.ReferenceConfig(max_image_size=1000, num_threads=1)
    gc = glomap.GlobalReferenceConfig.sharing_database(rc, {"seed": 3})
    assert gc.max_image_size == 1000 and gc.num_threads == 1 and gc.seed == 3
    assert gc.database_options() == rc.database_options()
    from pipeline.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[global_reference\]: unknown key\(s\) \['nope'\]"):
        glomap.GlobalReferenceConfig.sharing_database(rc, {"nope": 1})


def test_help_and_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pipeline.reference.global_mapping", "--help"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and "--database-dir" in r.stdout and "--K" in r.stdout and not r.stderr
    r = subprocess.run([sys.executable, "-m", "pipeline.reference.global_mapping", "--images", str(tmp_path / "no"),
                        "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("error:") and len(r.stderr.strip().splitlines()) == 1
