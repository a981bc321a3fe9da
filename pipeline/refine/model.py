"""The pycolmap side of the refinement's inputs: an in-memory COLMAP database and the starting reconstruction.

- :func:`correspondence_cache` writes our cameras, keypoints, kept pairs' inlier
  matches and relative poses into an in-memory COLMAP database (no file) and returns
  pycolmap's ``DatabaseCache`` (its correspondence graph feeds the pose graph and
  the retriangulation).
- :func:`starting_reconstruction` builds the reconstruction to refine, with our
  rotations and every track as a 3D point, in one batch: pycolmap 4.2.1 has no batch
  call for points (``Reconstruction.add_point3D`` takes one track), so the model is
  written in COLMAP's binary format from numpy (:func:`write_binary_model`, no Python
  loop over points or observations) and read back with ``Reconstruction.read_binary``.

Ids: image ``k`` of the caller's list is COLMAP image (and frame) ``k + 1``; cameras
are shared by images with the same K, size and knownness (ids from 1). Pixel
convention: our keypoints and K put pixel centres at integers, COLMAP at +0.5
(:data:`pipeline.reference.database.COLMAP_PIXEL_OFFSET`); both are shifted here, the
one place where our data crosses into pycolmap.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import TMP_TAG
from pipeline.reference.database import COLMAP_PIXEL_OFFSET, pinhole_params
from pipeline.refine.tracks import Tracks

__all__ = ["camera_groups", "check_inputs", "radial_terms", "correspondence_cache", "write_binary_model",
           "starting_reconstruction", "model_rotations", "INVALID_POINT3D_ID"]

INVALID_POINT3D_ID = np.iinfo(np.uint64).max  # COLMAP's kInvalidPoint3DId
_SIMPLE_PINHOLE, _PINHOLE, _SIMPLE_RADIAL = 0, 1, 2  # COLMAP's model ids
_MODEL_NAMES = {_SIMPLE_PINHOLE: "SIMPLE_PINHOLE", _PINHOLE: "PINHOLE", _SIMPLE_RADIAL: "SIMPLE_RADIAL"}


def radial_terms(n: int, k1: np.ndarray | None) -> np.ndarray:
    """(n,) starting radial terms: ``k1``, or 0 for every camera (undistorted keypoints)."""
    return np.zeros(n) if k1 is None else np.asarray(k1, float)


def camera_groups(K: np.ndarray, sizes: np.ndarray, known: np.ndarray, k1: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One COLMAP camera per distinct (K, size, known, k1): ``(camera id (N,), first image of each camera (C,))``."""
    k1 = radial_terms(len(K), k1)
    key = np.concatenate([np.asarray(K, float).reshape(len(K), 9), np.asarray(sizes, float).reshape(-1, 2),
                          np.asarray(known, float).reshape(-1, 1), k1.reshape(-1, 1)], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return inverse.reshape(-1) + 1, first


def colmap_camera(K: np.ndarray, known: bool, radial: bool = False, k1: float = 0.0) -> tuple[int, list[float]]:
    """COLMAP's model id and parameters of our K: PINHOLE where known; where refined, SIMPLE_PINHOLE (one focal
    length) when K has one focal length, or with ``radial`` SIMPLE_RADIAL from ``k1`` (one focal length and one
    radial term, as COLMAP's mappers model an unknown camera: k1 = 0 on the cameras stage's undistorted keypoints,
    the stage's own k1 on the measured ones). A nonzero ``k1`` is SIMPLE_RADIAL even without ``radial`` (then held
    constant by the bundle adjustment): the keypoints are the measured ones, and the lens must stay modelled.

    Refined separately, fx and fy let the bundle adjustment trade one against the rotations: on the
    templeSparseRing without K (a turntable ring, a critical motion for the focal length), fx drifted by 80%
    (standard deviation 770 px) while fy stayed within 1% (21 px), and the rotations went 3.6° wrong.
    """
    p = pinhole_params(K)
    if not known and K[0, 0] == K[1, 1]:
        if radial or k1 != 0.0:
            return _SIMPLE_RADIAL, [p[0], p[2], p[3], float(k1)]
        return _SIMPLE_PINHOLE, [p[0], p[2], p[3]]
    if k1 != 0.0:
        raise ValueError("a radial term needs an unknown camera with one focal length (SIMPLE_RADIAL)")
    return _PINHOLE, p


def _camera(pc: Any, camera_id: int, K: np.ndarray, size: np.ndarray, known: bool, radial: bool, k1: float) -> Any:
    model, params = colmap_camera(K, known, radial, k1)
    cam = pc.Camera(model=_MODEL_NAMES[model], width=int(size[0]), height=int(size[1]), params=params,
                    camera_id=int(camera_id))
    cam.has_prior_focal_length = bool(known)
    return cam


def correspondence_cache(pc: Any, names: Sequence[str], K: np.ndarray, sizes: np.ndarray, known: np.ndarray,
                         keypoints: Sequence[np.ndarray], images: np.ndarray, edges: np.ndarray,
                         match_offsets: np.ndarray, matches: np.ndarray, cam2_from_cam1: np.ndarray,
                         t_cam2_from_cam1: np.ndarray, radial: bool = False, k1: np.ndarray | None = None) -> Any:
    """A ``pycolmap.DatabaseCache`` of the images ``images`` and the given pairs (an in-memory database).

    Args:
        names, K (N, 3, 3), sizes (N, 2), known (N,), keypoints (N arrays (n_i, 2)): every image.
        images: indices of the images to include (the others are left out).
        edges: (M, 2) pairs among ``images``; match_offsets (M+1,), matches (T, 2): their inlier
            keypoint indices; cam2_from_cam1 (M, 3, 3) and t_cam2_from_cam1 (M, 3): relative poses.
        radial: unknown cameras as SIMPLE_RADIAL (:func:`colmap_camera`).
        k1: (N,) each camera's starting radial term (default 0: undistorted keypoints).
    """
    k1 = radial_terms(len(K), k1)
    cam_id, _ = camera_groups(K, sizes, known, k1)
    db = pc.Database.open(":memory:")
    try:
        written: set[int] = set()
        for k in np.asarray(images, np.int64).tolist():  # one call per image: no batch writer exists
            c = int(cam_id[k])
            if c not in written:
                cam = _camera(pc, c, K[k], sizes[k], bool(known[k]), radial, float(k1[k]))
                db.write_camera(cam, use_camera_id=True)
                rig = pc.Rig(rig_id=c)
                rig.add_ref_sensor(cam.sensor_id)
                db.write_rig(rig, use_rig_id=True)
                written.add(c)
            image = pc.Image(name=str(names[k]), camera_id=c, image_id=k + 1)
            db.write_image(image, use_image_id=True)
            frame = pc.Frame(frame_id=k + 1, rig_id=c)
            frame.add_data_id(image.data_id)
            db.write_frame(frame, use_frame_id=True)
            kp = np.asarray(keypoints[k], np.float32).reshape(-1, 2) + np.float32(COLMAP_PIXEL_OFFSET)
            db.write_keypoints(k + 1, np.ascontiguousarray(kp))
        m32 = np.ascontiguousarray(np.asarray(matches).reshape(-1, 2).astype(np.uint32))
        off = np.asarray(match_offsets, np.int64).tolist()
        for e, (i, j) in enumerate(np.asarray(edges, np.int64).reshape(-1, 2).tolist()):  # one call per pair
            m = m32[off[e]:off[e + 1]]
            g = pc.TwoViewGeometry()
            g.config = pc.TwoViewGeometryConfiguration.CALIBRATED
            g.inlier_matches = m
            g.cam2_from_cam1 = pc.Rigid3d(pc.Rotation3d(cam2_from_cam1[e]), np.asarray(t_cam2_from_cam1[e], float))
            db.write_matches(i + 1, j + 1, m)
            db.write_two_view_geometry(i + 1, j + 1, g)
        opts = pc.DatabaseCacheOptions()
        opts.load_all_images = True
        return pc.DatabaseCache.create(db, opts)
    finally:
        db.close()


def _fill(buf: np.ndarray, starts: np.ndarray, records: np.ndarray) -> None:
    """Copy fixed-size binary ``records`` (R,) of a structured dtype into ``buf`` at byte offsets ``starts`` (R,)."""
    if len(records) == 0:
        return
    raw = np.ascontiguousarray(records).view(np.uint8).reshape(len(records), -1)
    for c in range(raw.shape[1]):  # one strided copy per byte of the record: memory O(R), not O(R × size)
        buf[starts + c] = raw[:, c]


def write_binary_model(folder: Path, *, camera_ids: np.ndarray, camera_models: np.ndarray,
                       camera_params: Sequence[Sequence[float]], camera_sizes: np.ndarray,
                       image_ids: np.ndarray, image_camera_ids: np.ndarray, image_names: Sequence[str],
                       cam_from_world: np.ndarray, points2D: Sequence[np.ndarray], tracks: Tracks,
                       track_image_ids: np.ndarray) -> None:
    """Write ``cameras.bin``, ``images.bin`` and ``points3D.bin`` (COLMAP's binary format) from arrays.

    Every image is registered at its rotation (translation zero); every track is a
    3D point at the origin, id ``p + 1``. pycolmap's reader adds a trivial rig and
    frame per image. Rotations (``cam_from_world`` (N, 3, 3)) and points are packed
    with numpy; only the per-image header is written per image.

    Args:
        camera_ids (C,), camera_models (C,) COLMAP model ids, camera_params: C parameter lists in COLMAP's
            convention, camera_sizes (C, 2).
        image_ids (N,), image_camera_ids (N,), image_names (N,), cam_from_world (N, 3, 3).
        points2D: N arrays (n_i, 2) in COLMAP's pixel convention.
        tracks: the tracks, with ``tracks.image`` indexing ``image_ids``.
        track_image_ids: (Q,) COLMAP image id of each observation.
    """
    folder = Path(folder)
    cam = np.zeros(len(camera_ids), np.dtype([("id", "<u4"), ("model", "<i4"), ("w", "<u8"), ("h", "<u8")]))
    cam["id"], cam["model"] = camera_ids, camera_models
    cam["w"], cam["h"] = np.asarray(camera_sizes)[:, 0], np.asarray(camera_sizes)[:, 1]
    (folder / "cameras.bin").write_bytes(np.uint64(len(cam)).tobytes() + b"".join(  # per camera (C): few
        c.tobytes() + np.asarray(p, "<f8").tobytes() for c, p in zip(cam, camera_params)))

    # each observation's point id, per image: track p is point p + 1
    n2d = np.array([len(p) for p in points2D], np.int64)
    base = np.concatenate([[0], np.cumsum(n2d)])
    pid = np.full(int(base[-1]), INVALID_POINT3D_ID, np.uint64)
    pid[base[tracks.image] + tracks.keypoint] = np.repeat(np.arange(1, tracks.n_tracks + 1, dtype=np.uint64),
                                                          tracks.lengths)
    q = so3.quat_from_matrix(np.asarray(cam_from_world, float).reshape(-1, 3, 3))
    head = np.dtype([("id", "<u4"), ("q", "<f8", (4,)), ("t", "<f8", (3,)), ("camera", "<u4")])
    pt = np.dtype([("xy", "<f8", (2,)), ("id", "<u8")])
    parts = [np.uint64(len(image_ids)).tobytes()]
    for k in range(len(image_ids)):  # per image (N), everything inside is vectorized
        h = np.zeros(1, head)
        h["id"], h["q"], h["camera"] = image_ids[k], q[k], image_camera_ids[k]
        p = np.zeros(n2d[k], pt)
        p["xy"], p["id"] = points2D[k], pid[base[k]:base[k + 1]]
        parts += [h.tobytes(), str(image_names[k]).encode() + b"\0", np.uint64(n2d[k]).tobytes(), p.tobytes()]
    (folder / "images.bin").write_bytes(b"".join(parts))

    point = np.zeros(tracks.n_tracks, np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)),
                                                ("error", "<f8"), ("length", "<u8")]))
    point["id"], point["length"] = np.arange(1, tracks.n_tracks + 1), tracks.lengths
    element = np.zeros(len(tracks.image), np.dtype([("image", "<u4"), ("point2D", "<u4")]))
    element["image"], element["point2D"] = track_image_ids, tracks.keypoint
    size_p, size_e = point.dtype.itemsize, element.dtype.itemsize
    starts = 8 + np.arange(tracks.n_tracks) * size_p + tracks.offsets[:-1] * size_e
    buf = np.zeros(8 + tracks.n_tracks * size_p + len(element) * size_e, np.uint8)
    buf[:8] = np.frombuffer(np.uint64(tracks.n_tracks).tobytes(), np.uint8)
    _fill(buf, starts, point)
    track_of = np.repeat(np.arange(tracks.n_tracks), tracks.lengths)
    within = np.arange(len(element)) - tracks.offsets[:-1][track_of]
    _fill(buf, starts[track_of] + size_p + within * size_e, element)
    (folder / "points3D.bin").write_bytes(buf.tobytes())


