"""A bounded, seeded fuzzer over every file reader of the pipeline (issue 12, acceptance item 5).

Each reader gets ``FUZZ_N`` (default 200) damaged copies of a good file or folder
(:mod:`pipeline.synthetic.damage`: bytes, text, JSON and array-level damage), each
read under a time limit and an address-space limit. A reader passes when every
copy is either

- refused with one of the project's errors (a :class:`PipelineError`), on one line
  that names the damaged file or its folder, or
- accepted with a result that still satisfies the reader's invariants (rotations
  are rotations, values finite, counts consistent): no silent acceptance of nonsense.

Anything else (another exception, a hang, a memory blow-up) fails, with the seed
and the damage that caused it. ``FUZZ_N=2000 pytest tests/badinput/test_fuzz.py``
runs a larger budget.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest
import scipy.io as sio

from pipeline.core import so3
from pipeline.core.errors import PipelineError
from pipeline.core.viewgraph import ViewGraph
from pipeline.frontend.intrinsics import check_K
from pipeline.stage import output_digest
from pipeline.synthetic.damage import damaged_copies

N = int(os.environ.get("FUZZ_N", "200"))
CALL_LIMIT_S = 60.0  # per read: a hang backstop above the readers' own child-process limits (COLMAP: 20 s)
MEMORY_HEADROOM = 3 << 30  # a read may allocate this much beyond what the test process holds


class Hang(BaseException):
    """Raised in the main thread when a read exceeds its time limit."""


@contextlib.contextmanager
def limits(seconds: float) -> Iterator[None]:
    """A time limit (SIGALRM) for one read, inside an address-space limit for the whole reader."""

    def alarm(signum: int, frame: Any) -> None:
        raise Hang()

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@contextlib.contextmanager
def memory_limit() -> Iterator[None]:
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    vm = int(Path("/proc/self/statm").read_text().split()[0]) * resource.getpagesize()
    cap = vm + MEMORY_HEADROOM
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ------------------------------------------------------------------ invariants
def _rotations(R: Any, n: int | None = None) -> None:
    R = np.asarray(R)
    assert R.ndim == 3 and R.shape[1:] == (3, 3) and (n is None or len(R) == n), R.shape
    assert np.isfinite(R).all() and so3.is_rotation(R, 1e-5).all(), "not rotations"


def _names(names: list[str]) -> None:
    assert all(isinstance(n, str) and n for n in names) and len(set(names)) == len(names), names[:5]


def _viewgraph(vg: ViewGraph) -> None:
    assert isinstance(vg, ViewGraph)
    _names(vg.names)
    M, N = vg.n_edges, vg.n_cameras
    assert vg.edges.shape == (M, 2) and (M == 0 or (vg.edges.min() >= 0 and vg.edges.max() < N))
    assert np.all(vg.edges[:, 0] < vg.edges[:, 1])
    _rotations(vg.R_rel, M)
    if vg.H is not None:
        assert vg.H.shape == (M, 3, 3) and np.isfinite(vg.H).all()
        assert np.all(np.linalg.eigvalsh(0.5 * (vg.H + vg.H.transpose(0, 2, 1)))[:, 0] > 0)
    for v in vg.stats.values():
        assert v.shape[:1] == (M,)


def _reference(ref: Any) -> None:
    _names(list(ref.names))
    _rotations(ref.R, len(ref.names))
    if ref.K is not None:
        for K in np.broadcast_to(ref.K, (len(ref.names), 3, 3)):
            check_K(K, "fuzz")
    if ref.centers is not None:
        assert ref.centers.shape == (len(ref.names), 3) and np.isfinite(ref.centers).all()


def _intrinsics(res: Any) -> None:
    for K in ([res] if isinstance(res, np.ndarray) else list(res.values())):
        check_K(K, "fuzz")
    if isinstance(res, dict):
        _names(list(res))


def _mat(data: Any) -> None:
    _viewgraph(data.vg)
    if data.R_gt is not None:
        _rotations(data.R_gt, data.vg.n_cameras)
        assert data.gt_mask.shape == (data.vg.n_cameras,) and data.gt_mask.dtype == bool


def _features(fs: Any) -> None:
    _names(fs.names)
    n = len(fs.names)
    assert n >= 1 and fs.K.shape == (n, 3, 3) and fs.sizes.shape == (n, 2) and np.all(fs.sizes > 0)
    for K in fs.K:
        check_K(K, "fuzz")
    assert len(fs.keypoints) == len(fs.descriptors) == n
    for kp, d in zip(fs.keypoints, fs.descriptors):
        assert kp.ndim == 2 and kp.shape[1] == 2 and np.isfinite(kp).all()
        assert d.shape == (len(kp), 128) and d.dtype == np.uint8


def _matches(ms: Any) -> None:
    _names(ms.names)
    P = len(ms.pairs)
    assert ms.pairs.shape == (P, 2) and len(ms.matches) == P
    assert P == 0 or (ms.pairs.min() >= 0 and ms.pairs.max() < len(ms.names) and np.all(ms.pairs[:, 0] < ms.pairs[:, 1]))
    for m in ms.matches:
        assert m.ndim == 2 and m.shape[1] == 2 and m.dtype.kind in "iu" and (m.size == 0 or m.min() >= 0)


def _two_view(data: Any) -> None:
    _viewgraph(data.vg)
    n, total = data.vg.n_cameras, len(data.x_i)
    assert data.K.shape == (n, 3, 3) and np.isfinite(data.K).all()
    assert len(data.offsets) == data.vg.n_edges + 1 and len(data.x_j) == total  # one slice per edge, i and j paired
    assert data.offsets[0] == 0 and data.offsets[-1] == total and np.all(np.diff(data.offsets) >= 0)
    assert np.isfinite(data.x_i).all() and np.isfinite(data.x_j).all()
    assert isinstance(data.rejected, list)


def _record(rec: Any) -> None:
    assert rec is None or (isinstance(rec.fingerprint, str) and all(isinstance(v, int) for v in rec.outputs.values()))


def _summary(s: dict) -> None:
    _names(s["names"])
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in s["left_out"].items())


def _index(where: dict) -> None:
    import re

    assert all(isinstance(k, str) and re.fullmatch(r"chunk-[0-9a-f]+\.npz", v) for k, v in where.items()), where


def _configs(res: Any) -> None:
    from pipeline.core.config import Config

    yaml_data, configs, specs, _ = res
    assert all(isinstance(c, Config) for c in configs.values()) and all(isinstance(s.config, Config) for s in specs)


def _image(res: Any) -> None:
    sizes, bad, (img, why) = res
    if img is None:
        assert isinstance(why, str) and why
    else:
        assert img.dtype == np.uint8 and img.ndim == 2 and min(img.shape) >= 16


# ------------------------------------------------------------- seed files
def _fix_sizes(folder: Path, stage: str) -> None:
    """Make the record list the damaged files' sizes: the reader must then judge their content itself."""
    path = folder / f"{stage}.record.json"
    with contextlib.suppress(Exception):
        rec = json.loads(path.read_text())
        rec["outputs"] = {k: (folder / k).stat().st_size for k in rec["outputs"] if (folder / k).is_file()}
        rec["digests"] = {k: output_digest(folder / k) for k in rec["outputs"]}
        path.write_text(json.dumps(rec))


