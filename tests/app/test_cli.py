"""``meshmark`` embed / detect / capacity on files, with the documented exit codes."""

from __future__ import annotations

import json

import pytest

from app.cli import EXIT_NOT_DETECTED, EXIT_OK, EXIT_USAGE, main
from tests.app.conftest import KEY
from tests.conftest import shared_mesh_path


def run(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def spot(tmp_path):
    path = tmp_path / "spot.obj"
    path.write_bytes(shared_mesh_path("spot.obj").read_bytes())
    return path


def test_embed_detect_capacity(capsys, tmp_path, spot, monkeypatch):
    out_path = tmp_path / "spot.marked.obj"
    code, out, _ = run(capsys, "embed", str(spot), str(out_path), "--key", KEY, "--payload", "101100")
    assert code == EXIT_OK
    report = json.loads(out)
    assert report["payload_bits"] == 6 and report["carriers"] > 0
    assert out_path.read_bytes() != spot.read_bytes()

    key_file = tmp_path / "key.txt"
    key_file.write_text(KEY + "\n")  # the trailing newline is ignored
    code, out, _ = run(capsys, "detect", str(out_path), "--key-file", str(key_file))
    assert code == EXIT_OK
    found = json.loads(out)
    assert found["detected"] is True and found["payload"] == "101100"

    monkeypatch.setenv("MESHMARK_KEY", "not the key")
    code, out, _ = run(capsys, "detect", str(out_path))
    assert code == EXIT_NOT_DETECTED and json.loads(out)["detected"] is False

    code, out, _ = run(capsys, "capacity", str(spot), "--method", "planes")
    assert code == EXIT_OK and json.loads(out)["method"] == "planes"


@pytest.mark.parametrize("argv", [
    ["detect", "{spot}"],                                      # no key anywhere
    ["detect", "{spot}", "--key", ""],                         # empty key
    ["embed", "{spot}", "{out}", "--key", "k", "--payload", "12"],
    ["embed", "{spot}", "{out}", "--key", "k", "--strength", "-1"],
    ["detect", "{missing}", "--key", "k"],                     # unreadable input
    ["detect", "{jpeg}", "--key", "k"],                        # not a mesh
    ["detect", "{spot}", "--key-file", "{missing}"],
])
def test_bad_input_exits_2(capsys, tmp_path, spot, monkeypatch, argv):
    monkeypatch.delenv("MESHMARK_KEY", raising=False)
    jpeg = tmp_path / "photo.obj"
    jpeg.write_bytes(b"\xff\xd8\xff\xe0" + bytes(64))
    paths = {"spot": spot, "out": tmp_path / "o.obj", "missing": tmp_path / "none.obj", "jpeg": jpeg}
    code, out, err = run(capsys, *[a.format(**paths) for a in argv])
    assert code == EXIT_USAGE
    assert out == "" and err.startswith("meshmark: error: ")


def test_usage_errors_exit_2(capsys, spot):
    assert run(capsys, "embed", str(spot))[0] == EXIT_USAGE  # argparse: missing OUT
    assert run(capsys, "detect", str(spot), "--key", "a", "--key-file", "b")[0] == EXIT_USAGE
    assert run(capsys, "frobnicate")[0] == EXIT_USAGE
    code, _, err = run(capsys, "serve", "--port", "99999")  # refused before anything starts
    assert code == EXIT_USAGE and "port" in err
