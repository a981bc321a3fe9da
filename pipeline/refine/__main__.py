"""``python -m pipeline.refine``: see :mod:`pipeline.refine.stage`."""

import sys

from pipeline.refine.stage import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