def _copy(src: Path, dst: Path, names: list[str]) -> Path:
    dst.mkdir(parents=True)
    for n in names:
        s = src / n
        (shutil.copytree if s.is_dir() else shutil.copy2)(s, dst / n)
    return dst


@pytest.fixture(scope="session")
def seeds(baseline, tiny_scene, tmp_path_factory) -> dict[str, Path]:
    """One good file or folder per reader, from the finished tiny run and the scene's true cameras."""
    from pipeline.reference.truth import read_cameras_file
    from pipeline.io.mat import write_l1_mat
    from scipy.spatial.transform import Rotation

    d = tmp_path_factory.mktemp("seeds")
    work = baseline / "work"
    ref = read_cameras_file(tiny_scene / "cameras.txt")
    n = len(ref.names)
    t = -np.einsum("nij,nj->ni", ref.R, ref.centers)
    out: dict[str, Path] = {"viewgraph": baseline / "viewgraph.npz", "rotations": baseline / "rotations" / "irls-l0.5.txt",
                            "cameras": tiny_scene / "cameras.txt", "record": _copy(work, d / "record", ["two_view.record.json"])}
    mid = d / "templeSR_par.txt"
    mid.write_text(f"{n}\n" + "".join(f"{nm} " + " ".join(f"{x:.12g}" for x in [*K.ravel(), *R.ravel(), *tt]) + "\n"
                                      for nm, K, R, tt in zip(ref.names, ref.K, ref.R, t)))
    out["middlebury"] = mid
    st = d / "strecha" / "gt_dense_cameras"
    st.mkdir(parents=True)
    for nm, K, R, C in zip(ref.names, ref.K, ref.R, ref.centers):
        rows = [K[0], K[1], K[2], [0, 0, 0], R.T[0], R.T[1], R.T[2], C, [240, 180]]
        (st / f"{nm}.camera").write_text("\n".join(" ".join(f"{x:.12g}" for x in r) for r in rows) + "\n")
    out["strecha"] = st
    cm = d / "colmap"
    cm.mkdir()
    K0 = ref.K[0]
    (cm / "cameras.txt").write_text(f"# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n1 PINHOLE 240 180 {K0[0, 0]} {K0[1, 1]} "
                                    f"{K0[0, 2] + 0.5} {K0[1, 2] + 0.5}\n")
    pts = np.array([[0.0, 0.0, 0.5], [0.5, 0.2, 0.3], [-0.4, 0.1, 0.8]])
    img_lines, tracks = [], {k: [] for k in range(len(pts))}
    for i, (nm, R, tt) in enumerate(zip(ref.names, ref.R, t), 1):
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        img_lines.append(" ".join([str(i)] + [repr(float(v)) for v in (w, x, y, z, *tt)] + ["1", nm]))
        obs = []
        for k, X in enumerate(pts):
            p = ref.K[i - 1] @ (R @ X + tt)
            obs.append(f"{p[0] / p[2] + 0.5:.6f} {p[1] / p[2] + 0.5:.6f} {k + 1}")
            tracks[k].append(f"{i} {k}")
        img_lines.append(" ".join(obs))
    (cm / "images.txt").write_text("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n" + "\n".join(img_lines) + "\n")
    (cm / "points3D.txt").write_text("# POINT3D_ID X Y Z R G B ERROR TRACK[]\n" + "".join(
        f"{k + 1} {X[0]} {X[1]} {X[2]} 128 128 128 0.5 {' '.join(tracks[k])}\n" for k, X in enumerate(pts)))
    out["colmap"] = cm
    vg = ViewGraph.load(baseline / "viewgraph.npz")
    out["l1_mat"] = write_l1_mat(d / "l1.mat", vg.with_H(None), ref.R)
    blocks = np.zeros((n, 3, n, 3))
    alpha = np.zeros((n, 3, n, 3))
    for (i, j), Rij, H in zip(vg.edges, vg.R_rel, vg.H):
        blocks[i, :, j, :] = Rij
        alpha[i, :, j, :] = np.trace(H) / 2 * np.eye(3) - H  # M with H = tr(M) I - M
    sio.savemat(d / "lu.mat", {"Rrel": blocks.reshape(3 * n, 3 * n), "Alpha": alpha.reshape(3 * n, 3 * n),
                               "Rgt": ref.R.reshape(3 * n, 3)})
    out["lu_mat"] = d / "lu.mat"
    np.savetxt(d / "K.txt", ref.K[0])
    out["K"] = d / "K.txt"
    (d / "pairs.txt").write_text("# pairs\n" + "".join(f"{ref.names[a]} {ref.names[b]}\n" for a in range(n)
                                                        for b in range(a + 1, n) if b - a <= 2))
    out["pairs"] = d / "pairs.txt"
    cfg = (Path(__file__).resolve().parents[2] / "configs" / "default.yaml").read_text().replace("averaging: {}", "averaging:\n  alpha_deg: 5.0\n  irls: {loss: huber}")
    (d / "config.yaml").write_text(cfg.replace("sdp: {}", "sdp:\n  eps_abs: 1.0e-6\n  solver: scs"))
    out["config"] = d / "config.yaml"
    out["features"] = _copy(work, d / "features", ["features.json", "features", "features.record.json"])
    out["matches"] = _copy(work, d / "matches", ["matches.json", "matches", "matching.record.json"])
    out["two_view"] = _copy(work, d / "two_view", ["two_view.npz", "two_view_corr.npz", "two_view.record.json"])
    out["ba"] = _copy(work, d / "ba", ["viewgraph.npz", "two_view_ba.record.json"])
    out["summary"] = _copy(baseline, d / "summary", ["viewgraph.json"])
    out["index"] = _copy(work / "features", d / "index", ["index.json"])
    refdir = d / "reference"
    refdir.mkdir()
    from pipeline.io.rotations import write_rotations

    write_rotations(refdir / "rotations.txt", ref.names, ref.R)
    (refdir / "reference.json").write_text(json.dumps({"images": ref.names, "n_images": n, "n_registered": n,
                                                       "registered": ref.names, "unregistered": {}}))
    out["pycolmap_result"] = refdir
    from pipeline.io.g2o import write_g2o
    from pipeline.io.glomap import write_glomap_relpose, write_glomap_rotations
    from pipeline.synthetic.files import make_synthetic_1dsfm

    out["g2o"] = write_g2o(d / "graph.g2o", vg, ref.R)
    out["glomap_rotations"] = write_glomap_rotations(d / "glomap_rotations.txt", ref.names, ref.R)
    out["glomap_relpose"] = write_glomap_relpose(d / "relpose.txt", vg.with_H(None))
    make_synthetic_1dsfm(d / "onedsfm", n=8, n_extra_images=2, n_unregistered=1, seed=0)
    out["onedsfm"] = d / "onedsfm"
    import pycolmap

    (d / "colmap_bin").mkdir()
    pycolmap.Reconstruction(str(cm)).write(str(d / "colmap_bin"))
    out["colmap_bin"] = d / "colmap_bin"
    import cv2

    img = cv2.imread(str(tiny_scene / "view_000.png"))[40:104, 60:140]  # 80x64: decoding stays cheap
    for ext in ("png", "jpg"):
        (d / f"img_{ext}").mkdir()
        cv2.imwrite(str(d / f"img_{ext}" / f"view.{ext}"), img)
        out[f"image_{ext}"] = d / f"img_{ext}"
    return out


