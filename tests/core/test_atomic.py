"""pipeline.core.atomic's JSON: strict JSON whatever the object holds (null where a figure is not finite)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import atomic
from pipeline.core.atomic import TMP_TAG, finite_json, write_json

NAN, INF = float("nan"), float("inf")


def test_write_json_writes_null_where_a_figure_is_not_finite(tmp_path, strict_json) -> None:
    """NaN, ±inf (Python's and numpy's, alone, in lists, tuples and arrays, however deep) are null; every other
    value is written as before: finite numbers exactly, numpy integers and booleans as numbers and booleans."""
    obj = {"nan": NAN, "inf": INF, "-inf": -INF, "np_nan": np.float64("nan"), "np32_inf": np.float32("-inf"),
           "nested": [1.5, [NAN, {"deep": [INF, 2.0]}], (np.nan, 3)], "array": np.array([[1.0, np.nan], [np.inf, 4.0]]),
           "finite": {"f": 0.1, "np": np.float32(0.5), "i": np.int64(7), "b": np.bool_(True), "s": "NaN", "none": None},
           "path": Path("a/b")}
    text = write_json(tmp_path / "x.json", obj).read_text(encoding="utf-8")
    assert "NaN" not in text.replace('"NaN"', "") and "Infinity" not in text
    assert strict_json(text) == {
        "nan": None, "inf": None, "-inf": None, "np_nan": None, "np32_inf": None,
        "nested": [1.5, [None, {"deep": [None, 2.0]}], [None, 3]], "array": [[1.0, None], [None, 4.0]],
        "finite": {"f": 0.1, "np": 0.5, "i": 7, "b": True, "s": "NaN", "none": None}, "path": "a/b"}
    assert finite_json(obj)["finite"] == {"f": 0.1, "np": 0.5, "i": 7, "b": True, "s": "NaN", "none": None}
    assert type(finite_json(obj)["finite"]["i"]) is int and type(finite_json(obj)["finite"]["b"]) is bool


def test_a_non_finite_float_that_escapes_the_conversion_raises_and_writes_nothing(tmp_path, monkeypatch) -> None:
    """The encoder itself refuses NaN (``allow_nan=False``): were the conversion ever to miss one, write_json raises
    instead of writing a file strict readers refuse, and the file it would have replaced stays as it was."""
    path = write_json(tmp_path / "x.json", {"a": 1})
    monkeypatch.setattr(atomic, "finite_json", lambda obj: obj)  # a conversion that misses everything
    with pytest.raises(ValueError, match="not JSON compliant"):
        write_json(path, {"a": NAN})
    assert json.loads(path.read_text()) == {"a": 1} and not [p for p in tmp_path.iterdir() if TMP_TAG in p.name]


def test_what_is_not_json_still_raises(tmp_path) -> None:
    with pytest.raises(TypeError, match="set is not JSON serializable"):
        write_json(tmp_path / "x.json", {"a": {1, 2}})
    assert not list(tmp_path.iterdir())


def test_an_output_that_cannot_be_written_is_named_not_its_temporary(tmp_path) -> None:
    """`pipeline.convert g.npz /proc/g.g2o`, `pipeline.evaluate --json /proc/e.json`: the one error line was
    "[Errno 2] No such file or directory: '/proc/.e.json.rotavg-tmp-wl4czp85.json'", a file the user never named."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")  # no folder can be made under a file, even by root
    targets = [blocker / "out.json"] + ([Path("/proc/rotavg-test-out.json")] if Path("/proc/self").is_dir() else [])
    for target in targets:
        with pytest.raises(OSError) as exc:
            write_json(target, {"a": 1})
        msg = str(exc.value)
        assert f"cannot write {target}" in msg and TMP_TAG not in msg, msg
        with pytest.raises(OSError) as exc:
            with atomic.atomic_dir(target.with_suffix("")):
                pass
        assert f"cannot write {target.with_suffix('')}" in str(exc.value) and TMP_TAG not in str(exc.value)
