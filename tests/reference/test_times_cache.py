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
