"""The evidence the cameras stage estimates intrinsics from: normal-threshold detections only.

The features stage lowers the SIFT contrast threshold of a low-texture image and blurs it
first (:mod:`pipeline.frontend.features`). That helps the two-view geometry find pairs, but
the extra keypoints are weak: they are localized worse, and they crowd the ratio test of the
strong ones. On templeSparseRing (no K) the one pair that closes the ring's loop for the
rotation-consistency focal (1-13, 33 F inliers at the normal threshold) drops to 18 inliers
with the lowered keypoints, below ``cameras.min_inliers``: with no loop left, the focal
cost has no minimum of its own (f −29%), and a spurious radial κ moved it to −4.7%
(notes/issue-13.md).

So the focal and the distortion are estimated from the detections an image gives at the
normal ``contrast_threshold`` (no blur), the same evidence as for a well-textured image:
an image the rule did not lower keeps its features and matches as they are; an image it
lowered is detected once more at the normal threshold (:func:`normal_detection`), and every
pair that holds one is matched again with the matching stage's options
(:func:`reliable_matches`). Only the estimation uses these: the geometry keeps the features
stage's keypoints.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.frontend.features import FeatureConfig, extract_sift_adaptive
from pipeline.frontend.images import read_gray
from pipeline.frontend.matching import MatchingConfig, match_descriptors

__all__ = ["normal_detection", "reliable_matches", "features_evidence", "stage_evidence", "Evidence"]

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class Evidence:
    """Keypoints and matches of the estimation.

    Attributes:
        keypoints: N arrays (n_i, 2) float64, full-resolution pixels.
        pairs: (P, 2) image indices (those of the matching stage).
        matches: P arrays (m_p, 2) keypoint indices into ``keypoints``.
        redetected: names of the images detected again at the normal threshold.
    """

    keypoints: list[np.ndarray]
    pairs: np.ndarray
    matches: list[np.ndarray]
    redetected: list[str]


def normal_detection(gray: np.ndarray, config: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """SIFT of ``gray`` at ``config.contrast_threshold`` with the low-texture rule off (no blur, no lowering).

    Returns:
        ``(xy (n, 2) full-resolution px, descriptors (n, 128) uint8)``.
    """
    kp, _ = extract_sift_adaptive(gray, dataclasses.replace(config, min_keypoints=0))
    return kp.xy.astype(np.float64), kp.descriptors


def reliable_matches(names: Sequence[str], images: Path, lowered: Sequence[str], keypoints: Sequence[np.ndarray],
                     descriptors: Sequence[np.ndarray], pairs: np.ndarray, matches: Sequence[np.ndarray],
                     feature_config: FeatureConfig, matching_config: MatchingConfig) -> Evidence:
    """The normal-threshold evidence of a view graph (see the module docstring).

    Args:
        names: N image names.  images: their folder.  lowered: names the features stage lowered.
        keypoints, descriptors: the features stage's, per image (descriptors are needed only for
            images that share a pair with a lowered one; others may be empty).
        pairs: (P, 2) matched pairs.  matches: their P match arrays.
        feature_config, matching_config: the options of the two stages, used again as they were.
    Returns:
        :class:`Evidence`; the features stage's own when no image was lowered.
    """
    kp = [np.asarray(x, np.float64) for x in keypoints]
    low = [k for k, n in enumerate(names) if n in set(lowered)]
    if not low:
        return Evidence(kp, np.asarray(pairs), list(matches), [])
    desc = list(descriptors)
    for k in low:  # one SIFT pass per lowered image
        gray, why = read_gray(Path(images) / names[k])
        if gray is None:
            raise FileNotFoundError(f"{Path(images) / names[k]} {why}: the cameras stage detects it again")
        kp[k], desc[k] = normal_detection(gray, feature_config)
    is_low = np.zeros(len(names), bool)
    is_low[low] = True
    pairs = np.asarray(pairs)
    out = list(matches)
    for p in np.flatnonzero(is_low[pairs[:, 0]] | is_low[pairs[:, 1]]):  # pairs with a lowered image only
        a, b = pairs[p]
        out[p] = match_descriptors(desc[a], desc[b], matching_config)
    logger.info("cameras: %d low-texture image(s) detected again at the normal contrast threshold for the "
                "estimation; %d pair(s) matched again", len(low), int((is_low[pairs[:, 0]] | is_low[pairs[:, 1]]).sum()))
    return Evidence(kp, pairs, out, [names[k] for k in low])


def features_evidence(fs: Any, ms: Any) -> Evidence:
    """The features stage's own keypoints and matches ``fs``, ``ms``, as they are."""
    return Evidence([np.asarray(x, np.float64) for x in fs.keypoints], ms.pairs, ms.matches, [])


def stage_evidence(work: Path, fs: Any, ms: Any) -> Evidence:
    """:func:`reliable_matches` for a WORK folder's features ``fs`` and matches ``ms``."""
    from pipeline.features import load_features  # noqa: PLC0415
    from pipeline.frontend.matching_stage import load_manifest  # noqa: PLC0415

    if not fs.lowered or fs.images is None or fs.config is None:
        return features_evidence(fs, ms)
    descriptors = load_features(work, descriptors=True).descriptors
    mcfg = MatchingConfig.from_dict(load_manifest(work)["config"])
    return reliable_matches(fs.names, fs.images, list(fs.lowered), fs.keypoints, descriptors, ms.pairs, ms.matches,
                            fs.config, mcfg)
