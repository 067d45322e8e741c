"""A staged run in the browser (Debian's headless Chromium, driven by playwright): the
viewer names each frame's stage and no longer draws the blocks a stage dug out; the report
has the table of the stages."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.excavation_scenes import roof_wedge_scene
from tests.service_helpers import Server, wait_final
from tests.test_service_viewer_browser import ARGS, CHROMIUM, wait_js


@pytest.fixture(scope="module")
def staged(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, str, Any]]:
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    data = tmp_path_factory.mktemp("stages-browser") / "data"
    with Server(data) as server, sync_api.sync_playwright() as pw:
        with httpx.Client(base_url=server.url, timeout=30) as client:
            r = client.post("/jobs", json=roof_wedge_scene(fall=0.3))
            assert r.status_code == 201, r.text
            url = r.headers["Location"]
            assert wait_final(client, url, timeout=120)["status"] == "successful"
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        try:
            yield server, url.rsplit("/", 1)[1], browser
        finally:
            browser.close()


def test_viewer_shows_the_stages(staged: Any) -> None:
    server, job, browser = staged
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    # the page's Content-Security-Policy (service.api.middleware) blocks nothing it needs
    page.on("console", lambda m: errors.append(f"csp {m.text}")
            if "Content Security Policy" in m.text else None)
    try:
        # a finished run opens at its first frame and plays: stay, then go to its end
        page.goto(f"{server.url}/jobs/{job}/viewer?play=false")
        wait_js(page, "window.polydda && window.polydda.ready", timeout=20_000)
        assert "stage settle" in page.inner_text("#frame-label")
        page.focus("#slider")
        page.keyboard.press("End")
        assert "stage excavate" in page.inner_text("#frame-label")
        core = page.evaluate("polydda.removed()")
        assert len(core) == 1  # the cavern's rock, gone at the end
        if os.environ.get("POLYDDA_VIEWER_SCREENSHOTS"):
            page.screenshot(path=str(Path(os.environ["POLYDDA_VIEWER_SCREENSHOTS"])
                                     / "stages-end.png"))
        page.keyboard.press("Home")
        assert page.evaluate("polydda.removed()") == []
        assert "stage settle" in page.inner_text("#frame-label")
        r = httpx.get(f"{server.url}/jobs/{job}/report", timeout=60)
        assert r.status_code == 200 and "Stages" in r.text and "settle" in r.text
        assert "blocks removed" in r.text
    finally:
        page.close()
    assert errors == []
