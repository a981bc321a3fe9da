"""The Dask executor: the same outputs as the serial path, a cluster reached by address, a clean shutdown.

The cluster of the main test is started *before* the code under test and reached
by its address, the way ``--scheduler ADDRESS`` reaches a user's cluster.
"""

from __future__ import annotations

import logging
import multiprocessing.resource_tracker
import os
from pathlib import Path

import distributed  # a hard dependency (dask[distributed]): imported, never skipped
import numpy as np
import psutil
import pytest

from pipeline.core.dask_executor import client_session
from pipeline.core.errors import PipelineError
from pipeline.core.parallel import balanced_chunk_size, make_executor
from pipeline.core.store import ItemStore, compute_missing
from pipeline.frontend.feature_stage import FeaturesStage
from pipeline.frontend.features import FeatureConfig
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.matching_stage import MatchingStage
from pipeline.geometry.ba_solver import BAConfig
from pipeline.geometry.ba_stage import TwoViewBAStage
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.geometry.two_view_stage import TwoViewStage
from pipeline.synthetic.render import SceneConfig, render_scene


SCENE = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


def _square(x: int) -> int:
    return x * x


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("item 3 is bad")
    return x


def _results_of(tasks: list[int]) -> list[dict[str, np.ndarray]]:
    return [{"square": np.array(t * t)} for t in tasks]


def _profiling(*_: object) -> bool:
    import dask

    return bool(dask.config.get("distributed.worker.profile.enabled"))


def _worker_env(_: int) -> tuple[int, str, int]:
    import cv2

    return os.getpid(), os.environ.get("OMP_NUM_THREADS", ""), cv2.getNumThreads()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(n_views=5, seed=4, out=tmp_path_factory.mktemp("scene"), config=SCENE)


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as c:
        yield c


def _run_stages(scene, work: Path, **executor) -> None:
    # chunks of 2 pairs: several tasks per stage, so that both workers take part
    FeaturesStage(work, FeatureConfig(**executor), images=scene.out, K_path=scene.out / "cameras.txt",
                  progress=False).run()
    MatchingStage(work, MatchingConfig(chunk_size=2, **executor), progress=False).run()
    TwoViewStage(work, TwoViewConfig(chunk_size=2, progress=False, **executor)).run()
    TwoViewBAStage(work, BAConfig(chunk_size=2, progress=False, **executor)).run()


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _items(folder: Path) -> dict[str, dict[str, np.ndarray]]:
    store = ItemStore(folder)
    return {k: store.get(k) for k in store.load_index()}


def test_dask_by_address_gives_the_serial_outputs(scene, cluster, tmp_path):
    _run_stages(scene, tmp_path / "serial", executor="serial")
    with distributed.Client(cluster.scheduler_address) as client, distributed.get_task_stream(client) as stream:
        _run_stages(scene, tmp_path / "dask", scheduler=cluster.scheduler_address)
    # the cluster did the work: tasks of every per-item stage, on both of its workers
    done = [t for t in stream.data if any(s.get("action") == "compute" for s in t.get("startstops", ()))]
    assert len(done) >= 8 and len({t["worker"] for t in done}) == 2, [t.get("key") for t in done]
    for store in ("features", "matches"):  # per image, per pair: bit for bit
        a, b = _items(tmp_path / "serial" / store), _items(tmp_path / "dask" / store)
        assert list(a) == list(b)
        for k in a:
            assert a[k].keys() == b[k].keys()
            for name in a[k]:
                np.testing.assert_array_equal(a[k][name], b[k][name], err_msg=f"{store} {name}")
    for out in ("two_view.npz", "two_view_corr.npz", "viewgraph.npz"):
        a, b = _arrays(tmp_path / "serial" / out), _arrays(tmp_path / "dask" / out)
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{out} {name}")
    vg = _arrays(tmp_path / "dask" / "viewgraph.npz")
    assert len(vg["edges"]) >= 8 and "H" in vg  # 5 views: most of the 10 pairs overlap


def test_workers_of_an_existing_cluster_run_single_threaded_and_in_order(cluster):
    ex = make_executor(2, "processes", cluster.scheduler_address)
    with ex:
        assert ex.workers == 2
        assert list(ex.map(_square, range(20))) == [x * x for x in range(20)]
        env = set(ex.map(_worker_env, range(8)))
    assert {(omp, n) for _, omp, n in env} == {("1", 1)}
    assert len(cluster.scheduler_info["workers"]) == 2  # an external cluster outlives the executor


def test_each_reports_every_item_once_without_fetching_its_result_and_raises_a_task_error(cluster):
    with make_executor(2, "processes", cluster.scheduler_address) as ex:
        got = list(ex.each(_square, range(12)))
        assert sorted(i for i, _ in got) == list(range(12)) and {r for _, r in got} == {None}
        with pytest.raises(ValueError, match="item 3 is bad"):
            list(ex.each(_fail_on_three, range(6)))
        assert list(ex.map(_square, range(4))) == [0, 1, 4, 9]  # the executor is still usable
    for backend in ("serial", "threads"):  # results that cost nothing to fetch come with their index
        with make_executor(2, backend) as ex:
            assert sorted(ex.each(_square, range(5))) == [(i, i * i) for i in range(5)]


