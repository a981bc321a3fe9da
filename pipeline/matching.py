"""``python -m pipeline.matching``: the matching stage (:mod:`pipeline.frontend.matching_stage`)."""

import sys

from pipeline.frontend.matching import MatchingConfig, match_descriptors, root_sift  # noqa: F401
from pipeline.frontend.matching_stage import MatchSet, MatchingStage, load_matches, main, main_cli  # noqa: F401
from pipeline.frontend.pairs import exhaustive_pairs, read_pairs  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
