"""The page at ``/`` and its assets over HTTP: types, caching, security headers, no other host.
(The page in a real browser: ``test_web_e2e.py``.)"""

from __future__ import annotations

import hashlib
import re
from importlib import resources

from app.web import ASSETS, CONTENT_SECURITY_POLICY
from tests.app.conftest import assert_problem, make_client

EXPECTED_TYPES = {".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8",
                  ".svg": "image/svg+xml"}


def asset_urls(html: str) -> list[str]:
    return re.findall(r'(?:src|href)="(/web/[^"]+)"', html)


def test_page_is_served_at_the_root_with_its_headers(client):
    response = client.get("/")
    assert response.status_code == 200
    assert response.headers["content-type"] == "text/html; charset=utf-8"
    assert response.headers["cache-control"] == "no-cache"
    assert response.headers["content-security-policy"] == CONTENT_SECURITY_POLICY
    assert response.headers["x-content-type-options"] == "nosniff"
    assert "<h1>MeshMark</h1>" in response.text and "{{" not in response.text
    again = client.get("/", headers={"If-None-Match": response.headers["etag"]})
    assert again.status_code == 304 and again.content == b""
    assert client.head("/").status_code == 200


def test_every_asset_the_page_names_is_served_immutable_with_its_type(client):
    urls = asset_urls(client.get("/").text)
    assert {url.rsplit(".", 1)[-1] for url in urls} == {"js", "css", "svg"}
    for url in urls:
        response = client.get(url)
        assert response.status_code == 200, url
        assert response.headers["content-type"] == EXPECTED_TYPES["." + url.rsplit(".", 1)[-1]]
        assert response.headers["cache-control"] == "public, max-age=31536000, immutable"
        assert response.headers["x-content-type-options"] == "nosniff"
        assert client.get(url, headers={"If-None-Match": response.headers["etag"]}).status_code == 304


def test_asset_names_change_with_their_content():
    for name, asset in ASSETS.items():
        digest = name.rsplit(".", 2)[1]
        assert hashlib.sha256(asset.body).hexdigest().startswith(digest)


def test_unknown_assets_are_404_problems(client):
    for url in ("/web/app.js", "/web/../main.py", "/web/app.000000000000.js"):
        response = client.get(url)
        assert response.status_code == 404
        assert response.headers["content-type"] == "application/problem+json"


def test_the_page_names_no_other_host():
    folder = resources.files("app.web") / "static"
    for entry in folder.iterdir():
        text = entry.read_text(encoding="utf-8")
        hosts = re.findall(r"(?:https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, flags=re.I)
        assert hosts in ([], ["http://www.w3.org"]), (entry.name, hosts)  # the SVG namespace is a name


def test_page_is_open_while_the_api_wants_a_key():
    with make_client(api_keys="k1-0123456789abcdef") as client:
        assert client.get("/").status_code == 200
        for url in asset_urls(client.get("/").text):
            assert client.get(url).status_code == 200
        # how the page finds out that it must ask for an API key
        assert_problem(client.get("/v1/jobs/auth-check"), 401, "unauthorized")
        assert_problem(client.get("/v1/jobs/auth-check", headers={"X-API-Key": "k1-0123456789abcdef"}), 404,
                       "not-found")


def test_page_is_not_in_the_api_document(client):
    paths = client.get("/openapi.json").json()["paths"]
    assert "/" not in paths and not any(p.startswith("/web") for p in paths)
    assert "/v1/preview" in paths
