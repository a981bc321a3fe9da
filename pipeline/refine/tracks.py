"""Multi-view tracks from pairwise inlier matches, and the pairs the averaged rotations agree with (pure numpy).

A track is a connected component of the match graph whose nodes are
``(image, keypoint)`` pairs and whose edges are the verified inlier matches. The
rules are GLOMAP's (``track_establishment``): a component holding two keypoints
of one image farther apart than ``consistency_px`` is dropped, one observation per
image is kept, and a track must be seen in ``min_views`` images. Everything here
is vectorized: one scipy connected-components call and sorted-array reductions,
no Python loop over matches, keypoints or tracks.

Convention: image indices are positions in the caller's image list; keypoint
indices are rows of that image's keypoint array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from pipeline.core import so3

__all__ = ["Tracks", "build_tracks", "select_tracks", "subset_tracks", "restrict_tracks", "filter_edges",
           "select_matches", "long_tracks"]


@dataclass
class Tracks:
    """Tracks in CSR layout.

    Attributes:
        offsets: (P+1,) start of each track's observations.
        image: (Q,) image index of each observation (sorted within a track).
        keypoint: (Q,) keypoint index in that image.
        n_components: connected components of the match graph.
        n_inconsistent: components dropped by the consistency check.
        n_short: components dropped for being seen in fewer than ``min_views`` images.
    """

    offsets: np.ndarray
    image: np.ndarray
    keypoint: np.ndarray
    n_components: int = 0
    n_inconsistent: int = 0
    n_short: int = 0

    @property
    def n_tracks(self) -> int:
        return len(self.offsets) - 1

    @property
    def lengths(self) -> np.ndarray:
        """(P,) observations per track."""
        return np.diff(self.offsets)

    def observations_per_image(self, n_images: int) -> np.ndarray:
        """(n_images,) number of track observations in each image."""
        return np.bincount(self.image, minlength=n_images)


def _empty() -> Tracks:
    return Tracks(np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))


def build_tracks(keypoints: list[np.ndarray], edges: np.ndarray, match_offsets: np.ndarray, matches: np.ndarray,
                 min_views: int = 3, consistency_px: float = 10.0) -> Tracks:
    """Union of pairwise matches into multi-view tracks (GLOMAP's rules, vectorized).

    Args:
        keypoints: N arrays (n_i, 2) pixel coordinates (for the consistency check).
        edges: (M, 2) image indices of the pairs.
        match_offsets: (M+1,) start of each pair's matches in ``matches``.
        matches: (T, 2) keypoint indices (in image ``edges[e, 0]``, in image ``edges[e, 1]``).
        min_views: minimum number of distinct images per track.
        consistency_px: a component with two keypoints of one image farther apart than
            this is dropped.
    Returns:
        :class:`Tracks`.
    """
    n_kp = np.array([len(k) for k in keypoints], np.int64)
    base = np.concatenate([[0], np.cumsum(n_kp)])
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    counts = np.diff(np.asarray(match_offsets, np.int64))
    matches = np.asarray(matches, np.int64).reshape(-1, 2)
    if len(matches) == 0:
        return _empty()
    e_of = np.repeat(np.arange(len(edges)), counts)
    if np.any(matches >= n_kp[edges[e_of]]) or np.any(matches < 0):
        raise ValueError("a match refers to a keypoint index outside its image's keypoints")
    a = base[edges[e_of, 0]] + matches[:, 0]
    b = base[edges[e_of, 1]] + matches[:, 1]
    n_nodes = int(base[-1])
    G = sp.coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n_nodes, n_nodes)).tocsr()
    _, label = connected_components(G, directed=False)
    nodes = np.unique(np.concatenate([a, b]))
    lab = label[nodes]
    img = np.searchsorted(base, nodes, side="right") - 1
    kp = nodes - base[img]
    order = np.lexsort((kp, img, lab))
    nodes, lab, img, kp = nodes[order], lab[order], img[order], kp[order]
    xy = np.concatenate([np.asarray(k, np.float64).reshape(-1, 2) for k in keypoints])[nodes]
    # groups of (track, image): the consistency check, and one observation per image
    gs = np.flatnonzero(np.r_[True, (lab[1:] != lab[:-1]) | (img[1:] != img[:-1])])
    span = np.maximum.reduceat(xy, gs, axis=0) - np.minimum.reduceat(xy, gs, axis=0)
    bad_group = np.hypot(span[:, 0], span[:, 1]) > consistency_px
    g_lab = lab[gs]
    cs = np.flatnonzero(np.r_[True, g_lab[1:] != g_lab[:-1]])
    n_views = np.diff(np.r_[cs, len(gs)])
    comp_bad = np.logical_or.reduceat(bad_group, cs)
    comp_short = n_views < min_views
    keep = ~comp_bad & ~comp_short
    first = gs[np.repeat(keep, n_views)]  # the first observation of each kept (track, image) group
    return Tracks(offsets=np.concatenate([[0], np.cumsum(n_views[keep])]).astype(np.int64),
                  image=img[first].astype(np.int64), keypoint=kp[first].astype(np.int64), n_components=int(len(cs)),
                  n_inconsistent=int(comp_bad.sum()), n_short=int((comp_short & ~comp_bad).sum()))


def subset_tracks(tracks: Tracks, keep: np.ndarray) -> Tracks:
    """The tracks where ``keep`` (P,) is True."""
    lengths = tracks.lengths
    obs = np.repeat(keep, lengths)
    return Tracks(np.concatenate([[0], np.cumsum(lengths[keep])]).astype(np.int64), tracks.image[obs],
                  tracks.keypoint[obs], tracks.n_components, tracks.n_inconsistent, tracks.n_short)


def long_tracks(tracks: Tracks, n_images: int, min_views: int, min_observations: int) -> tuple[Tracks, np.ndarray]:
    """The tracks seen in at least ``min_views`` images, and every shorter one of a *starved* image: one with fewer
    than ``min_observations`` observations in the long tracks.

    A camera that turns on the spot (a pan) sees each point from one centre, so its tracks stay short; without them
    it is not refined, and the views on either side of the pan lose the one thing that ties them together (rendered
    street of 300 views whose halves meet at pans: refined 0.075° with 3-view tracks only, 0.047° with these).

    Returns:
        the tracks, and (n_images,) bool: the starved images.
    """
    lengths = tracks.lengths
    long = lengths >= min_views
    starved = np.bincount(tracks.image[np.repeat(long, lengths)], minlength=n_images) < min_observations
    touches = np.logical_or.reduceat(starved[tracks.image], tracks.offsets[:-1]) if tracks.n_tracks else long
    touches &= lengths > 0
    out = subset_tracks(tracks, long | touches)
    out.n_short = tracks.n_short + int((~(long | touches)).sum())
    return out, starved


def restrict_tracks(tracks: Tracks, active: np.ndarray, min_views: int) -> Tracks:
    """The tracks without the observations of inactive images; tracks left with < ``min_views`` are dropped.

    Args:
        active: (N,) bool per image.
    """
    obs_ok = np.asarray(active, bool)[tracks.image]
    if tracks.n_tracks == 0:
        return tracks
    lengths = np.add.reduceat(obs_ok.astype(np.int64), tracks.offsets[:-1])
    lengths[tracks.lengths == 0] = 0
    keep_track = lengths >= min_views
    keep_obs = obs_ok & np.repeat(keep_track, tracks.lengths)
    return Tracks(np.concatenate([[0], np.cumsum(lengths[keep_track])]).astype(np.int64), tracks.image[keep_obs],
                  tracks.keypoint[keep_obs], tracks.n_components, tracks.n_inconsistent, tracks.n_short)


def select_tracks(tracks: Tracks, n_images: int, per_image: int) -> np.ndarray:
    """(P,) bool: the tracks among the ``per_image`` longest tracks of at least one of their images.

    An order-free, vectorized form of GLOMAP's ``required_tracks_per_view``: each
    observation is ranked within its image by its track's length (longest first, ties
    by track index); a track is kept if any of its observations ranks below ``per_image``.
    """
    lengths = tracks.lengths
    tid = np.repeat(np.arange(tracks.n_tracks), lengths)
    order = np.lexsort((tid, -lengths[tid], tracks.image))
    img_sorted = tracks.image[order]
    start = np.searchsorted(img_sorted, np.arange(n_images))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - start[img_sorted]
    keep = np.zeros(tracks.n_tracks, bool)
    keep[tid[rank < per_image]] = True
    return keep


def filter_edges(edges: np.ndarray, cam2_from_cam1: np.ndarray, cam_from_world: np.ndarray,
                 max_deg: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs whose measured relative rotation agrees with the rotations ``cam_from_world``.

    Args:
        edges: (M, 2) image indices, i < j.
        cam2_from_cam1: (M, 3, 3) measured ``R_ij``.
        cam_from_world: (N, 3, 3) rotations; NaN rows for images without one.
        max_deg: threshold in degrees (None keeps every pair whose two rotations are known).
    Returns:
        keep (M,) bool and the residual angles (M,) in degrees (NaN where a rotation is missing).
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    R = np.asarray(cam_from_world, float)
    i, j = edges[:, 0], edges[:, 1]
    known = np.all(np.isfinite(R), axis=(1, 2))
    ok = known[i] & known[j]
    res = np.full(len(edges), np.nan)
    if ok.any():
        res[ok] = np.degrees(so3.angle_between(np.asarray(cam2_from_cam1, float)[ok], so3.relative(R, edges[ok])))
    keep = ok if max_deg is None else ok & (res <= max_deg)
    return keep, res


def select_matches(match_offsets: np.ndarray, matches: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The CSR matches of the pairs where ``keep`` (M,) is True: ``(offsets (M'+1,), matches (T', 2))``."""
    match_offsets = np.asarray(match_offsets, np.int64)
    counts = np.diff(match_offsets)
    rows = np.repeat(np.asarray(keep, bool), counts)
    kept = np.asarray(matches).reshape(-1, 2)[match_offsets[0]:match_offsets[-1]][rows]
    return np.concatenate([[0], np.cumsum(counts[keep])]).astype(np.int64), kept
