"""Alembic environment: runs on a connection handed over by the service, or on a URL (-x url=...)."""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine

from server.config import Settings, normalize_database_url
from server.db import UTCDateTime
from server.models import Base

config = context.config
target_metadata = Base.metadata


def run() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run_on(connection)
        return
    url = context.get_x_argument(as_dictionary=True).get("url") or config.get_main_option("sqlalchemy.url")
    engine = create_engine(normalize_database_url(url) if url else Settings().sqlalchemy_url)
    with engine.begin() as conn:
        _run_on(conn)


def _render_item(type_: str, obj: object, autogen_context: object) -> str | bool:
    # Migrations must not import the app: write the column type UTCDateTime stands for.
    if type_ == "type" and isinstance(obj, UTCDateTime):
        return "sa.DateTime(timezone=True)"
    return False


def _run_on(connection: object) -> None:
    context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True,
                      compare_type=True, render_item=_render_item)
    with context.begin_transaction():
        context.run_migrations()


run()