def starting_reconstruction(pc: Any, names: Sequence[str], K: np.ndarray, sizes: np.ndarray, known: np.ndarray,
                            keypoints: Sequence[np.ndarray], images: np.ndarray, cam_from_world: np.ndarray,
                            tracks: Tracks, scratch: Path | None = None, radial: bool = False,
                            k1: np.ndarray | None = None) -> Any:
    """The reconstruction to refine: the images ``images`` registered at ``cam_from_world``, every track a point.

    Args:
        names, K (N, 3, 3), sizes (N, 2), known (N,), keypoints: every image (indexed as in ``tracks``).
        images: indices of the images in the reconstruction (the tracks only observe these).
        cam_from_world: (N, 3, 3) starting rotations.
        scratch: folder for the temporary binary model (tagged, removed at once); default: system temp.
        radial: unknown cameras as SIMPLE_RADIAL (:func:`colmap_camera`).
        k1: (N,) each camera's starting radial term (default 0: undistorted keypoints).
    """
    images = np.asarray(images, np.int64)
    k1 = radial_terms(len(K), k1)
    cam_id, first = camera_groups(K, sizes, known, k1)
    used = np.unique(cam_id[images])
    rep = first[used - 1]  # one image of each used camera
    models, params = zip(*(colmap_camera(K[k], bool(known[k]), radial, float(k1[k])) for k in rep)) \
        if len(rep) else ((), ())
    pos = np.full(len(names), -1, np.int64)
    pos[images] = np.arange(len(images))
    local = Tracks(tracks.offsets, pos[tracks.image], tracks.keypoint)
    if np.any(local.image < 0):
        raise ValueError("a track observes an image that is not in the reconstruction")
    kp = [np.asarray(keypoints[k], np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET for k in images]
    if scratch is not None:
        Path(scratch).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".model{TMP_TAG}", dir=scratch) as tmp:
        write_binary_model(Path(tmp), camera_ids=used, camera_models=np.asarray(models, np.int64),
                           camera_params=list(params), camera_sizes=np.asarray(sizes)[rep],
                           image_ids=images + 1, image_camera_ids=cam_id[images], image_names=[names[k] for k in images],
                           cam_from_world=np.asarray(cam_from_world)[images], points2D=kp, tracks=local,
                           track_image_ids=tracks.image + 1)
        rec = pc.Reconstruction()
        rec.read_binary(tmp)
    return rec


