"""Large rendered scenes with known cameras and the truly overlapping pairs (street, ring, grid).

The layouts are :mod:`pipeline.synthetic.large_layouts`; this module renders them
(exactly, through plane-induced homographies with a z-buffer, as
:mod:`pipeline.synthetic.render`, with near-plane clipping and frustum culling so that
a facade extending behind the camera costs only the part of the image it covers) and
records which pairs truly overlap.

True overlap: points are sampled uniformly on every surface; a point is *visible* in
a view when it projects inside the image, in front of the camera, and its depth
agrees with the rendered depth map (occlusion). A point is *co-visible* in views i
and j when it is visible in both and the local affine map between its two images
(the derivative of the plane-induced homography) has a transition tilt σ₁/σ₂ ≤
``max_tilt`` (2) and a scale change within a factor ``max_scale`` (2): SIFT does not
match across larger viewpoint or scale changes (Morel & Yu's affine-SIFT analysis).
The overlap score of a pair is ``n_co / min(n_i, n_j)``; a pair *truly overlaps*
when its score is at least ``overlap_threshold`` (0.1).

Output folder (generated at run time; never committed)::

    DIR/view_000.png ...    images (8-bit RGB PNG), in capture order
    DIR/cameras.txt         name fx fy cx cy r11..r33 t1 t2 t3 (cam_from_world)
    DIR/K.txt               the common 3x3 intrinsics
    DIR/overlap.npz         pairs (P, 2) i<j with any co-visible point, score (P,), n_co, n_raw (P,),
                            n_visible (N,), threshold, centers (N, 3)
    DIR/true_pairs.txt      the truly overlapping pairs as a pairs file ('name_a name_b' lines)
    DIR/scene.json          layout, config, timings, counts

Command line::

    python -m pipeline.synthetic.large --layout street --views 300 --out DIR [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse as sp

from pipeline.core.atomic import atomic_open, atomic_path, check_writable, save_npz, write_json
from pipeline.core.errors import InputFileError
from pipeline.synthetic.large_layouts import LAYOUTS, LargeSceneConfig, make_scene
from pipeline.synthetic.render import supersampled_grid, write_cameras_txt
from pipeline.synthetic.scene import Plane

__all__ = ["plane_geometry", "render_view_clipped", "visibility", "pair_overlap", "true_pairs", "load_overlap",
           "write_pairs_file", "render_large", "main", "main_cli"]

# ------------------------------------------------------------------ rendering


def _clipped_bbox(Xc: np.ndarray, Ks: np.ndarray, W: int, H: int, z_near: float = 1e-3) -> tuple[int, int, int, int] | None:
    """Pixel bounding box ``(x0, y0, x1, y1)`` of a convex polygon (k, 3) in camera coordinates,
    clipped to z ≥ z_near and to the image; None when nothing of it is in view."""
    pts = []
    k = len(Xc)
    for a in range(k):
        p, q = Xc[a], Xc[(a + 1) % k]
        if p[2] >= z_near:
            pts.append(p)
        if (p[2] >= z_near) != (q[2] >= z_near):
            lam = (z_near - p[2]) / (q[2] - p[2])
            pts.append(p + lam * (q - p))
    if not pts:
        return None
    P = np.array(pts) @ Ks.T
    uv = P[:, :2] / P[:, 2:3]
    x0, y0 = max(0, int(np.floor(uv[:, 0].min())) - 1), max(0, int(np.floor(uv[:, 1].min())) - 1)
    x1, y1 = min(W, int(np.ceil(uv[:, 0].max())) + 2), min(H, int(np.ceil(uv[:, 1].max())) + 2)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def plane_geometry(planes: list[Plane]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World corners (n, 4, 3), unit normals a×b (n, 3) and origins (n, 3) of the planes."""
    if not planes:
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return (np.array([pl.corners() for pl in planes]), np.array([pl.normal for pl in planes]),
            np.array([pl.origin for pl in planes]))


