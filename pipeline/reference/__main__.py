"""``python -m pipeline.reference``: the pycolmap incremental reference (:mod:`pipeline.reference.incremental`)."""

import sys

from pipeline.reference.incremental import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
