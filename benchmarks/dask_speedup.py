"""The per-pair stages (matching + two-view + two-view BA) on a Dask cluster of 2 workers against 1 (issue 16).

A rendered scene (``--views`` views, all pairs) has its features extracted once.
Two local clusters are started first (1 and 2 single-threaded worker processes:
``pipeline.core.dask_executor.LocalDaskCluster``) and warmed up; startup is not
timed. Then, ``--repeats`` times, interleaved (1 worker, 2 workers, 1, 2, ...),
the three per-pair stages run on a fresh copy of the features, reaching the
cluster by its address as ``--scheduler`` does; the workers' per-process caches
(prepared descriptors, keypoints) are emptied before each run, so every run reads
its features from disk. Reported per run: wall time of the three stages, the load
average before and after (the machine is shared: read each ratio next to the
load), and whether the outputs are bit for bit those of the serial path (run
once, in this process). The speed-up is the ratio of the 1-worker to the 2-worker
wall time within each repeat; its median and every ratio are reported.

The machine is shared, and Linux gives each session (autogroup) a fair share of
the cores: when other sessions are busy, two processes of ours get no more CPU
than one. So every repeat also measures

- the machine's own ceiling at that moment: the throughput of two spinning
  processes against one (pure CPU, no Dask), ``ceiling``; a wall-time ratio can
  only exceed it by noise;
- the CPU seconds of the run: of this process (the client: assembling, writing)
  and of each worker (the tasks). ``cpu_speedup`` = (client + all workers' CPU with
  1 worker) / (client + the busiest worker's CPU with 2): the speed-up on two free
  cores if nothing else ran, i.e. how evenly the work is spread and how little
  of it is serial.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/dask_speedup.py [--views 16] [--width 1024] [--repeats 3] [--chunk-size 4]

Writes ``benchmarks/results/dask_speedup.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.dask_executor import DaskExecutor, LocalDaskCluster, client_session  # noqa: E402
from pipeline.frontend.feature_stage import FeaturesStage  # noqa: E402
from pipeline.frontend.features import FeatureConfig  # noqa: E402
from pipeline.frontend.matching import MatchingConfig  # noqa: E402
from pipeline.frontend.matching_stage import MatchingStage  # noqa: E402
from pipeline.geometry.ba_solver import BAConfig  # noqa: E402
from pipeline.geometry.ba_stage import TwoViewBAStage  # noqa: E402
from pipeline.geometry.ransac import TwoViewConfig  # noqa: E402
from pipeline.geometry.two_view_stage import TwoViewStage  # noqa: E402
from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "dask_speedup.json"
OUTPUTS = ("two_view.npz", "two_view_corr.npz", "viewgraph.npz")
FEATURE_FILES = ("features.json", "features.record.json", "features")


def clear_worker_caches() -> None:
    """Empty this process's caches of prepared descriptors and keypoints (run on every worker)."""
    from pipeline.frontend import matching_stage  # noqa: PLC0415
    from pipeline.geometry import two_view_stage  # noqa: PLC0415

    matching_stage._PREPARED.items.clear()
    two_view_stage._raw_keypoints.cache_clear()
    two_view_stage._match_chunk.cache_clear()


def _spin(seconds: float) -> int:
    """Busy-loop for ``seconds`` of wall time; returns the iterations done."""
    n, end = 0, time.perf_counter() + seconds
    while time.perf_counter() < end:
        for _ in range(10_000):
            n += 1
    return n


def machine_ceiling(seconds: float = 1.5) -> float:
    """Throughput of 2 spinning processes over 1 right now (2.0 on two free cores)."""
    import multiprocessing  # noqa: PLC0415

    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        pool.map(_spin, [0.05, 0.05])  # start-up
        one = pool.map(_spin, [seconds])[0]
        two = sum(pool.map(_spin, [seconds, seconds]))
    return two / max(one, 1)


def _process_cpu() -> float:
    return time.process_time()


def per_pair_stages(work: Path, chunk_size: int, **executor: object) -> float:
    """Matching, two-view and two-view BA in ``work`` (features already there); wall time."""
    chunks = {"chunk_size": chunk_size} if chunk_size > 0 else {}  # 0: each stage's default, as run.py has
    t0 = time.perf_counter()
    with client_session():  # one client of the cluster for the three stages, as run.py has
        MatchingStage(work, MatchingConfig(**chunks, **executor), progress=False).run()
        TwoViewStage(work, TwoViewConfig(**chunks, progress=False, **executor)).run()
        TwoViewBAStage(work, BAConfig(**chunks, progress=False, **executor)).run()
    return time.perf_counter() - t0


def fresh_copy(features: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for name in FEATURE_FILES:
        src = features / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst / name)
    return dst


