"""Large rendered scenes: layouts, files, and the truly overlapping pairs."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.errors import ConfigError, InputFileError
from pipeline.frontend.pairs import read_pairs
from pipeline.reference.truth import read_reference
from pipeline.synthetic import large
from pipeline.synthetic.large_layouts import LargeSceneConfig, make_scene

SMALL = dict(width=160, height=120, focal=140.0, supersample=1, points_per_view=800)


@pytest.fixture(scope="module")
def ring(tmp_path_factory):
    out = tmp_path_factory.mktemp("ring")
    return out, large.render_large(LargeSceneConfig(layout="ring", n_views=16, **SMALL), out, seed=1)


def test_files_and_true_pairs(ring):
    out, s = ring
    names = sorted(p.name for p in out.glob("view_*.png"))
    assert len(names) == 16 and s["n_views"] == 16
    ov = large.load_overlap(out)
    truth = large.true_pairs(ov, 0.1)
    assert len(truth) == s["n_true_pairs"] > 0
    assert len(truth) < 16 * 15 // 2  # the building hides the far side: not every pair overlaps
    np.testing.assert_array_equal(read_pairs(out / "true_pairs.txt", names), truth)
    ref = read_reference(out / "cameras.txt")
    assert len(ref.names) == 16
    np.testing.assert_allclose(np.loadtxt(out / "K.txt")[0, 0], 140.0)
    # neighbours on the circle overlap, opposite cameras do not
    keys = set(map(tuple, truth.tolist()))
    assert (0, 1) in keys and (0, 8) not in keys


def test_layouts_are_deterministic_and_sized():
    coarse = {**SMALL, "texel_per_px": 0.2}  # textures are most of the time; their size does not matter here
    built = {}
    for layout in large.LAYOUTS:
        s = built[layout] = make_scene(LargeSceneConfig(layout=layout, n_views=12, **coarse), seed=2)
        assert s.R.shape == (12, 3, 3) and s.t.shape == (12, 3) and len(s.planes) > 20
        np.testing.assert_allclose(np.einsum("nij,nkj->nik", s.R, s.R), np.broadcast_to(np.eye(3), (12, 3, 3)),
                                   atol=1e-12)
    a = built["ring"]
    b = make_scene(LargeSceneConfig(layout="ring", n_views=12, **coarse), seed=2)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.planes[-1].texture, b.planes[-1].texture)


def test_bad_config_and_damaged_overlap(tmp_path):
    with pytest.raises(ConfigError, match="layout"):
        LargeSceneConfig(layout="spiral")
    with pytest.raises(ConfigError, match="n_views"):
        LargeSceneConfig(n_views=1)
    with pytest.raises(InputFileError, match="not found"):
        large.load_overlap(tmp_path)
    (tmp_path / "overlap.npz").write_bytes(b"not a zip")
    with pytest.raises(InputFileError, match="damaged"):
        large.load_overlap(tmp_path)
