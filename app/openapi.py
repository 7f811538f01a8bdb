"""The OpenAPI document as committed in ``openapi/openapi.json``.

Regenerate after changing a route: ``.venv/bin/python scripts/export_openapi.py``
(or ``python -m app.openapi``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from app.config import Settings
from app.main import create_app

OPENAPI_PATH = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def render_openapi() -> str:
    """The document of an app with default settings (the document does not depend on them)."""
    document = create_app(Settings.model_construct()).openapi()  # defaults, not the environment
    return json.dumps(document, sort_keys=True, indent=2, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    path = Path(argv[0]) if argv else OPENAPI_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render_openapi(), encoding="utf-8")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
