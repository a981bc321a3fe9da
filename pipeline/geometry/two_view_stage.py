"""The two-view stage: the relative pose of every matched pair of a WORK folder (``python -m pipeline.two_view``).

It reads the front end's features, matches and camera models (K, and the keypoints
undistorted where the cameras stage found distortion), estimates each pair with
:func:`pipeline.geometry.ransac.estimate_pair` in chunks on an executor
(:mod:`pipeline.core.parallel`), keeps every finished chunk in an item store (an
interrupted run resumes per pair; a changed option recomputes), and writes::

    WORK/two_view.npz          the ViewGraph (allow_isolated=True): edges, R_rel = R_j R_iᵀ (cam2_from_cam1),
                               inliers, stats "t" (M, 3) unit translation (x_j = R_ij x_i + t),
                               "n_matches", "n_inliers_E", "n_inliers_H", "h_ratio",
                               "median_triangulation_deg", "median_parallax_px", "n_static" (matches
                               the zero-motion test removed), "n_guided" (matches guided matching added),
                               "small_baseline", "planar", "degenerate" (M,) bool
    WORK/two_view_corr.npz     K (N, 3, 3) of the cameras stage, sizes (N, 2), offsets (M+1,), inlier (undistorted) pixel
                               coordinates x_i (total, 2), x_j (total, 2), keypoint indices kp_i, kp_j (total,)
    WORK/two_view.record.json  the stage record; its summary lists the rejected pairs
                               ({pair, names, n_matches, n_inliers, reason}) and the counts
    WORK/two_view_pairs/       the per-pair results (chunks)

:func:`load_two_view` reads them back. Command line::

    python -m pipeline.two_view --work WORK [--method poselib|magsac|ransac] [--threshold-px 1.0] ...
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from pipeline.core import so3
from pipeline.core.atomic import save_npz
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.store import ItemStore, compute_missing, item_key
from pipeline.core.viewgraph import ViewGraph, pair_keys
from pipeline.frontend import feature_stage, matching_stage
from pipeline.frontend.camera_stage import NAME as CAMERAS, cameras_for
from pipeline.frontend.distortion import CameraModel, undistort_points
from pipeline.frontend.matching import root_sift
from pipeline.geometry.guided import estimate_pair_guided
from pipeline.geometry.ransac import PairGeometry, TwoViewConfig, estimate_pair
from pipeline.geometry.stage_io import PairStage, read_npz, read_viewgraph, recorded_output, rerun_hint, stage_cli
from pipeline.stage import StageRecord, read_record

__all__ = ["TwoViewStage", "TwoViewData", "load_two_view", "write_two_view", "main_cli", "VIEWGRAPH",
           "CORRESPONDENCES"]

logger = logging.getLogger(__name__)

NAME = "two_view"
COMMAND = "pipeline.two_view"
VIEWGRAPH = "two_view.npz"
CORRESPONDENCES = "two_view_corr.npz"
STORE = "two_view_pairs"
_CORR_ARRAYS = {"K": "f", "sizes": "iu", "offsets": "iu", "x_i": "f", "x_j": "f", "kp_i": "iu", "kp_j": "iu"}


def _frontend_inputs(work: Path) -> dict[str, str]:
    """Fingerprints of the front-end results this stage reads (their stage records; the cameras stage's if it ran)."""
    inp = {name: _upstream_record(work, name).fingerprint for name in ("features", "matching")}
    rec = read_record(work, CAMERAS)
    if rec is not None:
        inp[CAMERAS] = rec.fingerprint
    return inp


def _cameras(work: Path, fm: dict[str, Any]) -> tuple[np.ndarray, list[CameraModel | None]]:
    """K (N, 3, 3) and, per image, the camera model whose distortion the worker removes (None: none).

    The cameras stage's result when it ran, else the features' K as it is (with a warning
    when that loses something: an EXIF or default focal, or a file with distortion).
    """
    cams = cameras_for(work, fm["names"])
    if cams is None:
        from pipeline.frontend.distortion import is_camera_model_file  # noqa: PLC0415

        sources = [str(s) for s in fm.get("K_source", [])]
        lossy = any(not s.startswith("file:") or is_camera_model_file(s[len("file:"):]) for s in sources)
        (logger.warning if lossy else logger.info)(
            "two_view: %s has no result of the cameras stage; using the features' K as it is (file, EXIF or default "
            "focal, no distortion): run `python -m pipeline.cameras --work %s` first", work, work)
        return np.array(fm["K"], float).reshape(-1, 3, 3), [None] * len(fm["names"])
    return cams.K, [m if m.has_distortion else None for m in cams.models]


def _upstream_record(work: Path, name: str) -> StageRecord:
    rec = read_record(work, name)
    if rec is None:
        raise InputFileError(f"{work} has no result of the '{name}' stage, which 'two_view' needs; "
                             f"run `python -m pipeline.{name}` on it first")
    return rec


def _frontend_image_count(work: Path) -> int:
    """Number of images of the front end (the camera count of a two-view result)."""
    return len(feature_stage.load_manifest(work)["names"])


@dataclass
class TwoViewData:
    """What the two-view stage wrote (see :func:`load_two_view`).

    Attributes:
        vg: ViewGraph (allow_isolated=True) with R_rel, inliers and per-edge stats.
        K: (N, 3, 3) intrinsics; sizes: (N, 2) image sizes (w, h).
        rejected: list of ``{pair, names, n_matches, n_inliers, reason}``.
        offsets: (M+1,) start of each edge's correspondences.
        x_i, x_j: (total, 2) inlier pixel coordinates (full resolution).
        kp_i, kp_j: (total,) keypoint indices of the inliers in the features.
    """

    vg: ViewGraph
    K: np.ndarray
    sizes: np.ndarray
    rejected: list[dict]
    offsets: np.ndarray
    x_i: np.ndarray
    x_j: np.ndarray
    kp_i: np.ndarray
    kp_j: np.ndarray

    def correspondences(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Inlier pixel coordinates ``(x_i (n, 2), x_j (n, 2))`` of edge k (i = edges[k, 0])."""
        if not 0 <= k < self.vg.n_edges:
            raise IndexError(f"edge index {k} out of range for {self.vg.n_edges} edges")
        s, e = int(self.offsets[k]), int(self.offsets[k + 1])
        return self.x_i[s:e], self.x_j[s:e]

    def inliers_of(self, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inliers of the pairs ``edges`` (E, 2), ``i < j``, in their order: offsets (E+1,) and the keypoint
        index pairs (total, 2). Raises ValueError when a pair is not one of this result's edges."""
        n, e = self.vg.n_cameras, np.asarray(edges, np.int64).reshape(-1, 2)
        key_tv, key = pair_keys(*self.vg.edges.T, n), pair_keys(*e.T, n)
        order = np.argsort(key_tv)
        e_tv = order[np.minimum(np.searchsorted(key_tv[order], key), len(order) - 1)] if len(order) else order
        if len(e_tv) != len(key) or np.any(key_tv[e_tv] != key):
            raise ValueError("a pair is not among the two-view result's edges")
        counts = np.diff(self.offsets)[e_tv]
        offsets = np.r_[0, np.cumsum(counts)].astype(np.int64)
        rows = np.arange(offsets[-1]) + np.repeat(self.offsets[e_tv] - offsets[:-1], counts)
        return offsets, np.stack([self.kp_i[rows], self.kp_j[rows]], axis=1)


def write_two_view(work: Path, vg: ViewGraph, K: np.ndarray, sizes: np.ndarray, offsets: np.ndarray,
                   x_i: np.ndarray, x_j: np.ndarray, kp_i: np.ndarray, kp_j: np.ndarray) -> list[Path]:
    """Write the view graph and the correspondences files atomically; returns their paths."""
    corr_path = Path(work) / CORRESPONDENCES
    save_npz(corr_path, K=K, sizes=sizes, offsets=offsets, x_i=x_i, x_j=x_j, kp_i=kp_i, kp_j=kp_j)
    return [vg.save(Path(work) / VIEWGRAPH), corr_path]


def _check_corr(path: Path, arr: dict[str, np.ndarray], vg: ViewGraph) -> None:
    if missing := [k for k in _CORR_ARRAYS if k not in arr]:
        raise CacheError(f"{path} lacks the array(s) {missing}")
    for k, kinds in _CORR_ARRAYS.items():
        if arr[k].dtype.kind not in kinds:
            raise CacheError(f"{path}: {k} has dtype {arr[k].dtype}, expected {'float' if kinds == 'f' else 'integer'}")
    N, M, T, off = vg.n_cameras, vg.n_edges, len(arr["x_i"]) if arr["x_i"].ndim else -1, arr["offsets"]
    expected = {"K": (N, 3, 3), "sizes": (N, 2), "offsets": (M + 1,), "x_i": (T, 2), "x_j": (T, 2), "kp_i": (T,),
                "kp_j": (T,)}
    for k, shape in expected.items():
        if arr[k].shape != shape:
            raise CacheError(f"{path}: {k}.shape={arr[k].shape} but expected {shape} for {N} cameras, {M} edges")
    if off[0] != 0 or np.any(np.diff(off) < 0) or off[-1] != T:
        raise CacheError(f"{path}: offsets are not increasing from 0 to the {T} correspondences")
    if vg.inliers is None or not np.array_equal(np.diff(off), vg.inliers):
        raise CacheError(f"{path}: the correspondences per edge differ from the inlier counts of the view graph")
    if not (np.isfinite(arr["K"]).all() and np.isfinite(arr["x_i"]).all() and np.isfinite(arr["x_j"]).all()):
        raise CacheError(f"{path}: K or the pixel coordinates hold NaN or inf")
    if T and min(arr["kp_i"].min(), arr["kp_j"].min()) < 0:
        raise CacheError(f"{path}: negative keypoint indices")


def _read_two_view(work: Path, rec: StageRecord) -> TwoViewData:
    """The files of the record ``rec`` in ``work``, checked; :class:`CacheError` naming the bad file."""
    vg_path, corr_path = Path(work) / VIEWGRAPH, Path(work) / CORRESPONDENCES
    vg = read_viewgraph(vg_path)
    t = vg.stats.get("t")
    if t is None or t.shape != (vg.n_edges, 3) or t.dtype.kind != "f":
        raise CacheError(f"{vg_path} has no per-edge 't' statistic (M, 3): the translations of the pairs")
    if rec.summary.get("n_accepted") != vg.n_edges:
        raise CacheError(f"{vg_path} has {vg.n_edges} edges but its record says {rec.summary.get('n_accepted')}")
    rejected = rec.summary.get("rejected")
    if not isinstance(rejected, list) or not all(isinstance(r, dict) for r in rejected):
        raise CacheError(f"the record of {NAME} in {work} has no list of rejected pairs")
    arr = read_npz(corr_path, "correspondences file")
    _check_corr(corr_path, arr, vg)
    return TwoViewData(vg, arr["K"], arr["sizes"], rejected, arr["offsets"], arr["x_i"], arr["x_j"], arr["kp_i"],
                       arr["kp_j"])


def load_two_view(work: Path) -> TwoViewData:
    """Read the result of :class:`TwoViewStage`: ViewGraph, K, sizes, rejected pairs and correspondences.

    Raises:
        InputFileError: the stage has not run in ``work``.
        CacheError: a file is damaged (one line naming it; a re-run of the stage heals it).
    """
    work = Path(work)
    rec, _ = recorded_output(work, NAME, VIEWGRAPH, COMMAND)
    recorded_output(work, NAME, CORRESPONDENCES, COMMAND)
    try:
        return _read_two_view(work, rec)
    except CacheError as exc:
        raise CacheError(f"{exc}; {rerun_hint(COMMAND, work)}") from None


# ----------------------------------------------------------------- per pair
# A task names its inputs on disk: (feature chunk a, feature key a, feature chunk b, feature key b, match chunk,
# match key, K_a, K_b, pixel scale, camera model a, camera model b); the worker reads them itself (a worker holds a
# few images, never the collection) and undistorts the keypoints of a camera model with distortion.
Task = tuple[str, str, str, str, str, str, np.ndarray, np.ndarray, float, "CameraModel | None", "CameraModel | None"]


@functools.lru_cache(maxsize=64)
def _raw_keypoints(chunk: str, key: str) -> np.ndarray:
    return ItemStore.read_chunk(Path(chunk))[key]["keypoints"].astype(np.float32)


def _keypoints(chunk: str, key: str, camera: CameraModel | None) -> np.ndarray:
    """The keypoints the geometry uses: undistorted to the pinhole K where the camera has distortion."""
    kp = _raw_keypoints(chunk, key)
    return kp if camera is None else undistort_points(camera, kp)


@functools.lru_cache(maxsize=4)
def _match_chunk(chunk: str) -> dict[str, dict[str, np.ndarray]]:
    return ItemStore.read_chunk(Path(chunk))


@functools.lru_cache(maxsize=16)  # 16 images of 8192 keypoints: 64 MB per worker
def _root_sift(chunk: str, key: str) -> np.ndarray | None:
    """RootSIFT descriptors of one stored image (None when the features carry none, e.g. from a database)."""
    item = ItemStore.read_chunk(Path(chunk))[key]
    return root_sift(item["descriptors"]) if "descriptors" in item and len(item["descriptors"]) else None


def _estimate_chunk(tasks: list[Task], config: TwoViewConfig) -> list[dict[str, Any]]:
    """Worker: estimate a chunk of pairs read from disk; each result as arrays (see :func:`_geometry_from_item`),
    with the inliers' keypoint indices ``kp_i``, ``kp_j`` and pixels ``x_i``, ``x_j``."""
    out = []
    for ca, ka, cb, kb, cm, km, K_i, K_j, pixel_scale, cam_a, cam_b in tasks:
        kp_a, kp_b = _keypoints(ca, ka, cam_a), _keypoints(cb, kb, cam_b)
        m = _match_chunk(cm)[km]["matches"].astype(np.int32).reshape(-1, 2)
        q_a, q_b = (_root_sift(ca, ka), _root_sift(cb, kb)) if config.guided else (None, None)
        if q_a is not None and q_b is not None:
            g, m, _ = estimate_pair_guided(kp_a, q_a, kp_b, q_b, m, K_i, K_j, config, pixel_scale)
        else:
            g = estimate_pair(kp_a[m[:, 0]], kp_b[m[:, 1]], K_i, K_j, config, pixel_scale=pixel_scale)
        item = {f.name: np.asarray(getattr(g, f.name)) for f in dataclasses.fields(PairGeometry)}
        inl = m[g.inlier_mask] if g.ok else m[:0]
        item.update(kp_i=inl[:, 0], kp_j=inl[:, 1], x_i=kp_a[inl[:, 0]], x_j=kp_b[inl[:, 1]])
        out.append(item)
    return out


_SCALARS = {"bool": bool, "int": int, "float": float, "str": str}


def _geometry_from_item(item: dict[str, np.ndarray]) -> PairGeometry:
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(PairGeometry):
        v = item[f.name]
        kw[f.name] = _SCALARS[f.type](v.item()) if f.type in _SCALARS else v
    return PairGeometry(**kw)


_FIELDS = tuple(f.name for f in dataclasses.fields(PairGeometry)) + ("kp_i", "kp_j", "x_i", "x_j")


def _check_item(item: dict[str, np.ndarray], n_kp: tuple[int, int]) -> None:
    """:class:`CacheError` where a stored pair result reads well but is not what :func:`_estimate_chunk` writes:
    a field missing or of the wrong shape, an accepted pair whose R is not a rotation or whose t is not a unit
    vector (or 0, a pure rotation), inliers that disagree in number or refer to keypoints outside ``n_kp`` (the two
    images' counts)."""
    missing = [f for f in _FIELDS if f not in item]
    if missing:
        raise CacheError(f"lacks the field {missing[0]!r}")
    try:
        g = _geometry_from_item(item)
    except (ValueError, TypeError) as exc:
        raise CacheError(f"has a malformed field ({exc})") from None
    kp_i, kp_j, x_i, x_j = (np.asarray(item[f]) for f in ("kp_i", "kp_j", "x_i", "x_j"))
    n = len(kp_i) if kp_i.ndim == 1 else -1
    if n < 0 or kp_j.shape != (n,) or x_i.shape != (n, 2) or x_j.shape != (n, 2):
        raise CacheError(f"has inlier arrays of disagreeing shapes {kp_i.shape}, {kp_j.shape}, {x_i.shape}, "
                         f"{x_j.shape}")
    if min(g.n_matches, g.n_inliers, g.n_inliers_E, g.n_inliers_H, g.n_static, g.n_guided) < 0:
        raise CacheError("has a negative count")
    if not g.ok:
        if n:
            raise CacheError(f"is rejected ({g.reason}) but carries {n} inliers")
        return
    if g.R.shape != (3, 3) or not so3.is_rotation(g.R) or g.t.shape != (3,) or not np.isfinite(g.t).all() \
            or min(abs(np.linalg.norm(g.t) - 1.0), np.linalg.norm(g.t)) > 1e-6:  # t = 0: a pure rotation
        raise CacheError("is accepted with an R that is not a rotation or a t that is neither a unit vector nor 0")
    if n != g.n_inliers:
        raise CacheError(f"is accepted with {g.n_inliers} inliers but carries {n}")
    if not (np.isfinite(x_i).all() and np.isfinite(x_j).all()):
        raise CacheError("has inlier pixels that are NaN or inf")
    if n and (min(kp_i.min(), kp_j.min()) < 0 or kp_i.max() >= n_kp[0] or kp_j.max() >= n_kp[1]):
        raise CacheError(f"refers to keypoints outside the images' {n_kp[0]} and {n_kp[1]}")


class TwoViewStage(PairStage[TwoViewConfig]):
    """Relative poses of the matched pairs of a WORK folder (folder = WORK)."""

    name = NAME
    title = "two-view geometry"
    config_cls = TwoViewConfig
    store = STORE

    def inputs(self) -> dict[str, str]:
        return _frontend_inputs(self.folder)

    def verify(self, record: StageRecord) -> None:
        data = _read_two_view(self.folder, record)
        n = _frontend_image_count(self.folder)
        if data.vg.n_cameras != n:
            raise CacheError(f"{self.folder / VIEWGRAPH} has {data.vg.n_cameras} cameras but the features {n} images")

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        config, work = self.config, self.folder
        t_start = time.perf_counter()
        logger.info("two_view: %s", config)
        fm, mm = feature_stage.load_manifest(work), matching_stage.load_manifest(work)
        names, pairs = list(fm["names"]), np.asarray(mm["pairs"], np.int64).reshape(-1, 2)
        if list(mm["names"]) != names:
            raise InputFileError(f"{work}: the matches were computed for other images than the current features; "
                                 f"re-run `python -m pipeline.matching --work {work}`")
        K, cams = _cameras(work, fm)
        sizes = np.array(fm["sizes"], np.int64).reshape(-1, 2)
        max_size = int(fm.get("config", {}).get("max_image_size", 0) or 0)
        scale = np.ones(len(names))
        if max_size > 0:
            scale = np.maximum(sizes.max(axis=1) / max_size, 1.0)
        # absolute paths: the workers may run in another folder or on another machine
        fdir, mdir = (work / feature_stage.STORE).resolve(), (work / matching_stage.STORE).resolve()
        fwhere, mwhere = ItemStore(fdir).load_index(), ItemStore(mdir).load_index()
        fkeys, mkeys = list(fm["keys"]), list(mm["keys"])

        def task(p: int) -> Task:
            a, b = pairs[p]
            return (str(fdir / fwhere[fkeys[a]]), fkeys[a], str(fdir / fwhere[fkeys[b]]), fkeys[b],
                    str(mdir / mwhere[mkeys[p]]), mkeys[p], K[a], K[b], float(0.5 * (scale[a] + scale[b])),
                    cams[a], cams[b])

        def lens(c: CameraModel | None) -> Any:
            return None if c is None else [c.model, c.params]

        fp = config.fingerprint()
        keys = [item_key(fp, fkeys[a], fkeys[b], mkeys[p], K[a], K[b], float(0.5 * (scale[a] + scale[b])),
                         lens(cams[a]), lens(cams[b])) for p, (a, b) in enumerate(pairs)]
        store = ItemStore(work / self.store)
        n_kp = functools.cache(lambda a: len(_raw_keypoints(str(fdir / fwhere[fkeys[a]]), fkeys[a])))
        store.drop_damaged(keys, lambda p, item: _check_item(item, (n_kp(pairs[p][0]), n_kp(pairs[p][1]))),
                           f"pairs' two-view results in {work / self.store}",
                           name=lambda p: "-".join(names[c] for c in pairs[p]))
        done = store.done(keys)
        with tqdm(total=len(keys), initial=sum(k in done for k in keys), desc="two-view", unit="pair",
                  disable=not config.progress) as bar:
            n_computed = compute_missing(store, keys, task, functools.partial(_estimate_chunk, config=config),
                                         workers=config.workers, chunk_size=config.chunk_size, on_chunk=bar.update,
                                         backend=config.backend("processes"), scheduler=config.scheduler)
        items = [store.get(k) for k in keys]
        paths, summary = self._write(names, K, sizes, pairs, items)
        summary["n_computed"] = n_computed
        paths += store.write_index(keys)
        vg_iso = summary["isolated"]
        logger.info("two_view: %d of %d pairs accepted (%d flagged near-degenerate), %d rejected %s; %d computed, "
                    "%d reused, in %.1f s", summary["n_accepted"], len(keys), summary["n_degenerate"],
                    summary["n_rejected"], summary["rejected_reasons"] or "", n_computed, len(keys) - n_computed,
                    time.perf_counter() - t_start)
        if vg_iso:
            logger.warning("%d camera(s) have no accepted pair: %s", len(vg_iso), ", ".join(vg_iso[:5]))
        return paths, summary

    def _write(self, names: list[str], K: np.ndarray, sizes: np.ndarray, pairs: np.ndarray,
               items: Sequence[dict[str, np.ndarray]]) -> tuple[list[Path], dict[str, Any]]:
        """Assemble and write the view graph and correspondences; returns the paths and the summary."""
        geoms = [_geometry_from_item(it) for it in items]
        acc = [p for p, g in enumerate(geoms) if g.ok]
        rejected = [
            {"pair": [int(pairs[p][0]), int(pairs[p][1])], "names": [names[pairs[p][0]], names[pairs[p][1]]],
             "n_matches": g.n_matches, "n_inliers": g.n_inliers if g.n_inliers else g.n_inliers_E, "reason": g.reason}
            for p, g in enumerate(geoms) if not g.ok
        ]
        edges = pairs[acc].reshape(-1, 2)
        G = [geoms[p] for p in acc]
        stats = {
            "t": np.array([g.t for g in G]).reshape(-1, 3),
            "n_matches": np.array([g.n_matches for g in G], np.int64),
            "n_inliers_E": np.array([g.n_inliers_E for g in G], np.int64),
            "n_inliers_H": np.array([g.n_inliers_H for g in G], np.int64),
            "h_ratio": np.array([g.n_inliers_H / max(g.n_inliers_E, 1) for g in G], float),
            "median_triangulation_deg": np.array([g.median_triangulation_deg for g in G], float),
            "median_parallax_px": np.array([g.median_parallax_px for g in G], float),
            "n_static": np.array([g.n_static for g in G], np.int64),
            "n_guided": np.array([g.n_guided for g in G], np.int64),
            "small_baseline": np.array([g.small_baseline for g in G], bool),
            "planar": np.array([g.planar for g in G], bool),
        }
        stats["degenerate"] = stats["small_baseline"] | stats["planar"]
        vg = ViewGraph(list(names), edges, np.array([g.R for g in G]).reshape(-1, 3, 3),
                       inliers=np.array([g.n_inliers for g in G], np.int64), stats=stats, allow_isolated=True)
        kp_i = [items[p]["kp_i"] for p in acc]
        kp_j = [items[p]["kp_j"] for p in acc]
        xi = [items[p]["x_i"] for p in acc]
        xj = [items[p]["x_j"] for p in acc]
        counts = np.array([len(k) for k in kp_i], np.int64)

        def cat(arrs: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> np.ndarray:
            return np.concatenate(arrs).astype(dtype) if arrs else np.zeros(shape, dtype)

        paths = write_two_view(self.folder, vg, K, sizes, np.concatenate([[0], np.cumsum(counts)]),
                               cat(xi, (0, 2), np.float64), cat(xj, (0, 2), np.float64), cat(kp_i, (0,), np.int32),
                               cat(kp_j, (0,), np.int32))
        reasons: dict[str, int] = {}
        for r in rejected:
            key = r["reason"].split(" (")[0]
            reasons[key] = reasons.get(key, 0) + 1
        summary = {
            "n_images": vg.n_cameras,
            "n_pairs": int(len(pairs)),
            "n_accepted": int(len(acc)),
            "n_rejected": len(rejected),
            "n_degenerate": int(stats["degenerate"].sum()),
            "n_small_baseline": int(stats["small_baseline"].sum()),
            "n_planar": int(stats["planar"].sum()),
            "n_static_removed": int((stats["n_static"] > 0).sum()),
            "n_guided": int((stats["n_guided"] > 0).sum()),
            "isolated": [names[k] for k in np.flatnonzero(vg.degrees() == 0)],
            "rejected_reasons": reasons,
            "rejected": rejected,
        }
        return paths, summary


def main_cli(argv: Sequence[str] | None = None) -> int:
    return stage_cli(TwoViewStage, "python -m pipeline.two_view",
                     "5-point RANSAC relative poses of the matched pairs of WORK.", VIEWGRAPH, argv)
