"""The pycolmap database's timings back the peers' speed figures: a damaged timings file rebuilds the database."""

from __future__ import annotations

import json
import logging

from pipeline.reference import database


def test_damaged_timings_rebuild_the_database_instead_of_being_guessed(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(database, "check_database", lambda path, names: None)  # the database itself is intact
    builds = []

    def build(tmp):
        builds.append(tmp)
        tmp.write_bytes(b"db")
        return {"extract_s": 4.5, "match_s": 1.25}

    monkeypatch.setattr(database, "_checkpoint", lambda path: None)
    db = tmp_path / "database-x.db"
    assert database.ensure_database(db, ["a", "b"], build) == {"extract_s": 4.5, "match_s": 1.25}
    assert database.ensure_database(db, ["a", "b"], build) == {"extract_s": 4.5, "match_s": 1.25} and len(builds) == 1
    db.with_suffix(".times.json").write_text('{"extract_s": "fast"')  # garbled
    with caplog.at_level(logging.WARNING, logger="pipeline.reference.database"):
        assert database.ensure_database(db, ["a", "b"], build) == {"extract_s": 4.5, "match_s": 1.25}
    assert len(builds) == 2 and "timings of the pycolmap database" in caplog.text and "building it again" in caplog.text
    assert json.loads(db.with_suffix(".times.json").read_text()) == {"extract_s": 4.5, "match_s": 1.25}


def test_the_database_is_built_with_seeded_verification_and_builds_again_the_same(tmp_path, monkeypatch):
    """pycolmap's two-view verification draws its RANSAC samples from the clock by default: two builds of castle's
    internet imitation verified different inlier sets on 17 of 34 pairs. Seeded (``verification_seed``), every
    pair's inliers are the same each time the database is built (compared by image name: the extraction's threads
    may number the images in another order)."""
    import numpy as np
    import pycolmap

    from pipeline.reference.database import DatabaseConfig, build_database
    from pipeline.synthetic.render import SceneConfig, render_scene

    render_scene(5, 3, tmp_path / "scene", config=SceneConfig(width=320, height=240, focal=280.0))
    names = sorted(p.name for p in (tmp_path / "scene").glob("*.png"))
    seen = []
    real = pycolmap.match_exhaustive
    monkeypatch.setattr(pycolmap, "match_exhaustive", lambda *a, **k: (seen.append(k["verification_options"]),
                                                                       real(*a, **k))[1])
    got = []
    for k in range(2):
        db = tmp_path / f"db{k}.db"
        build_database(pycolmap, db, tmp_path / "scene", names, None, DatabaseConfig(verification_seed=7), None)
        d = pycolmap.Database.open(db)
        name = {img.image_id: img.name for img in d.read_all_images()}
        pairs, geoms = d.read_two_view_geometries()
        canon = {}  # by image names: the extraction's threads may number the images in another order
        for p, g in zip(pairs, geoms):
            a, b = (name[i] for i in pycolmap.pair_id_to_image_pair(int(p)))
            m = np.asarray(g.inlier_matches).reshape(-1, 2)
            if a > b:
                a, b, m = b, a, m[:, ::-1]
            canon[(a, b)] = sorted(map(tuple, m.tolist()))
        got.append(canon)
        d.close()
    assert [o.ransac.random_seed for o in seen] == [7, 7]
    assert got[0] == got[1] and len(got[0]) >= 4