# ------------------------------------------------------------------ readers
def _read_image(folder: Path) -> Any:
    from pipeline.frontend.images import check_headers, read_gray

    name = next(p.name for p in folder.iterdir())
    sizes, bad = check_headers(folder, [name])
    return sizes, bad, read_gray(folder / name)


def _load_two_view(folder: Path) -> Any:
    from pipeline.geometry.two_view_stage import load_two_view

    _fix_sizes(folder, "two_view")
    return load_two_view(folder)


def _load_ba(folder: Path) -> Any:
    from pipeline.geometry.ba_stage import load_ba_viewgraph

    _fix_sizes(folder, "two_view_ba")
    return load_ba_viewgraph(folder)


def _names_of(seeds: dict[str, Path]) -> list[str]:
    return [ln.split()[0] for ln in seeds["cameras"].read_text().splitlines() if ln and not ln.startswith("#")]


@dataclass
class Target:
    read: Callable[[Path], Any]
    check: Callable[[Any], None]
    files: list[str] | None = None  # for a folder: the files that get damaged


def _targets(seeds: dict[str, Path]) -> dict[str, tuple[Path, Target]]:
    from pipeline.core.store import ItemStore
    from pipeline.frontend.feature_stage import load_features
    from pipeline.frontend.intrinsics import parse_intrinsics_file, read_intrinsics
    from pipeline.frontend.matching_stage import load_matches
    from pipeline.frontend.pairs import read_pairs
    from pipeline.graph.stage import load_graph_summary
    from pipeline.io.g2o import read_g2o
    from pipeline.io.graphs import read_input_graph
    from pipeline.io.mat import read_mat
    from pipeline.io.rotations import read_rotations
    from pipeline.plan import load_configs
    from pipeline.reference.models import load_reference
    from pipeline.reference.truth import read_reference
    from pipeline.stage import read_record

    names = _names_of(seeds)
    return {
        "ViewGraph.load": (seeds["viewgraph"], Target(lambda p: ViewGraph.load(p, allow_isolated=True), _viewgraph)),
        "g2o file": (seeds["g2o"], Target(read_g2o, lambda d: (_viewgraph(d.vg), _rotations(d.R_init)))),
        "1DSfM folder": (seeds["onedsfm"], Target(read_input_graph, _mat)),
        "truth: 1DSfM gt_bundle.out": (seeds["onedsfm"], Target(lambda p: read_reference(p / "gt_bundle.out"), _reference,
                                                              files=["gt_bundle.out", "list.txt"])),
        "GLOMAP rotations": (seeds["glomap_rotations"], Target(read_rotations, lambda r: (_names(r[0]),
                                                                                         _rotations(r[1], len(r[0]))))),
        "GLOMAP relative poses": (seeds["glomap_relpose"], Target(lambda p: read_input_graph(p).vg, _viewgraph)),
        "read_rotations": (seeds["rotations"], Target(read_rotations, lambda r: (_names(r[0]), _rotations(r[1], len(r[0]))))),
        "truth: rotations file": (seeds["rotations"], Target(read_reference, _reference)),
        "truth: cameras file": (seeds["cameras"], Target(read_reference, _reference)),
        "truth: Middlebury _par.txt": (seeds["middlebury"], Target(read_reference, _reference)),
        "truth: Strecha gt_dense_cameras": (seeds["strecha"], Target(read_reference, _reference)),
        "truth: COLMAP text model": (seeds["colmap"], Target(read_reference, _reference)),
        "truth: .mat Rgt": (seeds["l1_mat"], Target(read_reference, _reference)),
        "truth: COLMAP binary model": (seeds["colmap_bin"], Target(read_reference, _reference)),
        ".mat LU Sphinx layout": (seeds["lu_mat"], Target(read_mat, _mat)),
        ".mat l1-RA layout": (seeds["l1_mat"], Target(read_mat, _mat)),
        "intrinsics K.txt": (seeds["K"], Target(parse_intrinsics_file, _intrinsics)),
        "intrinsics cameras file": (seeds["cameras"], Target(read_intrinsics, _intrinsics)),
        "pairs file": (seeds["pairs"], Target(lambda p: read_pairs(p, names), lambda pr: (
            pr.shape[1:] == (2,) and np.all(pr[:, 0] < pr[:, 1]) and pr.max() < len(names)) or _fail(pr))),
        "YAML config": (seeds["config"], Target(load_configs, _configs)),
        "features store + manifest": (seeds["features"], Target(load_features, _features)),
        "matches store + manifest": (seeds["matches"], Target(load_matches, _matches)),
        "item store index": (seeds["index"], Target(lambda p: ItemStore(p).load_index(), _index)),
        "stage record": (seeds["record"], Target(lambda p: read_record(p, "two_view"), _record)),
        "two-view output": (seeds["two_view"], Target(_load_two_view, _two_view)),
        "two-view BA output": (seeds["ba"], Target(_load_ba, _viewgraph)),
        "view-graph summary": (seeds["summary"], Target(load_graph_summary, _summary)),
        "pycolmap reference result": (seeds["pycolmap_result"], Target(load_reference, _reference)),
        "image PNG": (seeds["image_png"], Target(_read_image, _image)),
        "image JPEG": (seeds["image_jpg"], Target(_read_image, _image)),
    }


