"""Synthetic datasets in other tools' file layouts, with known truth: fixtures for the readers' tests.

:func:`make_synthetic_1dsfm` writes a small 1DSfM folder (``list.txt``, ``cc.txt``,
``EGs.txt``, ``gt_bundle.out``) in the files' own conventions (:mod:`pipeline.io.onedsfm`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import atomic_open
from pipeline.io.onedsfm import BUNDLER_TO_CV

__all__ = ["make_synthetic_1dsfm"]


def make_synthetic_1dsfm(folder: str | os.PathLike, n: int = 30, p: float = 0.4, sigma_deg: float = 1.0,
                         n_extra_images: int = 3, n_unregistered: int = 2, digits: int | None = 7,
                         seed: int = 0) -> dict[str, np.ndarray]:
    """Write a small 1DSfM-style folder with known truth, in the files' own conventions.

    Cameras look at the origin from random points on a sphere of radius 5 (OpenCV: +z forward),
    so every true camera sees the scene in front of it; they are converted to Bundler's frame
    (``F R``, ``F t``) for gt_bundle.out and EGs are written as ``R_i^b R_j^bᵀ`` (plus left
    noise in our frame) with ``t`` = camera j's centre in camera i's Bundler frame, exactly
    as the SfM_Init README describes. ``list.txt`` has ``n_extra_images`` images not in cc.txt
    (one with an EG to a cc image, which the reader must drop); ``n_unregistered`` cc cameras
    are all-zero in gt_bundle.out; numbers are printed with ``digits`` significant digits
    (None: full precision) like the public files.

    Returns:
        dict with ``R_cv`` (n_total, 3, 3) true OpenCV cam_from_world, ``C`` centres,
        ``cc`` indices, ``registered`` mask, ``names``.
    """
    rng = np.random.default_rng(seed)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n_total = n + n_extra_images
    C = rng.standard_normal((n_total, 3))
    C *= 5.0 / np.linalg.norm(C, axis=1, keepdims=True)
    # look-at: z axis towards the origin, x from a random up vector
    z = -C / np.linalg.norm(C, axis=1, keepdims=True)
    up = rng.standard_normal((n_total, 3))
    x = np.cross(up, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R_cv = np.stack([x, y, z], axis=1)                     # rows: camera axes in world
    t_cv = -np.einsum("nab,nb->na", R_cv, C)
    names = [f"images/img_{k:04d}.jpg" for k in range(n_total)]
    perm = rng.permutation(n_total)
    cc = np.sort(perm[:n])
    extra = np.sort(perm[n:])
    pairs = np.argwhere(np.triu(rng.random((n, n)) < p, 1))
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)   # keep cc connected
    pairs = np.unique(np.vstack([pairs, chain]), axis=0)
    ij = cc[pairs]
    swap = rng.random(ij.shape[0]) < 0.3                    # some EGs written with i > j
    ij[swap] = ij[swap][:, ::-1]
    if extra.size:
        ij = np.vstack([ij, [[extra[0], cc[0]]]])
    F = BUNDLER_TO_CV
    Rb = F @ R_cv
    i, j = ij[:, 0], ij[:, 1]
    noise = so3.exp(np.deg2rad(sigma_deg) * rng.standard_normal((ij.shape[0], 3)))
    R_ours = noise @ R_cv[j] @ np.swapaxes(R_cv[i], 1, 2)  # R_j R_iᵀ with left noise
    R_eg = F @ np.swapaxes(R_ours, 1, 2) @ F               # = R_i^b R_j^bᵀ without noise
    t_eg = np.einsum("mab,mb->ma", Rb[i], C[j] - C[i])
    t_eg /= np.linalg.norm(t_eg, axis=1, keepdims=True)
    fmt = (lambda v: f"{v:.{digits}g}") if digits else (lambda v: f"{v:.17g}")
    focal = rng.uniform(500, 1500, n_total)
    focal[extra[-1:]] = np.nan                            # one image with unknown focal
    with atomic_open(folder / "list.txt") as fh:
        for nm, f in zip(names, focal):
            fh.write(nm + ("\n" if not np.isfinite(f) else f" 0 {fmt(f)}\n"))
    with atomic_open(folder / "cc.txt") as fh:
        fh.write("".join(f"{k}\n" for k in cc))
    with atomic_open(folder / "EGs.txt") as fh:
        for (a, b), Rk, tk in zip(ij, R_eg, t_eg):
            fh.write(f"{a} {b} " + " ".join(fmt(v) for v in (*Rk.ravel(), *tk)) + "\n")
    registered = np.ones(n_total, bool)
    registered[cc[rng.choice(n, size=min(n_unregistered, n), replace=False)]] = False
    with atomic_open(folder / "gt_bundle.out") as fh:
        fh.write("# Bundle file v0.3\n")
        fh.write(f"{n_total} 0\n")
        for k in range(n_total):
            if registered[k]:
                rows = [(focal[k] if np.isfinite(focal[k]) else 1000.0, 0.0, 0.0), *Rb[k], F @ t_cv[k]]
            else:
                rows = [(0.0, 0.0, 0.0)] + [(0.0, 0.0, 0.0)] * 4
            for r in rows:
                fh.write(" ".join(fmt(v) for v in r) + "\n")
    return {"R_cv": R_cv, "t_cv": t_cv, "C": C, "cc": cc, "registered": registered, "names": names,
            "ij": ij, "R_ours": R_ours}
