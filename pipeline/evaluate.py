"""``python -m pipeline.evaluate``: evaluate rotations or a view graph against a reference (:mod:`pipeline.evaluation`)."""

import sys

from pipeline.evaluation.compare import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
