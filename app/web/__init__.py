"""The page for people at ``/``: mark, check and look at a mesh in the browser.

Everything it needs ships in ``static/`` (package data, a few hand-written files) and is served
by this router: the page loads nothing from any other host, which its Content-Security-Policy
enforces.  Assets are served under names that carry a hash of their content, cached for a year
as immutable; the page itself is revalidated on every load (``no-cache`` + ``ETag``), so a new
release is picked up at once.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from importlib import resources

from fastapi import APIRouter, Request, Response
from starlette.exceptions import HTTPException

#: media type of each asset kind
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
}

#: this server only, for scripts, styles, images and requests alike
CONTENT_SECURITY_POLICY = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
                           "connect-src 'self'; form-action 'none'; base-uri 'none'; frame-ancestors 'none'")
SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}
IMMUTABLE = "public, max-age=31536000, immutable"


@dataclass(frozen=True)
class Asset:
    body: bytes
    media_type: str
    etag: str
    cache_control: str


def _etag(body: bytes) -> str:
    return '"' + hashlib.sha256(body).hexdigest()[:16] + '"'


def _load() -> tuple[Asset, dict[str, Asset]]:
    """The rendered page and the assets by their hashed name (``app.3f2a9c1d0b7e.js``)."""
    folder = resources.files(__name__) / "static"
    assets: dict[str, Asset] = {}
    urls: dict[str, str] = {}
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        stem, dot, ext = entry.name.rpartition(".")
        if entry.name == "index.html" or not dot or "." + ext not in MEDIA_TYPES:
            continue
        body = entry.read_bytes()
        hashed = f"{stem}.{hashlib.sha256(body).hexdigest()[:12]}.{ext}"
        assets[hashed] = Asset(body, MEDIA_TYPES["." + ext], _etag(body), IMMUTABLE)
        urls[entry.name] = f"/web/{hashed}"
    template = (folder / "index.html").read_text(encoding="utf-8")
    page = re.sub(r"\{\{([\w.-]+)\}\}", lambda m: urls[m.group(1)], template).encode()
    return Asset(page, MEDIA_TYPES[".html"], _etag(page), "no-cache"), assets


PAGE, ASSETS = _load()

router = APIRouter(include_in_schema=False)


def _serve(asset: Asset, request: Request) -> Response:
    headers = {"ETag": asset.etag, "Cache-Control": asset.cache_control, **SECURITY_HEADERS}
    if asset.etag in request.headers.get("if-none-match", ""):
        return Response(status_code=304, headers=headers)
    return Response(asset.body, media_type=asset.media_type, headers=headers)


@router.api_route("/", methods=["GET", "HEAD"])
async def page(request: Request) -> Response:
    return _serve(PAGE, request)


@router.api_route("/web/{name}", methods=["GET", "HEAD"])
async def asset(name: str, request: Request) -> Response:
    found = ASSETS.get(name)
    if found is None:
        raise HTTPException(404, "no such file")
    return _serve(found, request)