def same_outputs(a: Path, b: Path) -> bool:
    for name in OUTPUTS:
        with np.load(a / name) as x, np.load(b / name) as y:
            if x.files != y.files or not all(np.array_equal(x[k], y[k]) for k in x.files):
                return False
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=16, help="rendered views (all pairs are matched)")
    ap.add_argument("--width", type=int, default=1024, help="image width (height 3/4 of it), px")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--chunk-size", type=int, default=4,
                    help="pairs per task, every stage (0: each stage's default, which a Dask cluster cuts finer "
                         "where a worker would get fewer than 16 tasks, as in run.py)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="dask-speedup-"))
    try:
        cfg = SceneConfig(width=a.width, height=a.width * 3 // 4, focal=0.875 * a.width,
                          texture_px_per_unit=220.0 * a.width / 640)
        scene = render_scene(n_views=a.views, seed=7, out=root / "scene", config=cfg)
        base = root / "features"
        FeaturesStage(base, FeatureConfig(), images=scene.out, K_path=scene.out / "cameras.txt", progress=False).run()
        serial = fresh_copy(base, root / "serial")
        t_serial = per_pair_stages(serial, a.chunk_size, executor="serial")
        print(f"serial (this process): {t_serial:.1f} s", flush=True)
        out: dict = {"views": a.views, "size": [scene.images[0].shape[1], scene.images[0].shape[0]],
                     "n_pairs": a.views * (a.views - 1) // 2, "chunk_size": a.chunk_size, "repeats": a.repeats,
                     "cpu_count": os.cpu_count(), "serial_in_process_s": t_serial, "runs": []}
        clusters = {n: LocalDaskCluster(n) for n in (1, 2)}
        try:
            for n, c in clusters.items():  # warm-up: imports in every worker, one full run
                per_pair_stages(fresh_copy(base, root / f"warm{n}"), a.chunk_size, scheduler=c.address)
            for r in range(a.repeats):
                for n, c in clusters.items():
                    with DaskExecutor(scheduler=c.address) as ex:
                        ex.client.run(clear_worker_caches)
                    work = fresh_copy(base, root / f"r{r}w{n}")
                    la0 = os.getloadavg()[0]
                    with DaskExecutor(scheduler=c.address) as ex:
                        w0, c0 = ex.client.run(_process_cpu), time.process_time()
                        wall = per_pair_stages(work, a.chunk_size, scheduler=c.address)
                        c1, w1 = time.process_time(), ex.client.run(_process_cpu)
                    worker_cpu = sorted(w1[k] - w0[k] for k in w0)
                    row = {"repeat": r, "workers": n, "wall_s": wall, "loadavg_before": la0,
                           "loadavg_after": os.getloadavg()[0], "client_cpu_s": c1 - c0, "worker_cpu_s": worker_cpu,
                           "identical_to_serial": same_outputs(serial, work)}
                    out["runs"].append(row)
                    print(f"repeat {r} workers {n}: {wall:6.2f} s  cpu client {c1 - c0:5.2f} s workers "
                          f"{', '.join(f'{x:5.2f}' for x in worker_cpu)} s  load {la0:.2f} -> "
                          f"{row['loadavg_after']:.2f}  identical {row['identical_to_serial']}", flush=True)
                out["runs"][-1]["ceiling"] = ceiling = machine_ceiling()
                print(f"repeat {r}: machine ceiling (2 spinning processes / 1) {ceiling:.2f}", flush=True)
        finally:
            for c in clusters.values():
                c.close()
        w = {n: [x["wall_s"] for x in out["runs"] if x["workers"] == n] for n in (1, 2)}
        out["ratio_per_repeat"] = [x / y for x, y in zip(w[1], w[2])]
        out["median_ratio"] = float(np.median(out["ratio_per_repeat"]))
        out["ratio_of_medians"] = float(np.median(w[1]) / np.median(w[2]))
        runs = {n: [x for x in out["runs"] if x["workers"] == n] for n in (1, 2)}
        out["cpu_speedup_per_repeat"] = [
            (x["client_cpu_s"] + sum(x["worker_cpu_s"])) / (y["client_cpu_s"] + max(y["worker_cpu_s"]))
            for x, y in zip(runs[1], runs[2])]
        out["median_cpu_speedup"] = float(np.median(out["cpu_speedup_per_repeat"]))
        out["ceiling_per_repeat"] = [x["ceiling"] for x in runs[2]]
        out["all_identical_to_serial"] = all(x["identical_to_serial"] for x in out["runs"])
        print(f"\n{'workers':>8} {'median wall s':>14} {'min wall s':>11}")
        for n in (1, 2):
            print(f"{n:>8} {np.median(w[n]):14.2f} {min(w[n]):11.2f}")
        print(f"speed-up 2 vs 1 worker (wall): per repeat {', '.join(f'{x:.2f}' for x in out['ratio_per_repeat'])}; "
              f"median {out['median_ratio']:.2f} (target >= 1.6); machine ceiling per repeat "
              f"{', '.join(f'{x:.2f}' for x in out['ceiling_per_repeat'])}")
        print(f"speed-up from CPU seconds (two free cores): per repeat "
              f"{', '.join(f'{x:.2f}' for x in out['cpu_speedup_per_repeat'])}; median {out['median_cpu_speedup']:.2f}; "
              f"identical to serial: {out['all_identical_to_serial']}")
        write_json(a.out, out)
        print(f"wrote {a.out}")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
