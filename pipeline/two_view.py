"""``python -m pipeline.two_view``: the two-view stage (:mod:`pipeline.geometry.two_view_stage`)."""

import sys

from pipeline.geometry.two_view_stage import load_two_view, main_cli  # noqa: F401 - load_two_view: old import path

if __name__ == "__main__":
    sys.exit(main_cli())
