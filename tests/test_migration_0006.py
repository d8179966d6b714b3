"""Migration 0006 (study assets and build jobs) on a database populated at revision 0005: nothing existing moves,
the new tables take rows that refer to the existing studies, and going back to 0005 keeps everything else."""

from __future__ import annotations

import random

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from server.db import downgrade, migrate
from server.jobs.models import BuildJob
from server.studies.models import Study
from server.uploads.models import StudyAsset
from tests.conftest import DATABASES, _fresh_engine
from tests.test_migration_0004 import populate_0003
from tests.test_migration_0005 import dump


@pytest.mark.parametrize("kind", DATABASES)
def test_0006_adds_assets_and_jobs_and_keeps_everything(kind, tmp_path_factory):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migration_0006")
    try:
        migrate(engine, "0003")
        with engine.begin() as conn:
            study_id = populate_0003(conn, random.Random(6))
        migrate(engine, "0005")
        with engine.connect() as conn:
            before = dump(conn)
            assert "study_assets" not in sa.inspect(conn).get_table_names()
        assert sum(len(rows) for rows in before.values()) > 100

        migrate(engine)

        with engine.connect() as conn:
            assert dump(conn) == before
        with Session(engine) as db:
            assert db.get(Study, study_id) is not None
            db.add(StudyAsset(study_id=study_id, name="walk2", filename="walk2.bvh", size_bytes=10, sha256="0" * 64,
                              kind="gait", first_frame=0, last_frame=9, report={"joints": 31}))
            db.add(BuildJob(study_id=study_id))
            db.commit()
            job = db.scalar(sa.select(BuildJob))
            assert (job.state, job.stage, job.done, job.total, job.error) == ("queued", "queued", 0, 0, None)
            db.add(StudyAsset(study_id=study_id, name="walk2", filename="other.bvh", size_bytes=10,
                              sha256="0" * 64, kind="gait", first_frame=0, last_frame=9, report={}))
            with pytest.raises(sa.exc.IntegrityError):  # one animation name per study
                db.commit()

        downgrade(engine, "0005")
        with engine.connect() as conn:
            assert dump(conn) == before
            assert "study_assets" not in sa.inspect(conn).get_table_names()
    finally:
        engine.dispose()
