"""The cameras stage: every image's camera model, and where each part of it came from (``python -m pipeline.cameras``).

It runs after matching and before the two-view geometry, which reads its result
(:func:`load_cameras`) instead of the features' K:

- a K read from a file (``--K`` or the image folder) is used as it is, with the
  distortion the file gives (COLMAP cameras, OpenCV coefficients);
- otherwise (an EXIF prior or nothing) the images are grouped by size and EXIF
  focal, and for each group with enough pairs one radial distortion parameter
  (``radial``) and the focal length (``estimate_focal``) are estimated from the view
  graph (:mod:`pipeline.frontend.camera_estimate`), the principal point at the image
  centre. A group that cannot be estimated keeps its EXIF or default focal, and says why;
- the keypoints of every image with distortion are undistorted to the pixels of the
  pinhole K (:mod:`pipeline.frontend.distortion`), so the geometry works on
  undistorted, K-normalized points.

With every K from a file and no distortion, the K's are the features' to the last
digit and nothing is estimated. WORK folder layout::

    WORK/cameras.json            names, sizes, K (N, 3, 3) of the undistorted keypoints,
                                 K_source (file:<path> | exif | estimated:<method> [(exif prior)] |
                                 default), the COLMAP camera model of each image, distortion_source
                                 (file:<path> | estimated:radial | none), the estimates and their diagnostics
    WORK/cameras_keypoints.npz   undistorted keypoints (offsets (N+1,), xy (T, 2)), when any image has distortion
    WORK/cameras_pairs/          per-pair work (F, profiles): resumable chunks
    WORK/cameras.record.json     the stage record

Command line::

    python -m pipeline.cameras --work WORK [--focal-method profile+rotcons] [--radial auto] ...
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import save_npz, write_json
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.store import ItemStore, compute_missing, item_key
from pipeline.frontend.camera_estimate import CamerasConfig, estimate_focal, estimate_radial
from pipeline.frontend.camera_evidence import Evidence, features_evidence, stage_evidence
from pipeline.frontend.camera_items import check_item
from pipeline.frontend.distortion import (COLMAP_OFFSET, CameraModel, is_camera_model_file, radial_undistort,
                                          undistort_points)
from pipeline.frontend.focal import K_from_focal
from pipeline.frontend.intrinsics import camera_models_for_names, focal_summary, intrinsics_summary
from pipeline.frontend.vg_calibration import calibrate_focals, choose_focal_lengths
from pipeline.stage import Stage, StageRecord, file_fingerprint, fingerprint_of, read_record

__all__ = ["CamerasStage", "CameraSet", "load_cameras", "cameras_for", "given_source", "intrinsics_summary", "main", "main_cli", "MANIFEST",
           "KEYPOINTS", "STORE", "CamerasConfig"]

logger = logging.getLogger(__name__)

NAME = "cameras"
MANIFEST = "cameras.json"
KEYPOINTS = "cameras_keypoints.npz"
STORE = "cameras_pairs"
#: ``K_source`` of an image whose focal the per-image view-graph calibration estimated (the two-view BA refines
#: these with ``refine_focal: auto``).
PER_IMAGE_SOURCE = "estimated:view-graph"


@dataclass
class CameraSet:
    """What the cameras stage wrote (see :func:`load_cameras`).

    Attributes:
        names: N image names (those of the features).  sizes: (N, 2) (w, h).
        K: (N, 3, 3) pinhole intrinsics of the (undistorted) keypoints the geometry uses.
        K_source: N strings: ``file:<path>``, ``exif``, ``estimated:<method>[ (exif prior …)]`` or ``default``.
        models: N COLMAP camera models (with the distortion).
        distortion_source: N strings: ``file:<path>``, ``estimated:radial`` or ``none``.
        keypoints: N undistorted keypoint arrays (n_i, 2), or None when no image has distortion.
        estimate: the estimates (per camera group) and their diagnostics.
        digest: the stage's fingerprint.
    """

    names: list[str]
    sizes: np.ndarray
    K: np.ndarray
    K_source: list[str]
    models: list[CameraModel]
    distortion_source: list[str]
    keypoints: list[np.ndarray] | None = None
    estimate: dict[str, Any] = field(default_factory=dict)
    digest: str = ""

    @property
    def known(self) -> np.ndarray:
        """(N,) True where the intrinsics come from a file (never refined)."""
        return np.array([given_source(s) for s in self.K_source], bool)

    def keypoints_for_geometry(self, raw: Sequence[np.ndarray]) -> list[np.ndarray]:
        """The keypoints the geometry uses: undistorted where there is distortion, else ``raw``."""
        return list(raw) if self.keypoints is None else self.keypoints


def given_source(source: str) -> bool:
    """Whether a K source is given by the user (a file, or a COLMAP database's camera: its keypoints are
    undistorted already), not estimated here."""
    return source.startswith(("file", "database:"))


def _file_sources(sources: Sequence[str]) -> list[str]:
    return sorted({s[len("file:"):] for s in sources if s.startswith("file:")})


def _path_fingerprint(path: Path) -> str:
    if path.is_dir():
        return fingerprint_of([(p.name, file_fingerprint(p)) for p in sorted(path.iterdir())
                               if p.is_file() and p.name.split(".")[0] in ("cameras", "images")])
    return file_fingerprint(path)


def _model_from_K(K: np.ndarray, w: int, h: int) -> CameraModel:
    """The COLMAP PINHOLE model of a K (skew, which COLMAP cannot hold, is dropped from the model only)."""
    return CameraModel("PINHOLE", int(w), int(h), (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + COLMAP_OFFSET,
                                                  float(K[1, 2]) + COLMAP_OFFSET))


def _groups(keys: list[Any], member: np.ndarray) -> dict[Any, np.ndarray]:
    out: dict[Any, list[int]] = {}
    for k in np.flatnonzero(member):
        out.setdefault(keys[k], []).append(int(k))
    return {g: np.array(v) for g, v in out.items()}


class CamerasStage(Stage[CamerasConfig]):
    """Camera models of the images of a WORK folder (folder = WORK)."""

    name = NAME
    title = "cameras (intrinsics, distortion)"
    config_cls = CamerasConfig
    version = 3  # 2: a focal estimated from no pair is not 'determined'; 3: the view-graph calibration keeps the
    # pairs of images whose names hold a space

    def inputs(self) -> dict[str, str]:
        # the first round's matches: a loop-closure round (pipeline.frontend.loop_stage) adds pairs, not cameras
        rec = self.upstream("matching")
        return {**self.file_inputs(), "matching": str(rec.summary.get("base") or rec.fingerprint)}

    def file_inputs(self) -> dict[str, str]:
        """The inputs besides the matches: the features, and the camera files whose distortion is read here."""
        inp = {"features": self.upstream("features").fingerprint}
        from pipeline.frontend.feature_stage import load_manifest  # noqa: PLC0415

        for src in _file_sources(load_manifest(self.folder).get("K_source", [])):
            if is_camera_model_file(src):  # its distortion is read here, not by the features
                inp[f"camera_file:{src}"] = _path_fingerprint(Path(src))
        return inp

    def run(self, overwrite: bool = False) -> StageRecord:
        if overwrite:
            shutil.rmtree(self.folder / STORE, ignore_errors=True)
        return super().run(overwrite)

    # ----------------------------------------------------------- per-pair work
    def _pmap(self, tag: str, tasks: list[tuple], worker: Any) -> list[dict[str, Any]]:
        """Run ``worker`` over ``tasks`` in chunks on an executor, each finished chunk kept in the store."""
        fp = self.config.fingerprint()
        keys = [item_key(fp, tag, *task) for task in tasks]
        self._keys.extend(keys)
        self._store.drop_damaged(keys, lambda k, item: check_item(worker, tasks[k], item),
                                 f"pairs' {tag} results in {self._store.folder}")
        done = self._store.done(keys)
        with tqdm(total=len(keys), initial=sum(k in done for k in keys), desc=f"cameras {tag}", unit="pair",
                  disable=not self.config.progress) as bar:
            compute_missing(self._store, keys, tasks.__getitem__, worker, workers=self.config.workers,
                            chunk_size=self.config.chunk_size, on_chunk=bar.update)
        return [{k: (v.item() if v.ndim == 0 else v) for k, v in self._store.get(key).items()} for key in keys]

    # ------------------------------------------------------------------ compute
    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        from pipeline.features import load_features  # noqa: PLC0415
        from pipeline.matching import load_matches  # noqa: PLC0415

        cfg, work = self.config, self.folder
        logger.info("cameras: %s", cfg)
        fs = load_features(work, descriptors=False)
        n = len(fs.names)
        K, sources = fs.K.copy(), list(fs.K_source) or ["default"] * n
        models: list[CameraModel | None] = [None] * n
        dist_src = ["none"] * n
        for src in _file_sources(sources):
            for k, cam in enumerate(camera_models_for_names(src, fs.names)):
                if cam is not None and sources[k] == f"file:{src}":
                    models[k] = cam
                    dist_src[k] = f"file:{src}" if cam.has_distortion else "none"
        known = np.array([given_source(s) for s in sources], bool)
        from_file = np.array([m is not None for m in models], bool)
        radial_set = ~from_file & (~known if cfg.radial == "auto" else np.ones(n, bool))
        if cfg.radial == "off":
            radial_set[:] = False
        focal_set = ~known if cfg.estimate_focal else np.zeros(n, bool)
        exif = [float(K[k, 0, 0]) if sources[k] == "exif" else None for k in range(n)]
        gkey = [(int(fs.sizes[k, 0]), int(fs.sizes[k, 1]), None if exif[k] is None else round(exif[k], 1))
                for k in range(n)]
        self._store, self._keys = ItemStore(work / STORE), []
        kp = [np.asarray(x, np.float64) for x in fs.keypoints]
        undistorted = [False] * n
        for k in np.flatnonzero(from_file):
            if models[k].has_distortion:  # type: ignore[union-attr]
                kp[k], undistorted[k] = undistort_points(models[k], kp[k]), True  # type: ignore[arg-type]
        estimate: dict[str, Any] = {"groups": []}
        ev = None
        if radial_set.any() or focal_set.any():  # the estimation's own keypoints and matches
            ev = self._evidence(fs, load_matches(work))
            estimate["redetected"] = ev.redetected
        redetected = set(ev.redetected if ev is not None else [])
        ekp = [ev.keypoints[k] if fs.names[k] in redetected else kp[k] for k in range(n)]
        scale = np.ones(n)
        max_size = fs.config.max_image_size if fs.config is not None else 0
        if max_size > 0:
            scale = np.maximum(fs.sizes.max(axis=1) / max_size, 1.0)
        kappa = np.zeros(n)
        for g, members in _groups(gkey, radial_set).items():
            x1, x2, _, sc = self._pair_data(ev, members, ekp, scale)
            r = estimate_radial(x1, x2, g[:2], sc, cfg, self._pmap, tag=f"radial-{g[0]}x{g[1]}-{g[2]}")
            estimate["groups"].append({"images": [fs.names[k] for k in members], "radial": r.summary()})
            logger.info("cameras: radial κ = %.4f (raw %.4f, Δχ² %.1f / dispersion %.2f vs %.1f, %s) for %d image(s) "
                        "of %dx%d from %d pairs", r.kappa, r.kappa_raw, r.delta_chi2, max(r.dispersion, 1.0),
                        r.critical, "kept" if r.significant else "not significant", len(members), g[0], g[1],
                        r.n_pairs)
            if r.kappa != 0.0:
                for k in members:
                    kp[k], undistorted[k] = radial_undistort(kp[k], r.c, r.s, r.kappa)[0], True
                    ekp[k] = radial_undistort(ekp[k], r.c, r.s, r.kappa)[0] if fs.names[k] in redetected else kp[k]
                    kappa[k], dist_src[k] = r.kappa, "estimated:radial"
        for g, members in _groups(gkey, focal_set).items():
            x1, x2, pairs, sc = self._pair_data(ev, members, ekp, scale)
            est = estimate_focal(x1, x2, pairs, len(members), g[:2], cfg.threshold_px * sc, cfg, self._pmap,
                                 prior=g[2], tag=f"focal-{g[0]}x{g[1]}-{g[2]}")
            entry = {"images": [fs.names[k] for k in members], "focal": est.summary()}
            if np.isfinite(est.f):
                pp = np.array([(g[0] - 1) / 2.0, (g[1] - 1) / 2.0])
                for k in members:
                    K[k] = K_from_focal(est.f, pp)
                    sources[k] = f"estimated:{est.method}" + (f" ({est.prior} prior)" if est.prior else "")
            else:
                logger.warning("cameras: the focal of %d image(s) of %dx%d cannot be estimated (%s); keeping the %s "
                               "focal %.1f px", len(members), g[0], g[1], est.note, sources[members[0]],
                               K[members[0], 0, 0])
            if not est.determined:
                logger.warning("cameras: %d image(s) of %dx%d: %s", len(members), g[0], g[1], est.note)
            self._merge_group(estimate, entry)
            logger.info("cameras: focal %.1f px (%s%s) for %d image(s) of %dx%d from %d pairs", est.f, est.method,
                        f", {est.prior} prior" if est.prior else "", len(members), g[0], g[1], est.n_pairs)
        if cfg.per_image_focal == "auto" and ev is not None and focal_set.sum() >= 2 and len(ev.pairs):
            prior = known | np.array([e is not None for e in exif])
            self._per_image_focal(fs, ev.pairs, ev.matches, ekp, K, sources, focal_set, prior, gkey, estimate)
        final = [self._final_model(models[k], K[k], kappa[k], fs.sizes[k]) for k in range(n)]
        return self._write(fs, K, sources, final, dist_src, kp, any(undistorted), estimate)

    def _per_image_focal(self, fs: Any, pairs: np.ndarray, matches: list[np.ndarray], kp: list[np.ndarray],
                         K: np.ndarray, sources: list[str], focal_set: np.ndarray, prior: np.ndarray,
                         gkey: list[Any], estimate: dict[str, Any]) -> None:
        """Per-image focal lengths by pycolmap's view-graph calibration, kept where the view graph prefers them.

        The calibrator starts from the group focal lengths and, where those differ from the features' start
        values (EXIF or 1.2·max(w, h)), also from the latter: a group focal that is far off can hold it in a
        wrong minimum. The choice is :func:`~pipeline.frontend.vg_calibration.choose_focal_lengths`. ``K`` and
        ``sources`` are updated in place for the images of ``focal_set``; the costs and the decision go into
        ``estimate["per_image"]``.
        """
        cfg = self.config
        starts = {"group": K} | ({"start": fs.K} if not np.allclose(K[focal_set], fs.K[focal_set]) else {})
        cals = calibrate_focals(list(fs.names), fs.sizes, list(starts.values()), prior, kp, pairs, matches,
                                self.folder, cfg.seed)
        fitted = [gkey[k] if sources[k].startswith("estimated:") else None for k in range(len(K))]
        guessed = np.array([sources[k] == "default" for k in range(len(K))])  # no file, no EXIF, no estimate
        choice = choose_focal_lengths(cals, list(starts), list(starts.values()), K, kp, list(fs.names), focal_set,
                                      fitted, cfg.per_image_level, cfg.rotation_loss_deg, guessed)
        estimate["per_image"] = choice.record
        rec = choice.record
        logger.info("cameras: view-graph calibration (%d pairs): rotation consistency %s with per-image focal "
                    "lengths, %.4g with the group ones (%s): %s", rec["n_pairs"],
                    " / ".join(f"{v['consistency']:.4g}" for v in rec["calibrations"].values()), rec["consistency_group"],
                    f"F {rec['F']:.3g} vs {rec['F_critical']:.3g}" if rec["no_test"] is None else f"no F test: {rec['no_test']}",
                    "per-image kept" if choice.chosen else "group focal lengths kept")
        changed_names = {fs.names[k] for k in choice.changed}
        for g in estimate["groups"]:
            if "focal" in g and changed_names.intersection(g["images"]):
                g["focal"] = g["focal"] | {"determined": None, "group_note": g["focal"].get("note", ""),
                                           "note": choice.why}
        for k in choice.changed:
            K[k] = choice.K[k]
            sources[k] = PER_IMAGE_SOURCE + (" (exif prior)" if prior[k] else "")

    def _evidence(self, fs: Any, ms: Any) -> Evidence:
        """The keypoints and matches the estimation uses (``evidence``, :mod:`pipeline.frontend.camera_evidence`)."""
        if self.config.evidence == "features":
            return features_evidence(fs, ms)
        return stage_evidence(self.folder, fs, ms)

    @staticmethod
    def _merge_group(estimate: dict[str, Any], entry: dict[str, Any]) -> None:
        for g in estimate["groups"]:
            if g["images"] == entry["images"]:
                g.update(entry)
                return
        estimate["groups"].append(entry)

    @staticmethod
    def _pair_data(ms: Any, members: np.ndarray, kp: list[np.ndarray], scale: np.ndarray
                   ) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray, np.ndarray]:
        """The matched pairs inside ``members``: pixels, pairs (in group indices) and threshold scales."""
        pos = np.full(len(kp), -1)
        pos[members] = np.arange(len(members))
        inside = np.flatnonzero((pos[ms.pairs[:, 0]] >= 0) & (pos[ms.pairs[:, 1]] >= 0))
        x1 = [kp[ms.pairs[p, 0]][ms.matches[p][:, 0]] for p in inside]
        x2 = [kp[ms.pairs[p, 1]][ms.matches[p][:, 1]] for p in inside]
        pairs = pos[ms.pairs[inside]].reshape(-1, 2)
        return x1, x2, pairs, 0.5 * (scale[ms.pairs[inside, 0]] + scale[ms.pairs[inside, 1]])

    @staticmethod
    def _final_model(model: CameraModel | None, K: np.ndarray, kappa: float, size: np.ndarray) -> CameraModel:
        w, h = int(size[0]), int(size[1])
        if model is not None:
            return model
        if kappa != 0.0:
            s = float(max(w, h))
            k1 = kappa * K[0, 0] * K[1, 1] / (s * s)  # κ at scale s is k1 = κ f²/s² (SIMPLE_RADIAL)
            return CameraModel("SIMPLE_RADIAL", w, h, (float(K[0, 0]), float(K[0, 2]) + COLMAP_OFFSET,
                                                       float(K[1, 2]) + COLMAP_OFFSET, k1))
        return _model_from_K(K, w, h)

    def _write(self, fs: Any, K: np.ndarray, sources: list[str], models: list[CameraModel], dist_src: list[str],
               kp: list[np.ndarray], undistorted: bool, estimate: dict[str, Any]) -> tuple[list[Path], dict[str, Any]]:
        paths: list[Path] = []
        if undistorted:
            counts = np.array([len(x) for x in kp], np.int64)
            xy = np.concatenate(kp).reshape(-1, 2) if kp else np.zeros((0, 2))
            paths.append(save_npz(self.folder / KEYPOINTS, offsets=np.concatenate([[0], np.cumsum(counts)]), xy=xy))
        else:
            (self.folder / KEYPOINTS).unlink(missing_ok=True)
        manifest = {"format": "rotavg-cameras", "names": list(fs.names), "sizes": fs.sizes.tolist(), "K": K.tolist(),
                    "K_source": sources, "models": [m.as_dict() for m in models], "distortion_source": dist_src,
                    "undistorted_keypoints": bool(undistorted), "estimate": estimate}
        paths.append(write_json(self.folder / MANIFEST, manifest))
        paths += self._store.write_index(self._keys)
        summary = {"n_images": len(fs.names), "n_estimated": sum(s.startswith("estimated") for s in sources),
                   "n_file": sum(s.startswith("file") for s in sources), "n_undistorted": int(undistorted and sum(
                       d != "none" for d in dist_src)), "focal_px": focal_summary(K, sources),
                   "groups": intrinsics_summary(CameraSet(list(fs.names), fs.sizes, K, sources, models, dist_src,
                                                          estimate=estimate))["estimates"]}
        return paths, summary

    def verify(self, record: StageRecord) -> None:
        cams = _read(self.folder, record)
        from pipeline.frontend.feature_stage import load_manifest  # noqa: PLC0415

        if cams.names != list(load_manifest(self.folder)["names"]):
            raise CacheError(f"{self.folder / MANIFEST} describes other images than the current features")


def _read(work: Path, rec: StageRecord | None) -> CameraSet:
    path = Path(work) / MANIFEST
    if not path.is_file():
        raise InputFileError(f"{path} not found: run `python -m pipeline.cameras --work {work}` first")
    try:
        m = json.loads(path.read_text(encoding="utf-8"))
        n = len(m["names"])
        K = np.asarray(m["K"], np.float64).reshape(n, 3, 3)
        sizes = np.asarray(m["sizes"], np.int64).reshape(n, 2)
        models = [CameraModel(d["model"], int(d["width"]), int(d["height"]), tuple(float(p) for p in d["params"]))
                  for d in m["models"]]
        if not (len(m["K_source"]) == len(models) == len(m["distortion_source"]) == n) or not np.isfinite(K).all():
            raise ValueError("per-image lists of different lengths or a K that is not finite")
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run pipeline.cameras") from None
    kps = None
    if m.get("undistorted_keypoints"):
        from pipeline.geometry.stage_io import read_npz  # noqa: PLC0415

        arr = read_npz(Path(work) / KEYPOINTS, "keypoints file")
        off, xy = arr.get("offsets"), arr.get("xy")
        if off is None or xy is None or off.shape != (n + 1,) or xy.ndim != 2 or xy.shape[1] != 2 or \
                off[-1] != len(xy) or np.any(np.diff(off) < 0) or not np.isfinite(xy).all():
            raise CacheError(f"{Path(work) / KEYPOINTS} is damaged (offsets and keypoints disagree); re-run "
                             "pipeline.cameras")
        kps = [xy[off[k]:off[k + 1]] for k in range(n)]
    return CameraSet(list(m["names"]), sizes, K, list(m["K_source"]), models, list(m["distortion_source"]), kps,
                     dict(m.get("estimate") or {}), rec.fingerprint if rec is not None else "")


def cameras_for(work: Path, names: Sequence[str]) -> CameraSet | None:
    """The cameras stage's result in ``work`` for the images ``names``; None when the stage has not run.

    Raises:
        InputFileError: the result is of other images than ``names`` (the front end changed since).
    """
    if read_record(work, NAME) is None:
        return None
    cams = load_cameras(work)
    if cams.names != list(names):
        raise InputFileError(f"{work}: the cameras were computed for other images than the current features; "
                             f"re-run `python -m pipeline.cameras --work {work}`")
    return cams


def load_cameras(work: Path) -> CameraSet:
    """The camera models the cameras stage wrote in ``work``.

    Raises:
        InputFileError: the stage has not run in ``work``.
        CacheError: its files are damaged (a re-run of the stage heals them).
    """
    work = Path(work)
    rec = read_record(work, NAME)
    if rec is None:
        raise InputFileError(f"{work} has no result of the cameras stage: run `python -m pipeline.cameras --work "
                             f"{work}` first")
    return _read(work, rec)


def main(work: Path, config: CamerasConfig | None = None, overwrite: bool = False) -> Path:
    """Run the stage (reusing an intact cached result); returns the manifest path."""
    CamerasStage(work, config).run(overwrite)
    return Path(work) / MANIFEST


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.geometry.stage_io import stage_cli  # noqa: PLC0415

    return stage_cli(CamerasStage, "python -m pipeline.cameras",
                     "Camera models of WORK's images: K from a file, or focal length and radial distortion "
                     "estimated from the view graph; keypoints undistorted.", MANIFEST, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
