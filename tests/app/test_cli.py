"""``meshmark`` embed / detect / capacity on files and pipes, with the documented exit codes."""

from __future__ import annotations

import importlib.metadata
import json
import os
import socket
import subprocess
from typing import Any

import pytest

import meshmark
from app.cli import EXIT_NOT_DETECTED, EXIT_OK, EXIT_USAGE, main
from tests.app.conftest import KEY
from tests.app.real_server import MESHMARK
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


def test_version(capsys):
    code, out, _ = run(capsys, "--version")
    assert code == EXIT_OK and out.strip() == f"meshmark {meshmark.__version__}"
    assert meshmark.__version__ == importlib.metadata.version("meshmark")


def test_an_output_named_for_another_format_is_refused(capsys, tmp_path, spot):
    """The marked file keeps the input's format: `embed x.obj out.ply` would write OBJ text into a
    .ply file, so it is refused before any work, with the extension to use."""
    out_path = tmp_path / "spot.marked.ply"
    code, out, err = run(capsys, "embed", str(spot), str(out_path), "--key", KEY)
    assert code == EXIT_USAGE and out == "" and not out_path.exists()
    assert "name the output .obj" in err


def _meshmark(*args: str, stdin: bytes = b"", env: dict[str, str] | None = None) -> Any:
    return subprocess.run([str(MESHMARK), *args], input=stdin, capture_output=True, timeout=120,
                          env={**os.environ, **(env or {})})


def test_dash_reads_stdin_and_writes_stdout(tmp_path, spot):
    """`meshmark embed - - < in > out`: the mesh through the pipes, the report on stderr; the bytes
    are those of the same embedding written to a file."""
    source = spot.read_bytes()
    piped = _meshmark("embed", "-", "-", "--key", KEY, stdin=source)
    assert piped.returncode == 0, piped.stderr
    report = json.loads(piped.stderr.decode().strip().splitlines()[-1])
    assert report["carriers"] > 0
    on_disk = _meshmark("embed", str(spot), str(tmp_path / "m.obj"), "--key", KEY)
    assert on_disk.returncode == 0 and json.loads(on_disk.stdout) == report
    assert piped.stdout == (tmp_path / "m.obj").read_bytes() != source
    found = _meshmark("detect", "-", "--key", KEY, stdin=piped.stdout)
    assert found.returncode == EXIT_OK and json.loads(found.stdout)["detected"] is True
    empty = _meshmark("detect", "-", "--key", KEY, stdin=b"")
    assert empty.returncode == EXIT_USAGE and b"the file is empty" in empty.stderr


def test_invalid_settings_are_usage_errors_without_traceback():
    bad_level = _meshmark("serve", env={"MESHMARK_LOG_LEVEL": "loud"})
    assert bad_level.returncode == EXIT_USAGE, bad_level.stderr
    assert b"log_level" in bad_level.stderr and b"Traceback" not in bad_level.stderr


def test_a_port_in_use_is_a_usage_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        busy = _meshmark("serve", "--port", str(port))
    assert busy.returncode == EXIT_USAGE, busy.stderr
    assert f"cannot listen on 127.0.0.1:{port}".encode() in busy.stderr and b"Traceback" not in busy.stderr


def test_capacity_with_the_key_counts_the_embedding_carriers(capsys, tmp_path, spot, monkeypatch):
    monkeypatch.delenv("MESHMARK_KEY", raising=False)
    _, out, _ = run(capsys, "embed", str(spot), str(tmp_path / "m.obj"), "--key", KEY)
    carriers = json.loads(out)["carriers"]
    _, out, _ = run(capsys, "capacity", str(spot), "--key", KEY)
    assert json.loads(out)["carriers"] == carriers
    monkeypatch.setenv("MESHMARK_KEY", KEY)
    _, out, _ = run(capsys, "capacity", str(spot))
    assert json.loads(out)["carriers"] == carriers


def test_copy_and_trace(capsys, tmp_path, monkeypatch):
    """`meshmark copy` records each recipient's copy in the registry of the settings; `meshmark
    trace` names the one that leaked (exit 0) and no one for the cover (exit 1)."""
    monkeypatch.setenv("MESHMARK_REGISTRY_PATH", str(tmp_path / "copies.sqlite3"))
    cover = tmp_path / "rocker.obj"
    cover.write_bytes(shared_mesh_path("rocker-arm.obj").read_bytes())
    for who in ("alice", "bob"):
        code, out, err = run(capsys, "copy", str(cover), str(tmp_path / f"{who}.obj"), "--key", KEY,
                             "--recipient", who, "--asset-id", "rocker")
        assert code == EXIT_OK, err
        issued = json.loads(out)
        assert issued["asset_id"] == "rocker" and issued["recipient"] == who and issued["score"] > 8
    code, out, _ = run(capsys, "trace", str(tmp_path / "bob.obj"), "--key", KEY, "--asset-id", "rocker")
    assert code == EXIT_OK and json.loads(out)["accused"] == ["bob"]
    code, out, _ = run(capsys, "trace", str(cover), "--key", KEY)
    assert code == EXIT_NOT_DETECTED and json.loads(out)["verdict"] == "no-one"
    code, _, err = run(capsys, "trace", str(cover), "--key", KEY, "--asset-id", "other")
    assert code == EXIT_USAGE and "no copies" in err
    code, _, err = run(capsys, "copy", str(cover), str(tmp_path / "a2.obj"), "--key", KEY, "--recipient",
                       "alice", "--asset-id", "rocker", "--method", "planes")
    assert code == EXIT_USAGE and "ellipsoids" in err
