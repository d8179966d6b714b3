"""Uploads of motion from the wild (issue 24): units, up axis and a joint mapping given with the upload or changed
afterwards, as on the command line, and upload errors that say what to do next."""

import json

from anim_core.io.bvh import Bvh, format_bvh, parse_bvh
from anim_core.math.skeleton import Skeleton
from server.uploads.models import StudyAsset
from tests.test_uploads import admin, app_settings, asset_rows, draft, excerpt, stored_files, uclient, upload

__all__ = ["admin", "app_settings", "draft", "uclient"]  # fixtures used below


def _scaled(body: bytes, factor: float) -> bytes:
    bvh = parse_bvh(body.decode(), "small.bvh")
    motion = bvh.motion.copy()
    motion[:, :3] *= factor  # the root's position channels
    s = bvh.skeleton
    return format_bvh(Bvh(Skeleton(s.names, s.parents, s.offsets * factor), bvh.channels,
                          {j: e * factor for j, e in bvh.end_sites.items()}, bvh.frame_time, motion)).encode()


def test_units_up_axis_and_mapping_with_the_upload(uclient, admin, draft, data, app_settings, db):
    small = _scaled(excerpt(data), 0.3)  # legs of 4.4 units: no human in any unit
    r = upload(uclient, admin, small, "small.bvh")
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "not a human height" in detail and "To go on: choose the units, the up axis or a joint mapping" in detail
    assert stored_files(app_settings) == [] and asset_rows(db) == 0
    assert upload(uclient, admin, small, "small.bvh", units="furlong").status_code == 422
    r = upload(uclient, admin, small, "small.bvh", units="m", up="y")
    assert r.status_code == 201, r.text
    report = r.json()["report"]
    assert report["units"] == "m" and report["options"] == {"units": "m", "up_axis": "y"}

    # A rig whose left leg the names do not tell: refused, then read with a mapping.
    text = excerpt(data).decode()
    for joint in ("LeftUpLeg", "LeftLeg", "LeftFoot"):
        text = text.replace(f"JOINT {joint}\n", f"JOINT Stick{joint[4:]}\n")
    r = upload(uclient, admin, text.encode(), "stick.bvh")
    assert r.status_code == 422 and "left leg" in r.json()["detail"] and "joint mapping" in r.json()["detail"]
    mapping = {"LeftUpLeg": "StickUpLeg", "LeftLeg": "StickLeg", "LeftFoot": "StickFoot"}
    r = upload(uclient, admin, text.encode(), "stick.bvh", mapping=json.dumps(mapping))
    assert r.status_code == 201, r.text
    assert r.json()["report"]["options"]["mapping"] == mapping
    assert {m["joint"]: m["source"] for m in r.json()["report"]["mapping"]}["LeftLeg"] == "StickLeg"
    for bad in ("{not json", '{"Knee": "StickLeg"}', '["StickLeg"]'):
        assert upload(uclient, admin, text.encode(), "stick2.bvh", mapping=bad).status_code == 422


def test_changing_how_a_file_is_read_inspects_it_again(uclient, admin, draft, data, app_settings):
    assert upload(uclient, admin, excerpt(data)).status_code == 201
    r = uclient.patch("/api/v1/studies/mine/assets/idle45", json={"units": "cm"}, headers=admin)
    assert r.status_code == 200, r.text
    assert r.json()["report"]["units"] == "cm" and r.json()["report"]["options"] == {"units": "cm"}
    r = uclient.patch("/api/v1/studies/mine/assets/idle45", json={"units": "auto"}, headers=admin)
    assert r.json()["report"]["units"] == "cmu" and r.json()["report"]["options"] == {}
    r = uclient.patch("/api/v1/studies/mine/assets/idle45", json={"mapping": {"LeftLeg": "NoSuchJoint"}},
                      headers=admin)
    assert r.status_code == 422 and "NoSuchJoint" in r.json()["detail"] and "To go on" in r.json()["detail"]
    assert uclient.patch("/api/v1/studies/mine/assets/idle45", json={"up_axis": "x"},
                         headers=admin).status_code == 422


def test_the_clip_set_description_reads_the_file_as_the_researcher_said(tmp_path):
    from server.clipset.config import CharacterConfig
    from server.pipeline.assets import BaseClipSet, assets_config

    options = {"units": "cm", "up_axis": "z", "mapping": {"LeftLeg": "StickLeg"}}
    asset = StudyAsset(id=1, name="stick", filename="stick.bvh", kind="idle", first_frame=0, last_frame=9,
                       report={"options": options})
    config = assets_config([asset], lambda a: tmp_path / a.filename,
                           BaseClipSet(30, ("LHipJoint",), CharacterConfig(), [("keyframe", "keyframe", {})]))
    cfg = config.animations["stick"]
    assert (cfg.units, cfg.up_axis) == ("cm", "z")
    assert json.loads((tmp_path / "stick.mapping.json").read_text()) == options["mapping"] == json.loads(
        open(cfg.mapping).read())
