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


def test_image_uses_the_shipped_data_without_a_mount():
    app = yaml.safe_load(COMPOSE.read_text())["services"]["app"]
    dockerfile = app["build"]["dockerfile_inline"]
    assert "COPY . ." in dockerfile and "ANIMSTUDY_DATA_DIR=/app/data" in dockerfile  # /app/data = the repo's data/
    assert not [v for v in app.get("volumes", []) if ":/app/data" in v or ":/data" in v]
    ignored = (COMPOSE.parent / ".dockerignore").read_text().split()
    assert "data" not in ignored and "/data" not in ignored
