"""End to end (issue 24): a study whose clip set mixes the CMU motion with a Bandai-style rig made from CMU motion
(a static root above the hips, 6 channels on every joint, bones along local X so the zero pose lies in a heap,
Euler order ZXY, centimetres) uploaded with no options: it builds through the gate, renders small, and a
participant is served its trials.  A source with left and right swapped fails the gate; built anyway, its votes
are marked unfaithful in the export."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from anim_core.io.bvh import format_bvh, parse_bvh
from server.app import create_app
from server.clipset.manifest import read_clip_manifest
from server.config import Settings
from server.db import migrate
from server.media.manifest import read_render_manifest
from tests.conftest import _fresh_engine
from tests.server_fixtures import RESEARCHER, start, vote
from tests.test_upload_job import small_site, wait_for
from tests.test_uploads import SECRET, excerpt, login
from tests.test_wild_motion import _swapped, wild_rig


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_mixed_cmu_and_bandai_style_rig_build_render_and_serve(tmp_path, tmp_path_factory, data):
    engine = _fresh_engine("sqlite", tmp_path_factory)
    settings = Settings(var_dir=tmp_path / "var", data_dir=data, secret_key=SECRET)
    try:
        migrate(engine)
        small_site(settings, engine, tmp_path)  # the CMU animation "base", keyframe and hybrid0, 64x48 videos
        cmu = parse_bvh(excerpt(data, frames=45, start=60).decode(), "sway.bvh")
        rig = wild_rig(cmu, np.random.default_rng(24), "x-bones", scale=100 * 0.0254 / 0.45, static_root=True,
                       six_channels=True, order="ZXY")
        with TestClient(create_app(settings, engine, run_migrations=False)) as client:
            headers = login(client, *RESEARCHER)
            r = client.post("/api/v1/studies/own/assets", params={"filename": "bandai_sway.bvh"},
                            content=format_bvh(rig).encode(), headers=headers)
            assert r.status_code == 201, r.text
            report = r.json()["report"]
            assert (report["units"], report["up_axis"], report["options"]) == ("cm", "y", {})
            assert any("not a standing pose" in n for n in report["notes"])
            assert any("'joint_Root' above 'Hips' left out" in n for n in report["notes"])

            swapped = format_bvh(_swapped(cmu)).encode()  # its left leg on the body's right
            r = client.post("/api/v1/studies/own/assets", params={"filename": "swapped.bvh"}, content=swapped,
                            headers=headers)
            assert r.status_code == 201, r.text
            assert client.post("/api/v1/studies/own/assets/build", headers=headers).status_code == 202
            job = wait_for(client, headers, timeout_s=600)
            assert job["state"] == "failed" and "[animations.swapped]" in job["error"]
            assert "left and right swapped" in job["error"] and "accept_unfaithful" in job["error"]
            r = client.patch("/api/v1/studies/own/assets/swapped", json={"accept_unfaithful": True},
                             headers=headers)
            assert r.status_code == 200 and r.json()["report"]["accept_unfaithful"] is True
            assert client.post("/api/v1/studies/own/assets/build", headers=headers).status_code == 202
            job = wait_for(client, headers, timeout_s=600)
            assert job["state"] == "done", (job, (settings.assets_dir / "1" / "build.log").read_text())

            clips = read_clip_manifest(settings.clips_dir)
            mine = {c.condition: c for c in clips.clips if c.animation == "bandai_sway"}
            assert set(mine) == {"keyframe", "hybrid0"}
            for c in mine.values():
                assert c.metrics["unfaithful"] == 0.0 and c.metrics["upright_m"] > 0.3
                assert c.metrics["foot_reach_m"] < 0.05 and c.metrics["handedness"] == 1.0
            assert mine["keyframe"].metrics["pose_error_deg"] < 20.0
            media = read_render_manifest(settings.media_dir)
            videos = [v for v in media.clips.values() if v.animation == "bandai_sway"]
            assert videos and all((settings.media_dir / v.video).stat().st_size > 0 for v in videos)

            assert client.post("/api/v1/studies/own/open", headers=headers).json()["state"] == "open"
            sid, participant = start(client, "own")
            served = 0
            while (r := client.get(f"/api/v1/sessions/{sid}/next", headers=participant)).status_code == 200:
                trial = r.json()
                video = client.get(trial["video_url"])
                assert video.status_code == 200 and len(video.content) > 0
                assert vote(client, sid, participant, trial["trial_id"]).status_code == 201
                served += 1
                if served > 20:
                    break
            assert served == 3 * 2 + 1  # base, bandai_sway and swapped: two trials each, and one catch trial
            assert {c.id for c in clips.clips if c.metrics.get("unfaithful")} == {"swapped-keyframe",
                                                                                   "swapped-hybrid0"}
            rows = client.get("/api/v1/studies/own/export.json", headers=headers).json()["votes"]
            assert len(rows) == served
            assert {r["animation"] for r in rows if r["unfaithful"]} == {"swapped"}
            assert {r["animation"] for r in rows if not r["unfaithful"]} >= {"base", "bandai_sway"}
    finally:
        engine.dispose()
