"""docker-compose.yml: PostgreSQL 16 with a health check and a named volume; the app waits for it."""

from pathlib import Path

import yaml

COMPOSE = Path(__file__).resolve().parents[1] / "docker-compose.yml"


def test_compose_file_describes_app_and_postgres():
    spec = yaml.safe_load(COMPOSE.read_text())
    db, app = spec["services"]["db"], spec["services"]["app"]
    assert db["image"] == "postgres:16"
    assert "pg_isready" in " ".join(db["healthcheck"]["test"])
    volume = db["volumes"][0].split(":")[0]
    assert volume in spec["volumes"]  # a named volume, not a bind mount
    assert app["depends_on"]["db"]["condition"] == "service_healthy"
    env = app["environment"]
    assert env["DATABASE_URL"].startswith("postgresql://") and "@db:5432/" in env["DATABASE_URL"]
    assert "ANIMSTUDY_SECRET_KEY" in env and "ANIMSTUDY_ADMIN_PASSWORD" in env
    assert "animstudy serve" in " ".join(yaml.safe_load(app["build"]["dockerfile_inline"].split("CMD", 1)[1]))
    assert app["healthcheck"]["test"] and app["ports"][0].endswith(":8000")
