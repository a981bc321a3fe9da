"""``python -m pipeline.convert``: file-format conversion (:mod:`pipeline.io.convert`)."""

import sys

from pipeline.io.convert import main, main_cli  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
