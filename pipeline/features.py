"""``python -m pipeline.features``: the SIFT stage (:mod:`pipeline.frontend.feature_stage`)."""

import sys

from pipeline.frontend.feature_stage import FeatureSet, FeaturesStage, load_features, main, main_cli  # noqa: F401
from pipeline.frontend.features import FeatureConfig, Keypoints, extract_sift  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
