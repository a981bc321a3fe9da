"""``python -m pipeline.average``: the averaging command (:mod:`pipeline.averaging.cli`)."""

import sys

from pipeline.averaging.cli import main, main_cli  # noqa: F401
from pipeline.averaging.solve import average  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
