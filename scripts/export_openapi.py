#!/usr/bin/env python
"""Write openapi/openapi.json from the app (tests/app/test_openapi.py fails when it drifts)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.openapi import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
