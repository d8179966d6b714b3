"""The dashboard reads a motion file as the researcher says (issue 24): units, up axis and a joint mapping chosen
in the upload form, shown in the list, and changed afterwards; in Chromium."""

from __future__ import annotations

import json

from tests.conftest import own_contexts
from tests.server_fixtures import RESEARCHER
from tests.test_participant_page import wait_until
from tests.test_upload_browser import site
from tests.test_uploads import excerpt
from tests.test_wild_uploads import _scaled

__all__ = ["site"]


def test_units_and_mapping_from_the_upload_form(browser, site, tmp_path, data):
    small = tmp_path / "small.bvh"
    small.write_bytes(_scaled(excerpt(data, frames=45), 0.3))  # legs of 4.4 units: no human in any unit
    stick = tmp_path / "stick.bvh"
    text = excerpt(data, frames=45).decode()
    for joint in ("LeftUpLeg", "LeftLeg", "LeftFoot"):
        text = text.replace(f"JOINT {joint}\n", f"JOINT Stick{joint[4:]}\n")
    stick.write_text(text)
    with own_contexts(browser):
        page = browser.new_context(viewport={"width": 1280, "height": 900}).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{site}/dashboard/studies")
        page.wait_for_selector("#login:not([hidden])")
        page.fill("#email", RESEARCHER[0])
        page.fill("#password", RESEARCHER[1])
        page.click("#login-form button")
        page.click("#table-studies tr[data-slug=own] >> text=Motion files")
        page.wait_for_selector("#assets-panel:not([hidden])")

        page.set_input_files("#asset-file", str(small))
        page.click("#asset-form button")
        wait_until(page, "document.getElementById('asset-errors').textContent.includes('To go on: choose the units')")
        page.set_input_files("#asset-file", str(small))
        page.select_option("#asset-units", "m")
        page.click("#asset-form button")
        page.wait_for_selector("#table-assets tr[data-asset=small]")
        assert "m (given), Y up" in page.inner_text("#table-assets tr[data-asset=small]")

        page.set_input_files("#asset-file", str(stick))
        page.select_option("#asset-units", "auto")
        page.fill("#asset-mapping", "LeftUpLeg = StickUpLeg\nLeftLeg = StickLeg\nLeftFoot = StickFoot")
        page.click("#asset-form button")
        page.wait_for_selector("#table-assets tr[data-asset=stick]")
        assert "3 joints mapped by hand" in page.inner_text("#table-assets tr[data-asset=stick]")

        # read again in other units: the list says so
        page.click("#table-assets tr[data-asset=stick] >> text=Change")
        assert page.input_value("#asset-mapping-edit").count("=") == 3
        page.select_option("#asset-units-edit", "cm")
        page.click("#asset-edit button[type=submit]")
        wait_until(page, "document.querySelector('#table-assets tr[data-asset=stick]') && "
                         "document.querySelector('#table-assets tr[data-asset=stick]').textContent"
                         ".includes('cm (given)')")
        assert errors == [], json.dumps(errors)
