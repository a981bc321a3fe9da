#!/usr/bin/env python
"""The whole pipeline on an image folder; with no argument, on a rendered scene.

A thin entry point: the implementation is ``pipeline/run.py`` (``python -m pipeline.run``
is the same command). ``python run.py --help`` lists the options.
"""

import sys

from pipeline.run import main_cli

if __name__ == "__main__":
    sys.exit(main_cli())
