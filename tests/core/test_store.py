"""The item store's chunk files: every array comes back as written, old chunks still read, damage is caught."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.core.errors import CacheError
from pipeline.core.store import ItemStore


def _items() -> dict[str, dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    return {
        "a" * 20: {"R": rng.normal(size=(3, 3)), "ok": np.array(True), "reason": np.array("too few matches"),
                   "n": np.array(17), "kp": rng.integers(0, 9, (5, 2)).astype(np.int32),
                   "desc": rng.random((4, 128)).astype(np.float32), "empty": np.zeros((0, 2), np.int64),
                   "strided": np.arange(12.0).reshape(3, 4)[:, ::2], "big_endian": np.arange(3, dtype=">f8")},
        "b" * 20: {"ok": np.array(False), "reason": np.array(""), "x": np.zeros(0, np.float32)},
    }


def test_a_chunk_gives_back_every_array_exactly(tmp_path):
    items = _items()
    path = ItemStore(tmp_path).write_chunk(items)
    back = ItemStore.read_chunk(path)
    assert set(back) == set(items)
    for key, fields in items.items():
        assert set(back[key]) == set(fields)
        for name, v in fields.items():
            got = back[key][name]
            assert got.shape == v.shape and got.dtype == v.dtype, (name, got.shape, got.dtype)
            assert np.array_equal(got, v), name
    with pytest.raises(CacheError, match="lacks its array"):
        back["b" * 20]["R"]


def test_a_chunk_of_the_earlier_one_array_per_field_layout_still_reads(tmp_path):
    items = _items()
    arrays = {"keys": np.array(list(items), dtype=str)}
    for q, fields in enumerate(items.values()):
        arrays.update({f"{q}__{name}": v for name, v in fields.items()})
    np.savez(tmp_path / "chunk-0123456789abcdef.npz", **arrays)
    back = ItemStore.read_chunk(tmp_path / "chunk-0123456789abcdef.npz")
    assert all(np.array_equal(back[k][n], v) for k, f in items.items() for n, v in f.items())


@pytest.mark.parametrize("damage", ["past the end", "object dtype", "wrong count", "not json"])
def test_a_damaged_layout_is_a_cache_error_and_the_scan_removes_the_chunk(tmp_path, damage):
    path = ItemStore(tmp_path).write_chunk(_items())
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    layout = json.loads(str(arrays["layout"]))
    if damage == "past the end":
        layout[0]["R"][2] = len(arrays["data"]) - 8
    elif damage == "object dtype":
        layout[0]["R"][0] = "|O"
    elif damage == "wrong count":
        layout = layout[:1]
    arrays["layout"] = np.array("{" if damage == "not json" else json.dumps(layout))
    np.savez(path, **arrays)
    with pytest.raises(CacheError, match="is damaged"):
        ItemStore.read_chunk(path)
    store = ItemStore(tmp_path)
    assert store.scan() == {} and not path.exists()


def test_python_objects_are_refused_when_written(tmp_path):
    with pytest.raises(TypeError, match="Python objects"):
        ItemStore(tmp_path).write_chunk({"k": {"x": np.array([{"a": 1}], dtype=object)}})


def test_a_chunk_is_adopted_by_the_name_its_keys_give_and_a_different_name_is_refused(tmp_path):
    # the Dask executor does not fetch a task's result: the client derives the chunk's name from its keys
    items = _items()
    path = ItemStore(tmp_path).write_chunk(items)
    keys = list(items)
    assert ItemStore.chunk_name(keys) == ItemStore.chunk_name(keys[::-1]) == path.name
    store = ItemStore(tmp_path)
    store.adopt_chunk(keys[::-1])  # no name: the one the keys give
    assert store.done(keys) == set(keys) and store.get(keys[1])["ok"] == np.array(False)
    store.adopt_chunk(keys, path.name)
    with pytest.raises(CacheError, match="belong in"):
        store.adopt_chunk(keys[:1], path.name)


def test_drop_damaged_removes_only_the_chunks_of_items_that_fail_and_counts_them(tmp_path, caplog):
    store = ItemStore(tmp_path)
    good = store.write_chunk({"k1" * 10: {"v": np.array(1.0)}, "k2" * 10: {"v": np.array(2.0)}})
    bad = store.write_chunk({"k3" * 10: {"v": np.array(np.nan)}, "k4" * 10: {"v": np.array(4.0)}})
    odd = store.write_chunk({"k5" * 10: {"w": np.array(5.0)}})  # a field the check does not find

    def check(i, item):
        if not np.isfinite(item["v"]):
            raise CacheError(f"item {i} is not finite")

    keys = ["k1" * 10, "k3" * 10, "k5" * 10, "k9" * 10]  # k4 is not asked for; k9 is not in the store
    fresh = ItemStore(tmp_path)
    with caplog.at_level("WARNING"):
        assert fresh.drop_damaged(keys, check, "values") == 2
    assert good.exists() and not bad.exists() and not odd.exists()
    assert fresh.done(keys + ["k4" * 10]) == {"k1" * 10}  # k4 shared the damaged chunk: it is recomputed too
    (msg,) = [r.getMessage() for r in caplog.records]
    assert msg.startswith("2 values damaged, e.g. item 1 is not finite") and "2 chunk file(s) removed" in msg
    assert ItemStore(tmp_path).drop_damaged(keys, check, "values") == 0  # nothing left to find
