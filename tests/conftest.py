from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout (a git worktree sits one level deeper)
SHARED_DATA = next((p / "shared" / "data" for p in REPO.parents if (p / "shared" / "data").is_dir()),
                   REPO.parent / "shared" / "data")


@pytest.fixture(autouse=True)
def _restore_logging():
    """In-process command lines reconfigure the root logger; give every test the same logging."""
    import logging

    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers


@pytest.fixture(scope="session")
def strict_json():
    """``parse(text)``: JSON read as a strict reader (jq, JavaScript, Go, serde) reads it: ``NaN``, ``Infinity`` and
    ``-Infinity`` are not JSON and raise ValueError (Python's ``json.loads`` takes them by default)."""
    import json

    def refuse(token: str) -> None:
        raise ValueError(f"{token} is not JSON")

    return lambda text: json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="session")
def damage_item():
    """``damage(store_dir, change, which=None) -> key``: rewrite the first stored item (in key order over the chunk
    files) that ``which(item)`` accepts, as ``change(fields)`` leaves its fields (a dict of arrays it may edit or
    delete from), in place: the chunk keeps its name and the store's index still places the item there, so only
    the item's contents are wrong."""
    import numpy as np

    from pipeline.core.store import ItemStore

    def damage(store_dir: Path, change, which=None) -> str:
        store = ItemStore(store_dir)
        for path in sorted(Path(store_dir).glob("chunk-*.npz")):
            items = store.read_chunk(path)
            for key, item in items.items():
                if which is None or which(item):
                    fields = {k: np.array(v) for k, v in item.items()}
                    change(fields)
                    assert store.write_chunk({**{k: dict(v) for k, v in items.items()}, key: fields}) == path
                    return key
        raise AssertionError(f"no item of {store_dir} to damage")

    return damage


@pytest.fixture
def rerun_with_a_damaged_item(damage_item, caplog):
    """``rerun(run, snapshot, store_dir, output, change, what)``: damage one accepted stored pair (``change``, as
    :func:`damage_item`), remove the stage's ``output`` and ``run()`` it again; asserts one warning naming one
    damaged pair (its message holds ``what``), only that pair's chunk of 2 recomputed, and ``snapshot()`` (a list of
    arrays) equal to the undamaged run's, bit for bit."""
    import logging

    import numpy as np

    def rerun(run, snapshot, store_dir: Path, output: Path, change, what: str) -> None:
        before = snapshot()
        damage_item(store_dir, change, which=lambda item: bool(item["ok"]))
        output.unlink()
        with caplog.at_level(logging.WARNING):
            rec = run()
        warned = [r.getMessage() for r in caplog.records if what in r.getMessage()]
        assert len(warned) == 1 and "1 pairs'" in warned[0] and "recomputed" in warned[0], warned
        assert rec.summary["n_computed"] == 2  # the damaged pair's chunk, no more
        for a, b in zip(before, snapshot()):
            np.testing.assert_array_equal(a, b)

    return rerun


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data``, read in place. Tests that need it skip, with the reason, when absent on a developer's
    machine; under CI (``CI`` set, as ``.ci/run`` runs beside ``../shared``) its absence is a failure, not a skip."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"shared data not found at {SHARED_DATA}: CI runs beside ../shared and must test with it")
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def fast_config(tmp_path_factory) -> Path:
    """A run.py config without plots, for the whole-chain tests."""
    p = tmp_path_factory.mktemp("cfg") / "fast.yaml"
    p.write_text("run:\n  plots: false\n")
    return p


# ----------------------------------------- a tiny rendered scene and a finished run on it
TINY_VIEWS = 6


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """6 rendered views of 240×180 pixels with their true cameras (``cameras.txt``)."""
    out = tmp_path_factory.mktemp("tiny_scene")
    from pipeline.synthetic.render import SceneConfig, render_scene

    render_scene(TINY_VIEWS, 0, out, config=SceneConfig(width=240, height=180, focal=210.0, supersample=1))
    return out


@pytest.fixture(scope="session")
def tiny_config(tmp_path_factory) -> Path:
    """run.py options for fast cases: IRLS only, no reference, no plots, no process pools."""
    p = tmp_path_factory.mktemp("tiny_cfg") / "tiny.yaml"
    p.write_text("run:\n  methods: [irls]\n  reference: false\n  plots: false\n"
                 "features:\n  workers: 1\nmatching:\n  workers: 1\n"
                 "two_view:\n  workers: 1\ntwo_view_ba:\n  workers: 1\n")
    return p


@pytest.fixture(scope="session")
def baseline(tiny_scene, tiny_config, tmp_path_factory) -> Path:
    """A finished ``run.py`` on the tiny scene (with ``--gt``): the OUT folder to copy, damage and re-run."""
    from pipeline import run

    out = tmp_path_factory.mktemp("baseline") / "out"
    t0 = time.perf_counter()
    run.main(tiny_scene, out, config=tiny_config, gt=tiny_scene / "cameras.txt", quiet=True, reference=False)
    assert (out / "metrics.json").is_file(), f"baseline run failed after {time.perf_counter() - t0:.1f} s"
    return out


@pytest.fixture
def run_copy(baseline, tmp_path) -> Path:
    """This test's own copy of the finished OUT folder (every stage up to date)."""
    return Path(shutil.copytree(baseline, tmp_path / "out", copy_function=shutil.copy2))
