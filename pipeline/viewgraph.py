"""``python -m pipeline.viewgraph``: the checked view graph (:mod:`pipeline.graph.stage`)."""

import sys

from pipeline.graph.stage import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
