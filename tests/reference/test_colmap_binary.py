"""The structural check of COLMAP binary models against models pycolmap writes."""

from __future__ import annotations

import shutil

import numpy as np
import pycolmap
import pytest

from pipeline.core.errors import InputFileError
from pipeline.reference.colmap_binary import check_binary_model
from pipeline.reference.truth import read_reference


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """A pycolmap-written binary model: 2 cameras (PINHOLE, OPENCV), 3 images, 2 points."""
    d = tmp_path_factory.mktemp("model")
    (d / "cameras.txt").write_text("1 PINHOLE 240 180 200 210 120 90\n2 OPENCV 240 180 200 200 120 90 0.1 0 0 0\n")
    (d / "images.txt").write_text("1 1 0 0 0 0 0 1 1 a.png\n10 20 1 30 40 -1\n"
                                  "2 0.7071067811865476 0 0.7071067811865476 0 1 0 1 2 b.png\n11 21 1 5 5 2\n"
                                  "3 1 0 0 0 2 0 1 1 c.png\n\n")
    (d / "points3D.txt").write_text("1 0 0 1 1 2 3 0.5 1 0 2 0\n2 1 0 1 1 2 3 0.5 2 1\n")
    (d / "bin").mkdir()
    pycolmap.Reconstruction(str(d)).write(str(d / "bin"))
    return d / "bin"


def test_a_written_model_passes_and_reads(model) -> None:
    check_binary_model(model)
    ref = read_reference(model)
    assert ref.names == ["a.png", "b.png", "c.png"]
    assert np.allclose(ref.R[1], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "frames.bin", "rigs.bin", "points3D.bin"])
@pytest.mark.parametrize("how", ["cut", "extra", "count"])
def test_damaged_files_are_refused_naming_the_file(model, tmp_path, name, how) -> None:
    bad = tmp_path / "m"
    shutil.copytree(model, bad)
    data = (bad / name).read_bytes()
    data = {"cut": data[: len(data) - 5], "extra": data + b"\0" * 11,
            "count": (10**9).to_bytes(8, "little") + data[8:]}[how]
    (bad / name).write_bytes(data)
    # rigs.bin's records have a least size, so a cut one is refused by its count bound like the others; the bytes
    # beyond the last record of rigs.bin and points3D.bin, and a cut points3D.bin (records of any size), are not
    # checked here (a limitation): pycolmap reads them in the sandbox, and what is asked is a one-line error or the
    # right cameras, never a crash or wrong ones
    if how != "count" and not (name == "rigs.bin" and how == "cut") and name in ("rigs.bin", "points3D.bin"):
        try:
            assert read_reference(bad).names == ["a.png", "b.png", "c.png"]
        except InputFileError as exc:
            assert str(bad) in str(exc) and "\n" not in str(exc)
        return
    with pytest.raises(InputFileError, match=name):
        check_binary_model(bad)
    with pytest.raises(InputFileError, match=name):
        read_reference(bad)
