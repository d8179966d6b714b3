"""The service's settings, read once from the environment (prefix ``ANIMSTUDY_``, plus ``DATABASE_URL``)."""

from __future__ import annotations

import ipaddress
import os
from functools import cached_property
from pathlib import Path
from typing import Annotated

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]


class Settings(BaseSettings):
    """``ANIMSTUDY_DATA_DIR``: read-only source assets (motion capture, character); default the sample data shipped
    in the repository (``data/``).  ``ANIMSTUDY_VAR_DIR``: everything the service writes (database file, clips, videos,
    secret key); default ``./var``.  ``DATABASE_URL``: default an SQLite file in the var directory; a
    ``postgresql://`` URL is the real deployment.  ``ANIMSTUDY_SECRET_KEY``: signs researcher tokens and names the
    videos; default a random key kept in ``<var>/secret.key``.  ``ANIMSTUDY_ALLOWED_HOSTS``: the host names the
    service answers to, comma-separated (``*.example.org`` matches subdomains); default ``*``, any; other
    ``Host`` headers get 400.  ``ANIMSTUDY_SESSIONS_PER_MINUTE``: new participant sessions allowed per client
    address and minute (counted in the database: once across every process and instance); default 60, 0 for no
    limit.  ``ANIMSTUDY_UPLOAD_MAX_BYTES``: the
    largest motion file a researcher may upload into a study's assets (``POST /api/v1/studies/{slug}/assets``);
    default 50 MB (50 * 2**20 bytes).  ``ANIMSTUDY_TRUSTED_PROXIES``: addresses of the reverse proxies whose
    ``X-Forwarded-For`` names the client (comma-separated IP addresses or networks, e.g. ``127.0.0.1,10.0.0.0/8``);
    default none: the header is ignored, and the rate limits count the connecting address.
    ``ANIMSTUDY_BUILD_MEMORY_MB``: the address space a build job's process may take (``RLIMIT_AS``), beyond which
    the build fails with a MemoryError instead of taking the machine's memory; default 8192, 0 for no limit.
    ``ANIMSTUDY_BUILDS_MAX``: how many build jobs (a study's uploads or inline ``[clips]``) may run at once on the
    server, one per researcher; default 2.
    ``ANIMSTUDY_DASK_SCHEDULER``: the Dask scheduler that renders run on (e.g. ``tcp://host:8786``, see
    docs/cluster.md); default none: a local Dask cluster started per job.  ``ANIMSTUDY_API_DOCS``: serve the
    API's documentation (``/docs``, ``/redoc``, ``/openapi.json``) to anyone; default false (404): it maps every
    endpoint for a visitor, and a researcher has it in the manual (docs/reference)."""

    model_config = SettingsConfigDict(env_prefix="ANIMSTUDY_", extra="ignore")

    data_dir: Path = REPO_ROOT / "data"
    var_dir: Path = Path("var")
    database_url: str | None = Field(default=None, validation_alias=AliasChoices("DATABASE_URL",
                                                                                 "ANIMSTUDY_DATABASE_URL"))
    secret_key: str | None = None
    admin_email: str | None = None
    admin_password: str | None = None
    token_hours: float = 12.0
    allowed_hosts: Annotated[list[str], NoDecode] = ["*"]
    trusted_proxies: Annotated[list[str], NoDecode] = []
    sessions_per_minute: int = Field(default=60, ge=0)
    upload_max_bytes: int = Field(default=50 * 2**20, ge=1)
    build_memory_mb: int = Field(default=8192, ge=0)
    builds_max: int = Field(default=2, ge=1)
    dask_scheduler: str | None = None
    api_docs: bool = False

    @field_validator("allowed_hosts", "trusted_proxies", mode="before")
    @classmethod
    def comma_separated(cls, value: object) -> object:
        if isinstance(value, str):
            return [h.strip() for h in value.split(",") if h.strip()]
        return value

    @field_validator("trusted_proxies")
    @classmethod
    def networks(cls, value: list[str]) -> list[str]:
        for item in value:
            try:
                ipaddress.ip_network(item, strict=False)
            except ValueError:
                raise ValueError(f"{item!r} is not an IP address or network") from None
        return value

    @cached_property
    def proxy_networks(self) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
        return tuple(ipaddress.ip_network(p, strict=False) for p in self.trusted_proxies)

    @classmethod
    def from_env(cls) -> Settings:
        return cls()

    @cached_property
    def data(self) -> Path:
        return self.data_dir.resolve()

    @cached_property
    def var(self) -> Path:
        return self.var_dir.resolve()

    @property
    def clips_dir(self) -> Path:
        return self.var / "clips"

    @property
    def media_dir(self) -> Path:
        return self.var / "media"

    @property
    def assets_dir(self) -> Path:
        """Uploaded motion files, ``<study id>/<file name>``; uploads arrive in ``.incoming/`` beside them."""
        return self.var / "assets"

    def study_assets_dir(self, study_id: int) -> Path:
        """One study's uploaded files, its asset clip set and its build log (deleted with the study)."""
        return self.assets_dir / str(study_id)

    @property
    def benchmark_path(self) -> Path:
        """Results of ``animstudy benchmark`` (shown on the dashboard when present)."""
        return self.var / "benchmark" / "results.json"

    @property
    def sqlalchemy_url(self) -> str:
        return normalize_database_url(self.database_url or f"sqlite:///{self.var / 'animstudy.db'}")

    @cached_property
    def secret(self) -> bytes:
        """The secret key (created once, 0600, in the var directory when not set)."""
        if self.secret_key:
            return self.secret_key.encode()
        path = self.var / "secret.key"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            except FileExistsError:  # another process made it first
                pass
            else:
                with os.fdopen(fd, "w") as f:
                    f.write(os.urandom(32).hex())
        return path.read_text().strip().encode()


def normalize_database_url(url: str) -> str:
    """``postgresql://`` and ``postgres://`` URLs use the psycopg 3 driver."""
    for prefix in ("postgres://", "postgresql://"):
        if url.startswith(prefix):
            return "postgresql+psycopg://" + url[len(prefix):]
    return url