def render_view_clipped(planes: list[Plane], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
                        supersample: int = 2, background: int = 90,
                        geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render one view of textured planes with a z-buffer (as ``render_view``, with near-plane clipping).

    Args:
        planes: the scene; K (3, 3); R (3, 3) cam_from_world; t (3,); width, height: output size.
        supersample: render at this factor, then area-average down.
        geometry: ``plane_geometry(planes)`` precomputed (optional, speed).
    Returns:
        image (height, width, 3) uint8 RGB, depth (height, width) float32 (inf = nothing).
    """
    s = int(supersample)
    Ks, W, H, Kinv, uu, vv = supersampled_grid(K, width, height, s)
    best = np.zeros((H, W), np.float32)
    image = np.full((H, W, 3), background, np.uint8)
    corners, normals, origins = plane_geometry(planes) if geometry is None else geometry
    Xc_all = corners @ R.T + t  # (n_planes, 4, 3)
    z_near = 1e-3
    zc = Xc_all[:, :, 2]
    all_front = (zc > z_near).all(axis=1)
    # vectorized bounding boxes of the planes entirely in front; the others are clipped one by one
    with np.errstate(divide="ignore", invalid="ignore"):
        P = Xc_all @ Ks.T
        uv = P[:, :, :2] / P[:, :, 2:3]
    bx0 = np.floor(np.nan_to_num(uv[:, :, 0].min(1), nan=0.0, posinf=W, neginf=-1)) - 1
    by0 = np.floor(np.nan_to_num(uv[:, :, 1].min(1), nan=0.0, posinf=H, neginf=-1)) - 1
    bx1 = np.ceil(np.nan_to_num(uv[:, :, 0].max(1), nan=0.0, posinf=W, neginf=-1)) + 2
    by1 = np.ceil(np.nan_to_num(uv[:, :, 1].max(1), nan=0.0, posinf=H, neginf=-1)) + 2
    in_view = all_front & (bx1 > 0) & (by1 > 0) & (bx0 < W) & (by0 < H)
    crossing = ~all_front & (zc > z_near).any(axis=1)
    # d_c = n_c·(R X0 + t) = n·X0 + n·Rᵀt: > 0 when the camera sees the plane's visible side
    d_all = np.einsum("nk,nk->n", normals, origins) + normals @ (R.T @ t)
    for k in np.flatnonzero((in_view | crossing) & (d_all > 1e-9)):
        pl = planes[k]
        if in_view[k]:
            x0, y0 = max(0, int(bx0[k])), max(0, int(by0[k]))
            x1, y1 = min(W, int(bx1[k])), min(H, int(by1[k]))
        else:
            bbox = _clipped_bbox(Xc_all[k], Ks, W, H, z_near)
            if bbox is None:
                continue
            x0, y0, x1, y1 = bbox
        n_c = R @ normals[k]
        d_c = float(d_all[k])
        Hm = Ks @ np.column_stack([R @ pl.a, R @ pl.b, R @ pl.origin + t])
        Hc = Hm @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
        T = np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]])
        warped = cv2.warpPerspective(pl.rgba, T @ Hc, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
        coef = ((n_c @ Kinv) / d_c).astype(np.float32)
        invz = coef[0] * uu[:, x0:x1] + (coef[1] * vv[y0:y1] + coef[2])
        zb = best[y0:y1, x0:x1]
        closer = invz > zb
        closer &= warped[..., 3] >= 128
        np.copyto(zb, invz, where=closer)
        np.copyto(image[y0:y1, x0:x1], warped[..., :3], where=closer[..., None])
    if s > 1:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
        best = best[s // 2::s, s // 2::s][:height, :width]
    depth = np.where(best > 0, 1.0 / np.maximum(best, 1e-12), np.inf).astype(np.float32)
    return image, depth


# ------------------------------------------------------------------ true overlap


def sample_surface_points(planes: list[Plane], density: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform on the planes, ``density`` per m² (Poisson count per plane).

    Returns:
        X (P, 3) and the tangent basis (P, 3, 2) of each point's plane (unit a, unit b).
    """
    pts, bases = [], []
    for pl in planes:
        h, w = pl.texture.shape[:2]
        area = np.linalg.norm(np.cross(pl.a * w, pl.b * h))
        n = rng.poisson(area * density)
        uv = rng.uniform([0, 0], [w, h], (n, 2))
        pts.append(pl.origin + uv[:, :1] * pl.a + uv[:, 1:] * pl.b)
        B = np.column_stack([pl.a / np.linalg.norm(pl.a), pl.b / np.linalg.norm(pl.b)])
        bases.append(np.broadcast_to(B, (n, 3, 2)))
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3, 2))
    return np.concatenate(pts), np.concatenate(bases)


