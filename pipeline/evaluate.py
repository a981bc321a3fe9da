"""``python -m pipeline.evaluate``: :func:`pipeline.evaluation.compare.main_cli`; old imports of the metrics still work."""

import sys

from pipeline.evaluation.compare import main_cli, match_reference  # noqa: F401
from pipeline.evaluation.metrics import *  # noqa: F401,F403

if __name__ == "__main__":
    sys.exit(main_cli())