def _fail(x: Any) -> None:
    raise AssertionError(f"accepted nonsense: {x!r}"[:200])


READERS = ["ViewGraph.load", "g2o file", "1DSfM folder", "truth: 1DSfM gt_bundle.out", "GLOMAP rotations",
           "GLOMAP relative poses", "read_rotations", "truth: rotations file", "truth: cameras file",
           "truth: Middlebury _par.txt", "truth: Strecha gt_dense_cameras", "truth: COLMAP text model",
           "truth: COLMAP binary model", "truth: .mat Rgt",
           ".mat LU Sphinx layout", ".mat l1-RA layout", "intrinsics K.txt", "intrinsics cameras file", "pairs file",
           "YAML config", "features store + manifest", "matches store + manifest", "item store index", "stage record",
           "two-view output", "two-view BA output", "view-graph summary", "pycolmap reference result", "image PNG",
           "image JPEG"]


@pytest.mark.parametrize("reader", READERS)
def test_fuzz_reader(reader: str, seeds, tmp_path, caplog) -> None:
    src, target = _targets(seeds)[reader]
    seed = READERS.index(reader) + 1000
    failures: list[str] = []
    t0 = time.perf_counter()
    with memory_limit():
        for k, path, what in damaged_copies(src, tmp_path, N, seed, target.files):
            caplog.clear()
            try:
                with limits(CALL_LIMIT_S):
                    result = target.read(path)
            except Hang:
                failures.append(f"#{k} {what}: no answer within {CALL_LIMIT_S:.0f} s")
                continue
            except PipelineError as exc:
                msg = str(exc)
                if "\n" in msg or str(path) not in msg:
                    failures.append(f"#{k} {what}: the error is not one line naming the file: {msg[:200]!r}")
                continue
            except BaseException as exc:  # noqa: BLE001 - what the fuzzer is looking for
                failures.append(f"#{k} {what}: {type(exc).__name__}: {' '.join(str(exc).split())[:160]}")
                continue
            try:
                target.check(result)
            except Exception as exc:  # noqa: BLE001
                failures.append(f"#{k} {what}: accepted, but {type(exc).__name__} {str(exc)[:160]}")
    dt = time.perf_counter() - t0
    assert not failures, f"{reader} (seed {seed}, {N} damaged copies, {dt:.1f} s): {len(failures)} failures:\n" + \
        "\n".join(failures[:15])