def visibility(X: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, depth: np.ndarray,
               rel_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Points of X (P, 3) visible in one view (in the image, in front, not occluded).

    Returns:
        indices (m,) of the visible points and their depths (m,).
    """
    Xc = X @ R.T + t
    z = Xc[:, 2]
    hh, ww = depth.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * Xc[:, 0] / z + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / z + K[1, 2]
    ok = (z > 1e-3) & (u >= -0.5) & (u < ww - 0.5) & (v >= -0.5) & (v < hh - 0.5)
    idx = np.flatnonzero(ok)
    ui = np.clip(np.round(u[idx]).astype(np.int64), 0, ww - 1)
    vi = np.clip(np.round(v[idx]).astype(np.int64), 0, hh - 1)
    keep = np.abs(depth[vi, ui] - z[idx]) < rel_tol * z[idx]
    return idx[keep], z[idx[keep]]


def surface_jacobians(X: np.ndarray, basis: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Jacobians (..., P, 2, 2) of the pixel position w.r.t. in-plane coordinates at points X (P, 3).

    ``R`` (..., 3, 3) and ``t`` (..., 3) may carry leading view dimensions; ``basis`` is (P, 3, 2).
    The local affine map from view i to view j is ``J_j J_i⁻¹``.
    """
    Xc = np.einsum("...ab,pb->...pa", R, X) + t[..., None, :]
    z = Xc[..., 2]
    P = np.zeros(Xc.shape[:-1] + (2, 3))
    P[..., 0, 0] = P[..., 1, 1] = 1.0 / z
    P[..., 0, 2] = -Xc[..., 0] / z**2
    P[..., 1, 2] = -Xc[..., 1] / z**2
    RB = np.einsum("...ab,pbc->...pac", R, basis)  # (..., P, 3, 2)
    f = np.array([K[0, 0], K[1, 1]])
    return f[:, None] * np.einsum("...pab,...pbc->...pac", P, RB)


def affine_tilt_scale(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transition tilt σ₁/σ₂ and scale change √(σ₁σ₂) of 2×2 maps A (..., 2, 2), in closed form."""
    fro2 = np.sum(A * A, axis=(-2, -1))
    det = np.abs(A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0])
    disc = np.sqrt(np.maximum(fro2**2 - 4 * det**2, 0.0))
    s1 = np.sqrt((fro2 + disc) / 2)
    s2 = np.sqrt(np.maximum((fro2 - disc) / 2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return s1 / s2, np.sqrt(det)


def pair_overlap(X: np.ndarray, basis: np.ndarray, vis_idx: list[np.ndarray], vis_z: list[np.ndarray],
                 K: np.ndarray, R: np.ndarray, t: np.ndarray, max_tilt: float = 2.0,
                 max_scale: float = 2.0) -> dict[str, np.ndarray]:
    """Co-visibility of every pair of views that sees a common point.

    A point visible in views i and j is *co-visible* when the local affine map between its two
    images (``J_j J_i⁻¹``, the derivative of the plane-induced homography) has a transition tilt
    σ₁/σ₂ ≤ ``max_tilt`` and a scale change √(σ₁σ₂) within [1/max_scale, max_scale]: the range in
    which SIFT descriptors of the same surface patch still match (affine-SIFT analysis: SIFT is
    invariant to tilts up to about 2).

    Args:
        X: (P, 3) surface points; basis: (P, 3, 2) their plane's unit tangent vectors.
        vis_idx, vis_z: per view, indices (m_i,) of the visible points and their depths.
        K: (3, 3); R: (N, 3, 3); t: (N, 3) cameras.
    Returns:
        ``pairs`` (M, 2) i < j, ``n_co`` (M,) co-visible points, ``n_raw`` (M,) visible in both
        (no appearance condition), ``n_visible`` (N,), ``score`` (M,) = n_co / min(n_i, n_j).
    """
    N, P = len(vis_idx), len(X)
    nvis = np.array([len(v) for v in vis_idx], np.int64)
    rows = np.repeat(np.arange(N), nvis)
    cols = np.concatenate(vis_idx) if N else np.zeros(0, np.int64)
    B = sp.csr_matrix((np.ones(len(cols), np.int32), (rows, cols)), shape=(N, P))
    Cr = sp.triu(B @ B.T, k=1).tocsr()
    out_pairs, out_co, out_raw = [], [], []
    for i in range(N):  # vectorized over the partners j and the points of view i
        js = Cr.indices[Cr.indptr[i]:Cr.indptr[i + 1]]
        if len(js) == 0 or nvis[i] == 0:
            continue
        idx = vis_idx[i]
        both = B[js][:, idx].toarray() > 0  # (|J|, m_i)
        Ji = surface_jacobians(X[idx], basis[idx], K, R[i], t[i])  # (m_i, 2, 2)
        Jj = surface_jacobians(X[idx], basis[idx], K, R[js], t[js])  # (|J|, m_i, 2, 2)
        det_i = Ji[:, 0, 0] * Ji[:, 1, 1] - Ji[:, 0, 1] * Ji[:, 1, 0]
        det_i = np.where(np.abs(det_i) < 1e-12, 1e-12, det_i)
        Ji_inv = np.stack([np.stack([Ji[:, 1, 1], -Ji[:, 0, 1]], -1), np.stack([-Ji[:, 1, 0], Ji[:, 0, 0]], -1)], -2)
        Ji_inv /= det_i[:, None, None]
        tilt, scale = affine_tilt_scale(Jj @ Ji_inv[None])
        with np.errstate(invalid="ignore"):
            co = both & (tilt <= max_tilt) & (scale <= max_scale) & (scale >= 1.0 / max_scale)
        out_pairs.append(np.column_stack([np.full(len(js), i), js]))
        out_co.append(co.sum(1))
        out_raw.append(both.sum(1))
    pairs = np.concatenate(out_pairs).astype(np.int64) if out_pairs else np.zeros((0, 2), np.int64)
    n_co = np.concatenate(out_co).astype(np.int64) if out_co else np.zeros(0, np.int64)
    n_raw = np.concatenate(out_raw).astype(np.int64) if out_raw else np.zeros(0, np.int64)
    denom = np.maximum(np.minimum(nvis[pairs[:, 0]], nvis[pairs[:, 1]]), 1)
    return {"pairs": pairs, "n_co": n_co, "n_raw": n_raw, "n_visible": nvis, "score": n_co / denom}


def true_pairs(overlap: dict[str, np.ndarray], threshold: float = 0.1) -> np.ndarray:
    """(M', 2) pairs whose overlap score is at least ``threshold``."""
    return overlap["pairs"][overlap["score"] >= threshold]


def load_overlap(scene_dir: str | Path) -> dict[str, np.ndarray]:
    """Read ``DIR/overlap.npz`` as a dict of arrays.

    Raises:
        InputFileError: missing or damaged file.
    """
    path = Path(scene_dir) / "overlap.npz"
    if not path.is_file():
        raise InputFileError(f"{path} not found: render the scene with python -m pipeline.synthetic.large")
    try:
        with np.load(path, allow_pickle=False) as d:
            out = {k: d[k] for k in d.files}
        pairs = np.asarray(out["pairs"], np.int64).reshape(-1, 2)
        score = np.asarray(out["score"], np.float64).reshape(-1)
        if len(score) != len(pairs) or (len(pairs) and (pairs[:, 0] >= pairs[:, 1]).any()):
            raise ValueError("pairs and scores disagree")
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise InputFileError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); render the scene again") from None
    out["pairs"], out["score"] = pairs, score
    return out


def write_pairs_file(path: str | Path, names: list[str], pairs: np.ndarray) -> Path:
    """Write index pairs (P, 2) as a pairs file of ``name_a name_b`` lines (atomically)."""
    with atomic_open(path) as f:
        f.writelines(f"{names[a]} {names[b]}\n" for a, b in pairs)
    return Path(path)


def render_large(config: LargeSceneConfig, out: Path | None, seed: int = 0) -> dict:
    """Render a scene, compute its true overlap, optionally write everything to ``out``.

    Returns:
        a summary dict (timings, counts, overlap statistics); with ``out`` None it also holds
        ``images``, ``depths`` and ``overlap``.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    scene = make_scene(config, seed)
    t_build = time.perf_counter() - t0
    N = config.n_views
    names = [f"view_{i:03d}.png" for i in range(N)]
    rng_pts = np.random.default_rng([seed, 11])
    X, basis = sample_surface_points(scene.planes, scene.point_density, rng_pts)
    geometry = plane_geometry(scene.planes)
    noise_rng = np.random.default_rng([seed, 13])
    if out is not None:
        out = Path(out)
        check_writable(out)
    vis_idx, vis_z, images, depths = [], [], [], []
    t_render = t_write = 0.0
    for i in range(N):
        t1 = time.perf_counter()
        img, depth = render_view_clipped(scene.planes, scene.K, scene.R[i], scene.t[i], config.width, config.height,
                                         config.supersample, geometry=geometry)
        if config.noise_sigma > 0:
            img = np.clip(img + noise_rng.normal(0, config.noise_sigma, img.shape), 0, 255).astype(np.uint8)
        vi, vz = visibility(X, scene.K, scene.R[i], scene.t[i], depth)
        vis_idx.append(vi)
        vis_z.append(vz)
        t2 = time.perf_counter()
        t_render += t2 - t1
        if out is not None:
            with atomic_path(out / names[i], suffix=".png") as tmp:
                if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                    raise OSError(f"could not write {out / names[i]}")
        else:
            images.append(img)
            depths.append(depth)
        t_write += time.perf_counter() - t2
    t3 = time.perf_counter()
    ov = pair_overlap(X, basis, vis_idx, vis_z, scene.K, scene.R, scene.t, config.max_tilt, config.max_scale)
    t_overlap = time.perf_counter() - t3
    tp = true_pairs(ov, config.overlap_threshold)
    deg = np.bincount(tp.ravel(), minlength=N)
    n_all = N * (N - 1) // 2
    summary = {
        "layout": config.layout, "n_views": N, "seed": seed, "config": dataclasses.asdict(config),
        "n_planes": len(scene.planes), "texels": int(sum(pl.texture.shape[0] * pl.texture.shape[1] for pl in scene.planes)),
        "n_points": int(len(X)), "median_visible_points": float(np.median(ov["n_visible"])),
        "n_pairs_any_covisible": int(len(ov["pairs"])), "n_true_pairs": int(len(tp)),
        "true_pair_fraction": len(tp) / n_all, "true_degree_mean": float(deg.mean()),
        "true_degree_max": int(deg.max()), "n_views_without_true_pair": int((deg == 0).sum()),
        "time_build_s": t_build, "time_render_s": t_render, "time_write_s": t_write, "time_overlap_s": t_overlap,
        "time_total_s": time.perf_counter() - t0, "cpu_total_s": time.process_time() - c0,
    }
    if out is not None:
        write_cameras_txt(out / "cameras.txt", names, np.repeat(scene.K[None], N, 0), scene.R, scene.t)
        with atomic_open(out / "K.txt") as f:
            np.savetxt(f, scene.K, fmt="%.10g")
        write_pairs_file(out / "true_pairs.txt", names, tp)
        save_npz(out / "overlap.npz", pairs=ov["pairs"], score=ov["score"], n_co=ov["n_co"],
                            n_raw=ov["n_raw"], n_visible=ov["n_visible"], threshold=config.overlap_threshold,
                            centers=scene.centers)
        write_json(out / "scene.json", summary)
    else:
        summary.update(images=images, depths=depths, overlap=ov, scene=scene)
    return summary


def main(out: str | Path, layout: str = "street", n_views: int = 100, seed: int = 0, width: int = 640,
         height: int = 480, noise_sigma: float = 0.0, spacing: float | None = None) -> dict:
    """Render a scene into ``out`` (focal 560 px at 640 px width, scaled with the width); returns its summary."""
    cfg = LargeSceneConfig(layout=layout, n_views=n_views, width=width, height=height, focal=560.0 * width / 640,
                           noise_sigma=noise_sigma, spacing=spacing)
    return render_large(cfg, Path(out), seed)


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.synthetic.large",
                                description="Render a large street / ring / grid scene with its truly overlapping pairs.")
    p.add_argument("--layout", choices=LAYOUTS, default="street")
    p.add_argument("--views", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--noise", type=float, default=0.0, help="pixel noise (0-255 scale)")
    p.add_argument("--spacing", type=float, default=None, help="camera spacing (m); default: the layout's")

    def body(a: argparse.Namespace) -> int:
        s = main(a.out, a.layout, a.views, a.seed, a.width, a.height, a.noise, a.spacing)
        print(json.dumps({k: v for k, v in s.items() if k != "config"}, indent=1))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