def model_rotations(rec: Any, n: int) -> np.ndarray:
    """(n, 3, 3) cam_from_world of image ``k`` = COLMAP image ``k + 1`` of ``rec``; NaN where not registered."""
    R = np.full((n, 3, 3), np.nan)
    for iid in rec.reg_image_ids():  # per image: pycolmap returns poses one by one
        R[iid - 1] = rec.image(iid).cam_from_world().rotation.matrix()
    return R


def check_inputs(n: int, K: np.ndarray, sizes: np.ndarray, keypoints: Sequence[np.ndarray], edges: np.ndarray,
                 match_offsets: np.ndarray, cam2_from_cam1: np.ndarray, t: np.ndarray, R_init: np.ndarray) -> None:
    """:func:`~pipeline.refine.refine.refine_rotations`'s arrays against each other: ValueError naming each mismatch."""
    m = len(edges)
    got = {"K": K.shape, "sizes": sizes.shape, "R_init": R_init.shape, "cam2_from_cam1": cam2_from_cam1.shape,
           "t_cam2_from_cam1": t.shape, "match_offsets": match_offsets.shape}
    want = {"K": (n, 3, 3), "sizes": (n, 2), "R_init": (n, 3, 3), "cam2_from_cam1": (m, 3, 3),
            "t_cam2_from_cam1": (m, 3), "match_offsets": (m + 1,)}
    bad = [f"{k}.shape={got[k]} but expected {want[k]}" for k in want if got[k] != want[k]]
    if len(keypoints) != n:
        bad.append(f"{len(keypoints)} keypoint arrays but expected {n}")
    if m and (np.any(edges[:, 0] >= edges[:, 1]) or edges.min() < 0 or edges.max() >= n):
        bad.append(f"edges must be pairs (i, j) with 0 <= i < j < {n}")
    if bad:
        raise ValueError(f"refine_rotations: {'; '.join(bad)} (for {n} images and {m} pairs)")
