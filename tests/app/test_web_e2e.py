"""The page at ``/`` driven in a real headless Chromium against a real ``meshmark serve``: choose a
shared mesh, mark it, download the marked file, check that file, see the payload; a bad file
shows its problem's title; with API keys on, the page asks for one.

Needs Debian's ``chromium`` (``/usr/bin/chromium``, or ``MESHMARK_TEST_CHROMIUM``) and the
``playwright`` package (dev extra; its own browser download is never used).  ``scripts/test``
installs chromium when it runs as root with apt; elsewhere these tests skip with the reason.

``MESHMARK_WEB_SCREENSHOTS=docs`` also saves the page before and after marking and after the
check (the README's screenshots) into that folder.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.app.real_server import Server, serve
from tests.conftest import ROOT, shared_mesh_path

CHROMIUM = Path(os.environ.get("MESHMARK_TEST_CHROMIUM", "/usr/bin/chromium"))
#: what works on a machine without a display or a GPU and with no network but loopback: the
#: network flags stop Chromium's own calls home; WebGL runs on SwiftShader (software)
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
KEY = "a key nobody guesses"
PAYLOAD = "1011001110001111"
TIMEOUT_MS = 90_000

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def playwright() -> Iterator[Any]:
    if not CHROMIUM.exists():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (scripts/test does it when run as "
                    "root), or set MESHMARK_TEST_CHROMIUM")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (.[dev])")
    with sync_api.sync_playwright() as p:
        yield p


def launch(playwright: Any, *extra: str) -> Any:
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS + list(extra), headless=True)


@pytest.fixture(scope="module")
def browser(playwright: Any) -> Iterator[Any]:
    browser = launch(playwright)
    yield browser
    browser.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with serve(tmp_path_factory.mktemp("web") / "server.log", workers="2") as s:
        yield s


class Page:
    """A fresh browser context on the page, recording every request and script error."""

    def __init__(self, browser: Any, base: str) -> None:
        self.context = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
        self.page = self.context.new_page()
        self.page.set_default_timeout(TIMEOUT_MS)
        self.requests: list[str] = []
        self.errors: list[str] = []
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.goto(base + "/")

    def webgl(self) -> bool:
        return bool(self.page.evaluate(
            "() => { const c = document.createElement('canvas');"
            " return !!(c.getContext('webgl2') || c.getContext('webgl')); }"))

    def choose(self, path_or_file: Any) -> None:
        self.page.set_input_files("#mesh", path_or_file)

    def wait_preview(self, heat: bool = False) -> None:
        self.page.wait_for_selector("#view[data-heat=on]" if heat else "#view[data-rendered]")

    def view_pixels(self) -> tuple[int, int, bytes]:
        """(pixels drawn, heat-coloured pixels, PNG) of the 3-D view as a person sees it."""
        from PIL import Image

        png = self.page.locator("#view").screenshot()
        r, g, b = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int32).transpose(2, 0, 1)
        drawn = (r < 245) | (g < 245) | (b < 245)
        # the unmarked surface is a blue-grey (b > r); the heat ramp goes from yellow to dark red
        heat = drawn & (r > b + 60) & (r >= g)
        return int(drawn.sum()), int(heat.sum()), png

    def close(self) -> None:
        assert not self.errors, self.errors
        self.context.close()


@pytest.fixture
def web(browser: Any, server: Server) -> Iterator[Page]:
    page = Page(browser, server.base)
    yield page
    page.close()


def screenshot(page: Page, name: str) -> None:
    folder = os.environ.get("MESHMARK_WEB_SCREENSHOTS")
    if folder:
        target = (ROOT / folder).resolve()
        target.mkdir(parents=True, exist_ok=True)
        page.page.screenshot(path=str(target / name), full_page=True)


def test_mark_download_then_check_the_downloaded_file(web: Page, server: Server, tmp_path: Path) -> None:
    bunny = shared_mesh_path("bun_zipper.ply")
    page = web.page
    web.choose(bunny)
    assert web.webgl(), "WebGL should run on SwiftShader with these flags"
    web.wait_preview()
    drawn, heat, _ = web.view_pixels()
    assert drawn > 20_000 and heat < 0.01 * drawn  # the bunny, unmarked: grey
    assert "35,947 vertices, 69,451 triangles (PLY)" in page.inner_text("#view-msg")
    screenshot(web, "web-before.png")

    page.fill("#key", KEY)
    page.fill("#payload", PAYLOAD)
    page.click("#embed-form button")
    page.wait_for_selector("#download")
    assert "Marked" in page.inner_text("#result")
    web.wait_preview(heat=True)
    assert page.locator("#legend").is_visible()
    assert "bounding-box diagonal" in page.inner_text("#legend-words")
    drawn, heat, _ = web.view_pixels()
    assert heat > 500, (drawn, heat)  # the carriers light up
    screenshot(web, "web-after.png")

    with page.expect_download() as download:
        page.click("#download")
    assert download.value.suggested_filename == "bun_zipper.marked.ply"
    marked = tmp_path / download.value.suggested_filename
    download.value.save_as(marked)
    original, data = bunny.read_bytes(), marked.read_bytes()
    # an ASCII PLY again, line for line, with moved vertices printed anew
    assert data != original and data.count(b"\n") == original.count(b"\n")
    assert data.split(b"end_header")[0] == original.split(b"end_header")[0]

    web.choose(marked)
    page.fill("#expected", PAYLOAD)
    page.click("#detect-form button")
    page.wait_for_selector("#result h3")
    assert page.inner_text("#result h3") == "Watermark found"
    assert page.inner_text("#payload-found") == PAYLOAD
    result = page.inner_text("#result")
    assert "by pure chance about 1 in" in result and "0 bits differ" in result
    assert page.locator("#result svg rect").count() == len(PAYLOAD)  # one confidence bar per bit
    assert page.inner_text("#status") == "Watermark found."
    screenshot(web, "web-detect.png")

    # the key went nowhere but the request bodies: not the address, storage or another host
    assert KEY not in page.url and "key" not in page.url
    assert page.evaluate("() => [localStorage.length, sessionStorage.length, document.cookie]") == [0, 0, ""]
    assert all(url.startswith((server.base + "/", "blob:")) for url in web.requests), web.requests
    assert not any(KEY.replace(" ", "%20") in url or KEY in url for url in web.requests)
    assert any(url.endswith("/v1/preview") for url in web.requests)


def test_a_bad_file_shows_the_problem_title(web: Page) -> None:
    page = web.page
    web.choose({"name": "broken.ply", "mimeType": "application/octet-stream",
                "buffer": b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n"})
    page.wait_for_selector("#view-msg:has-text('No preview')")
    assert "Malformed mesh file" in page.inner_text("#view-msg")
    page.fill("#key", KEY)
    page.click("#embed-form button")
    page.wait_for_selector("#error", state="visible")
    assert page.inner_text("#error-title") == "Malformed mesh file"
    detail = page.inner_text("#error-detail")
    assert detail and "{" not in detail
    assert '"type"' not in page.inner_text("body") and "problem+json" not in page.inner_text("body")


def test_a_missing_key_is_asked_for_before_any_request(web: Page) -> None:
    page = web.page
    web.choose(shared_mesh_path("spot.obj"))
    web.wait_preview()
    sent = len(web.requests)
    page.click("#embed-form button")
    assert page.inner_text("#error-title") == "A watermark key is needed"
    assert page.evaluate("() => document.activeElement.id") == "key"
    assert len(web.requests) == sent


def test_every_control_is_labelled_and_reached_by_the_keyboard(web: Page) -> None:
    page = web.page
    unlabelled = page.evaluate(
        "() => [...document.querySelectorAll('input, select')].filter(e => !e.labels.length).map(e => e.id)")
    assert unlabelled == []
    web.choose(shared_mesh_path("spot.obj"))  # enables the action buttons
    web.wait_preview()
    page.focus("body")
    reached = []
    for _ in range(30):
        page.keyboard.press("Tab")
        reached.append(page.evaluate("() => document.activeElement.id || document.activeElement.textContent"))
    for wanted in ("mesh", "key", "payload", "method", "strength", "Mark", "Check", "Measure", "background",
                   "view"):
        assert wanted in reached, (wanted, reached)
    # the view's keys do not scroll the page while it has the focus
    page.focus("#view")
    before = page.evaluate("() => window.scrollY")
    page.keyboard.press("ArrowDown")
    assert page.evaluate("() => window.scrollY") == before


def test_the_view_turns_by_keyboard_and_mouse_and_resets(web: Page) -> None:
    page = web.page
    web.choose(shared_mesh_path("spot.obj"))
    web.wait_preview()
    page.focus("#view")
    _, _, start = web.view_pixels()

    def after(action: Any) -> bytes:
        action()
        page.wait_for_timeout(200)  # a few animation frames
        return web.view_pixels()[2]

    assert after(lambda: [page.keyboard.press("ArrowLeft") for _ in range(4)]) != start
    assert after(lambda: page.keyboard.press("0")) == start
    assert after(lambda: page.keyboard.press("+")) != start
    page.keyboard.press("Home")
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2

    def drag() -> None:
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + 120, y + 30, steps=5)
        page.mouse.up()

    assert after(drag) != start


def test_large_files_go_through_a_job_with_a_progress_bar(web: Page, server: Server) -> None:
    page = web.page
    web.choose(shared_mesh_path("bun_zipper.ply"))
    assert not page.is_checked("#background")  # 2.9 MB: below the threshold
    page.check("#background")
    page.fill("#key", KEY)
    page.click("#embed-form button")
    page.wait_for_selector("#progress-wrap", state="visible")
    page.wait_for_selector("#download")
    assert page.locator("#progress-wrap").is_hidden()
    jobs = [url for url in web.requests if "/v1/jobs/" in url and "auth-check" not in url]
    assert jobs[0].endswith("/v1/jobs/embed") and any(url.endswith("/result") for url in jobs)
    log = server.text()
    assert "POST /v1/jobs/embed 202" in log and "DELETE /v1/jobs/{job_id} 204" in log


def test_a_large_file_is_sent_as_a_job_by_itself(web: Page) -> None:
    page = web.page
    threshold = int(page.get_attribute("body", "data-job-threshold") or 0)
    points = b"v 0 0 0\n" * (threshold // 8 + 1)  # just above the threshold (and no triangle)
    web.choose({"name": "points.obj", "mimeType": "model/obj", "buffer": points})
    assert page.is_checked("#background")
    page.wait_for_selector("#view-msg:has-text('No preview')")
    assert "The mesh cannot carry a watermark" in page.inner_text("#view-msg")


def test_without_webgl_the_page_says_so_and_still_works(playwright: Any, server: Server) -> None:
    browser = launch(playwright, "--disable-3d-apis")
    try:
        web = Page(browser, server.base)
        page = web.page
        assert not web.webgl()
        assert "cannot draw the 3-D preview" in page.inner_text("#view-msg")
        assert page.locator("#view").is_hidden()
        web.choose(shared_mesh_path("spot.obj"))
        page.click("#capacity-form button")
        page.wait_for_selector("#result h3")
        assert page.inner_text("#result h3") == "Capacity"
        assert "vertices can carry a bit" in page.inner_text("#result")
        assert not any(url.endswith("/v1/preview") for url in web.requests)  # nothing it cannot draw
        web.close()
    finally:
        browser.close()


def test_webgl1_draws_the_same_model(playwright: Any, server: Server) -> None:
    browser = launch(playwright, "--disable-webgl2")
    try:
        web = Page(browser, server.base)
        assert web.page.evaluate("() => !document.createElement('canvas').getContext('webgl2')")
        web.choose(shared_mesh_path("spot.obj"))
        web.wait_preview()
        drawn, heat, _ = web.view_pixels()
        assert drawn > 20_000 and heat == 0
        web.close()
    finally:
        browser.close()


def test_with_api_keys_the_page_asks_for_one(playwright: Any, browser: Any,
                                             tmp_path_factory: pytest.TempPathFactory) -> None:
    with serve(tmp_path_factory.mktemp("web-keys") / "server.log", api_keys="page-key-1-0123456789") as keyed:
        web = Page(browser, keyed.base)
        page = web.page
        page.wait_for_selector("#apikey-section", state="visible")
        assert page.get_attribute("#apikey", "type") == "password"
        web.choose(shared_mesh_path("spot.obj"))
        page.wait_for_selector("#view-msg:has-text('Missing or invalid API key')")
        page.fill("#key", KEY)
        page.click("#embed-form button")
        page.wait_for_selector("#error", state="visible")
        assert page.inner_text("#error-title") == "Missing or invalid API key"
        assert page.evaluate("() => document.activeElement.id") == "apikey"

        page.fill("#apikey", "page-key-1-0123456789")
        page.click("#embed-form button")
        page.wait_for_selector("#download")
        web.wait_preview(heat=True)
        assert page.is_hidden("#error")
        page.click("#check-marked")  # the marked file straight from memory, with the API key
        page.wait_for_selector("#result h3:has-text('Watermark found')")
        assert page.evaluate("() => [localStorage.length, sessionStorage.length]") == [0, 0]
        web.close()


def test_files_too_large_to_compare_show_the_marked_one_alone(
        browser: Any, tmp_path_factory: pytest.TempPathFactory) -> None:
    bunny = shared_mesh_path("bun_zipper.ply")  # 3.0 MB, marked 3.2 MB: one fits the limit, both do not
    limit = str(4 * 1024 * 1024)
    with serve(tmp_path_factory.mktemp("web-small") / "server.log", max_upload_bytes=limit) as small:
        web = Page(browser, small.base)
        page = web.page
        web.choose(bunny)
        web.wait_preview()
        page.fill("#key", KEY)
        page.click("#embed-form button")
        page.wait_for_selector("#download")
        page.wait_for_selector("#view-msg:has-text('No heat map')")
        assert page.get_attribute("#view", "data-heat") == "off"
        assert "35,947 vertices" in page.inner_text("#view-msg")
        assert page.is_hidden("#legend")
        web.close()
