"""``python -m pipeline.loop_closure``: the front end's rounds around the loop-closure stage
(:mod:`pipeline.frontend.loop_stage`)."""

import sys

from pipeline.frontend.loop_stage import LoopClosureStage, main, main_cli, run_front_end  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
