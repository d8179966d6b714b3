"""Migrations: empty -> head -> base works, and head matches the models exactly."""

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from server.db import downgrade, migrate
from server.models import Base
from tests.conftest import DATABASES, _fresh_engine


@pytest.mark.parametrize("kind", DATABASES)
def test_upgrade_downgrade_and_no_drift(kind, tmp_path_factory):
    engine = _fresh_engine(kind, tmp_path_factory, database="test_animstudy_migrations")
    try:
        migrate(engine)
        tables = set(inspect(engine).get_table_names())
        assert {"studies", "stimuli", "comparisons", "sessions", "trials", "votes", "researchers"} <= tables
        with engine.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
        assert diff == [], f"the models differ from the migrations: {diff}"
        downgrade(engine, "base")
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
        migrate(engine)  # and up again
        assert "votes" in inspect(engine).get_table_names()
    finally:
        engine.dispose()
