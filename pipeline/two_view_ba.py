"""``python -m pipeline.two_view_ba``: the two-view BA stage (:mod:`pipeline.geometry.ba_stage`)."""

import sys

from pipeline.geometry.ba_stage import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
