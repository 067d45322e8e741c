"""The /docs page renders in a real headless Chromium with no failed requests (offline).

Needs Debian's chromium (/usr/bin/chromium, installed by .ci/run) and the playwright package
(driver only; it never downloads a browser here).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.service_helpers import Server

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def test_docs_page_renders_in_headless_chromium(tmp_path: Path) -> None:
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    failed: list[str] = []
    outside: list[str] = []
    with Server(tmp_path / "data") as server, sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=CHROMIUM, headless=True,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"])
        try:
            page = browser.new_page()
            page.on("requestfailed", lambda r: failed.append(f"{r.url} {r.failure}"))
            page.on("console", lambda m: failed.append(f"csp: {m.text}")
                    if "Content Security Policy" in m.text else None)
            page.on("request", lambda r: outside.append(r.url)
                    if not r.url.startswith(server.url) and not r.url.startswith("data:")
                    else None)
            response = page.goto(server.url + "/docs", wait_until="networkidle")
            assert response is not None and response.status == 200
            # Swagger UI has rendered the operations of the API from /openapi.json
            page.wait_for_selector(".opblock", timeout=20_000)
            text = page.inner_text("body")
            assert "/jobs" in text and "/processes" in text
            page.screenshot(path=str(tmp_path / "docs.png"))
            if os.environ.get("POLYDDA_DOCS_SCREENSHOT"):
                page.screenshot(path=os.environ["POLYDDA_DOCS_SCREENSHOT"])
        finally:
            browser.close()
    assert failed == []
    assert outside == []  # every asset is served locally: works with no internet
    assert (tmp_path / "docs.png").stat().st_size > 10_000
