"""The researcher API of a study's assets (docs/motion/uploads.md).

``POST /api/v1/studies/{slug}/assets?filename=NAME[&name=ANIMATION]`` takes the file itself as the raw request
body (any content type; ``Content-Length`` or chunked), not a multipart form: the body streams straight into a
file, and the dashboard sends a ``File`` as is.
"""

from __future__ import annotations

import json
import re
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field

from server.deps import SessionDep, SettingsDep
from server.errors import PayloadTooLarge, Unprocessable
from server.jobs.control import job_json, latest_job
from server.researchers.deps import ResearcherDep
from server.security import StreamedRoute
from server.studies.service import managed_study

from . import service

router = APIRouter(prefix="/api/v1", tags=["assets"])
UPLOAD_PATH = re.compile(r"/api/v1/studies/[^/]+/assets")


def upload_route(max_bytes: int) -> StreamedRoute:
    """The upload route as the body-limit middleware exempts it (:class:`server.security.StreamedRoute`)."""
    return StreamedRoute("POST", UPLOAD_PATH, max_bytes)


class AssetChange(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    kind: str | None = Field(None, description="the clip-set kind its clips are built as (gait, crouch, idle)")
    frames: list[int] | None = Field(None, min_length=2, max_length=2,
                                     description="first and last source frame (inclusive)")
    units: str | None = Field(None, description="the file's units (m, cm, mm, inch, cmu); 'auto' detects them")
    up_axis: str | None = Field(None, description="the file's up axis (y, z); 'auto' detects it")
    mapping: dict[str, str] | None = Field(None, description="character joint -> file joint, where the names do "
                                                             "not tell; {} clears it")
    accept_unfaithful: bool | None = Field(None, description="build its clips even if they fail the fidelity gate "
                                                             "(they are marked unfaithful, also in the export)")


@router.post("/studies/{slug}/assets", status_code=status.HTTP_201_CREATED,
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_asset(slug: str, request: Request, session: SessionDep, settings: SettingsDep,
                       researcher: ResearcherDep,
                       filename: Annotated[str, Query(max_length=200, description="the file's name (.bvh, .glb, "
                                                      ".gltf)")],
                       name: Annotated[str | None, Query(description="the animation it becomes (default: from the "
                                                         "file name)")] = None,
                       units: Annotated[str | None, Query(description="the file's units (m, cm, mm, inch, cmu; "
                                                          "default: detected from the leg length)")] = None,
                       up: Annotated[str | None, Query(description="the file's up axis (y, z; default: detected "
                                                       "from the motion)")] = None,
                       mapping: Annotated[str | None, Query(max_length=8000, description="JSON object character "
                                                            "joint -> file joint, where the names do not tell")]
                       = None) -> dict[str, Any]:
    """Upload a BVH or glTF file into a draft study's assets (the raw body is the file; at most
    ``ANIMSTUDY_UPLOAD_MAX_BYTES``, default 50 MB, else 413).  It is inspected before anything is stored; the
    answer is the asset with what inspecting it found (joints, convention, units, fps, frames, suggested kind and
    frames).  Errors: a bad file name or a file that does not read → 422 with the reason (file and line for
    BVH), the name taken → 409, not a draft → 409."""
    filename = service.check_filename(filename)
    animation = service.animation_name(filename, name)
    try:
        explicit = json.loads(mapping) if mapping is not None else None
    except ValueError:
        raise Unprocessable("mapping: not JSON; an object of character joint -> file joint names, e.g. "
                            "{\"LeftUpLeg\": \"thigh_l\"}") from None
    options = service.check_options(units, up, explicit)

    def check() -> Any:
        study = service.draft_study(session, slug, researcher)
        service.check_takes_uploads(settings, study)
        service.check_free(session, study, filename, animation)
        # No transaction stays open while the body arrives (on SQLite it would hold the write lock).
        session.rollback()
        return study

    study = await run_in_threadpool(check)
    limit = settings.upload_max_bytes
    incoming = await run_in_threadpool(service.incoming_path, settings, filename)
    try:
        size = 0
        with incoming.open("wb") as f:  # chunks of at most 64 KiB into the page cache: written on the loop
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:  # stop reading here: the rest is never received
                    raise PayloadTooLarge(f"the file is larger than the upload limit of {limit} bytes "
                                          f"(ANIMSTUDY_UPLOAD_MAX_BYTES)")
                f.write(chunk)
        if size == 0:
            service.discard(incoming)
            raise Unprocessable(f"{filename}: the file is empty")
    except BaseException:
        service.discard(incoming)
        raise
    asset = await run_in_threadpool(service.store_upload, session, settings, study, incoming, animation, options)
    return service.asset_json(asset)


@router.get("/studies/{slug}/assets")
def list_assets(slug: str, session: SessionDep, researcher: ResearcherDep) -> dict[str, Any]:
    """The study's assets with their inspection reports, its latest build job (``build``, or null) and the kinds
    an asset may be built as (``kinds``)."""
    from server.clipset.config import KINDS

    study = managed_study(session, slug, researcher)
    return {"assets": [service.asset_json(a) for a in service.list_assets(session, study)],
            "build": job_json(latest_job(session, study)), "kinds": list(KINDS)}


@router.patch("/studies/{slug}/assets/{name}")
def change_asset(slug: str, name: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep,
                 body: Annotated[AssetChange, Body()]) -> dict[str, Any]:
    """Change the kind or the frames its clips are built from, or how the file is read (units, up axis, joint
    mapping: it is inspected again; 422 with what to change if it does not read so) (draft only)."""
    study = service.draft_study(session, slug, researcher)
    asset = service.get_asset(session, study, name)
    options = None
    if body.units is not None or body.up_axis is not None or body.mapping is not None:
        old = dict(asset.report.get("options", {}))
        for key, value in (("units", body.units), ("up_axis", body.up_axis)):
            if value == "auto":
                old.pop(key, None)
            elif value is not None:
                old[key] = value
        if body.mapping is not None:
            old["mapping"] = body.mapping
        options = service.check_options(old.get("units"), old.get("up_axis"), old.get("mapping"))
    asset = service.update_asset(session, study, asset, body.kind,
                                 tuple(body.frames) if body.frames else None,  # type: ignore[arg-type]
                                 options, settings)
    if body.accept_unfaithful is not None:
        asset = service.accept_unfaithful(session, asset, body.accept_unfaithful)
    return service.asset_json(asset)


@router.delete("/studies/{slug}/assets/{name}", status_code=status.HTTP_204_NO_CONTENT)
def delete_asset(slug: str, name: str, session: SessionDep, settings: SettingsDep,
                 researcher: ResearcherDep) -> Response:
    study = service.draft_study(session, slug, researcher)
    service.delete_asset(session, settings, study, service.get_asset(session, study, name))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


class ShareRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    email: str = Field(min_length=3, max_length=254)


@router.get("/studies/{slug}/assets/{name}/shares")
def read_shares(slug: str, name: str, session: SessionDep, settings: SettingsDep,
                researcher: ResearcherDep) -> dict[str, Any]:
    """Who besides the study's owner (and admins) may use the animation built from this upload."""
    study = managed_study(session, slug, researcher)
    service.check_animation_of(session, settings, study, name)
    return {"animation": name, "shared_with": service.shared_with(session, study, name)}


@router.post("/studies/{slug}/assets/{name}/shares")
def share(slug: str, name: str, session: SessionDep, settings: SettingsDep, researcher: ResearcherDep,
          body: Annotated[ShareRequest, Body()]) -> dict[str, Any]:
    """Share the animation built from this upload with one named researcher (explicit; nobody else sees it)."""
    study = managed_study(session, slug, researcher)
    return {"animation": name, "shared_with": service.share_animation(session, settings, study, name, body.email)}


@router.delete("/studies/{slug}/assets/{name}/shares/{email}")
def unshare(slug: str, name: str, email: str, session: SessionDep, settings: SettingsDep,
            researcher: ResearcherDep) -> dict[str, Any]:
    """Stop sharing it with that researcher (their studies keep what they pinned)."""
    study = managed_study(session, slug, researcher)
    return {"animation": name, "shared_with": service.unshare_animation(session, settings, study, name, email)}
