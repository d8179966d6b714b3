"""The FastAPI application."""

from __future__ import annotations

import json

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy import Engine
from sqlalchemy.exc import InterfaceError, OperationalError
from starlette.middleware.trustedhost import TrustedHostMiddleware

from .config import Settings
from .db import make_engine, migrate, read_only, session_factory
from .deps import request_is_https
from .errors import ServiceError
from .files import ContentStaticFiles
from .media.router import router as media_router
from .pages import STATIC_DIR
from .pages import router as pages_router
from .participants.router import router as participants_router
from .pipeline.router import router as builds_router
from .research.router import router as studies_router
from .researchers.router import router as researchers_router
from .security import RETRY_AFTER_S, LoginLimiter, Protect, RateLimiter
from .uploads.router import router as uploads_router
from .uploads.router import upload_route


def create_app(settings: Settings | None = None, engine: Engine | None = None, run_migrations: bool = True
               ) -> FastAPI:
    """The app for ``settings`` (default: from the environment); migrates the database unless told not to."""
    settings = settings or Settings()
    engine = engine or make_engine(settings.sqlalchemy_url)
    if run_migrations:
        migrate(engine, media_dir=settings.media_dir, clips_dir=settings.clips_dir)
    # No trailing-slash redirects: Starlette builds their Location from the request's Host header.
    # The API's documentation maps every endpoint for anyone: served only when ANIMSTUDY_API_DOCS says so.
    docs = settings.api_docs
    app = FastAPI(title="animstudy", version="0.1.0", redirect_slashes=False,
                  description="Side-by-side user studies of character animation: conditions against a reference.",
                  docs_url="/docs" if docs else None, redoc_url="/redoc" if docs else None,
                  openapi_url="/openapi.json" if docs else None)
    app.state.settings = settings
    app.state.engine = engine
    app.state.read_engine = read_only(engine)
    app.state.session_factory = session_factory(engine)

    app.state.login_limiter = LoginLimiter()
    app.state.session_limiter = RateLimiter(settings.sessions_per_minute, window_s=60.0)
    if "*" not in settings.allowed_hosts:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=settings.allowed_hosts, www_redirect=False)
    # Added last: outermost, so even the host check's 400 has the security headers.  Uploads stream their body.
    app.add_middleware(Protect, streamed=[upload_route(settings.upload_max_bytes)],
                       is_https=lambda scope: request_is_https(scope, settings.proxy_networks))

    @app.exception_handler(RequestValidationError)
    def invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = jsonable_encoder(exc.errors())
        for error in errors:  # an input that cannot be put in JSON is left out rather than failing the answer
            try:
                json.dumps(error.get("input"), ensure_ascii=False, allow_nan=False).encode()
            except (ValueError, TypeError):
                error.pop("input", None)
        return JSONResponse({"detail": errors}, status_code=422)

    @app.exception_handler(ServiceError)
    def service_error(_request: Request, exc: ServiceError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status_code == 401 else {}
        if exc.retry_after is not None:
            headers["Retry-After"] = str(exc.retry_after)
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(OperationalError)
    @app.exception_handler(InterfaceError)
    def database_unavailable(_request: Request, _exc: Exception) -> JSONResponse:
        # The database is down, restarting or locked: nothing was stored; the client should simply retry.
        return JSONResponse({"detail": "the database is unavailable for a moment; please retry"}, status_code=503,
                            headers={"Retry-After": str(RETRY_AFTER_S)})

    @app.get("/healthz", include_in_schema=False)
    def health() -> dict[str, str]:
        return {"status": "ok"}

    for router in (uploads_router, builds_router, studies_router, participants_router, researchers_router,
                   media_router, pages_router):
        app.include_router(router)
    app.mount("/static", ContentStaticFiles(directory=STATIC_DIR), name="static")
    return app


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory`` (several workers each build their own app)."""
    return create_app(run_migrations=False)