def test_a_dask_cluster_gets_enough_tasks_for_every_worker(cluster, tmp_path):
    # at most chunk_size items per task, fewer when that would leave a worker fewer than 16 tasks
    assert [balanced_chunk_size(120, 32, 2), balanced_chunk_size(2300, 32, 2), balanced_chunk_size(2300, 32, 16),
            balanced_chunk_size(5, 8, 1), balanced_chunk_size(0, 8, 2)] == [4, 32, 9, 1, 1]
    store = ItemStore(tmp_path / "store")
    keys = [f"{i:020x}" for i in range(40)]
    n = compute_missing(store, keys, lambda k: k, _results_of, chunk_size=32, backend="dask",
                        scheduler=cluster.scheduler_address)
    assert n == 40 and len(list((tmp_path / "store").glob("chunk-*.npz"))) == 20  # 2 items per task on 2 workers
    store.write_index(keys)
    assert [int(store.get(k)["square"]) for k in keys] == [i * i for i in range(40)]


def test_stages_of_a_session_share_one_client_closed_at_its_end(cluster):
    address = cluster.scheduler_address
    with client_session():
        with make_executor(2, "processes", address) as a:
            assert list(a.map(_square, range(6))) == [x * x for x in range(6)]
        with make_executor(2, "processes", address) as b:  # the next stage: the same, still open, client
            assert b.client is a.client and b.client.status == "running"
            assert {(omp, n) for _, omp, n in b.map(_worker_env, range(4))} == {("1", 1)}
    assert a.client.status == "closed"
    with make_executor(2, "processes", address) as c:  # outside a session: a client of its own
        assert c.client is not a.client
    assert c.client.status == "closed" and len(cluster.scheduler_info["workers"]) == 2


def test_local_cluster_leaves_no_process_and_no_scratch_space(tmp_path, monkeypatch, caplog):
    from pipeline.core.dask_executor import DaskExecutor

    caplog.set_level(logging.INFO)  # as run.py logs: the cluster's start and shutdown add no INFO lines
    monkeypatch.chdir(tmp_path)
    # multiprocessing's resource tracker, started once per process by the first pool or cluster, outlives
    # both by design: start it first, so that it is there before and after whichever test runs first
    multiprocessing.resource_tracker.ensure_running()
    me = psutil.Process()
    before = {p.pid for p in me.children(recursive=True)}
    with pytest.raises(KeyboardInterrupt):
        with DaskExecutor(workers=2) as ex:
            pids = set(ex.map(lambda _: os.getpid(), range(6)))
            assert len(ex.client.scheduler_info()["workers"]) == 2
            # the local cluster's workers run without the statistical profiler (no dashboard to show it)
            assert set(ex.client.run(_profiling).values()) == {False}
            # Ctrl-C reaches the workers too: they ignore it (no traceback of theirs), the client closes the cluster
            assert set(ex.client.run(_sigint_disposition, 0).values()) == {"ignored"}
            raise KeyboardInterrupt  # Ctrl-C in the middle of a run
    alive = [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
    assert not alive
    assert {p.pid for p in me.children(recursive=True)} - before == set()
    assert list(tmp_path.iterdir()) == []  # no dask-scratch-space in the working folder
    chatter = [r.getMessage() for r in caplog.records if r.name.startswith("distributed") and r.levelno < logging.WARNING]
    assert not chatter, chatter[:3]


def test_unreachable_scheduler_is_one_line_before_any_stage(tmp_path, monkeypatch, capsys):
    from pipeline.core import dask_executor
    from pipeline.run import main_cli

    with pytest.raises(PipelineError, match=r"cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'"):
        dask_executor.check_scheduler("tcp://127.0.0.1:9", timeout=1)
    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT_S", 1)
    assert main_cli(["--scheduler", "tcp://127.0.0.1:9", "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "cannot reach the Dask scheduler" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "work").exists()


def _sigint_disposition(_: int) -> str:
    import signal  # noqa: PLC0415

    return "ignored" if signal.getsignal(signal.SIGINT) == signal.SIG_IGN else "handled"


def test_process_workers_ignore_ctrl_c_and_the_parent_keeps_it():
    """Ctrl-C reaches the whole process group: the workers ignore it (no traceback of theirs; the parent stops the
    pool and says so in one line), and the parent's own Ctrl-C handling is back once the workers are started."""
    import signal  # noqa: PLC0415

    before = signal.getsignal(signal.SIGINT)
    with make_executor(2, "processes") as ex:
        assert set(ex.map(_sigint_disposition, range(4))) == {"ignored"}
        assert signal.getsignal(signal.SIGINT) is before
