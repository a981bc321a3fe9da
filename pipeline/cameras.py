"""``python -m pipeline.cameras``: the cameras stage (:mod:`pipeline.frontend.camera_stage`)."""

import sys

from pipeline.frontend.camera_stage import CameraSet, CamerasStage, load_cameras, main, main_cli  # noqa: F401

if __name__ == "__main__":
    sys.exit(main_cli())
