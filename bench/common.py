"""Shared helpers of the benchmark suites: meshes, writers, engine calls, report headers.

The suites call the engine only through its public entry points (:func:`core.api.embed_file`,
:func:`core.api.detect_file`, :func:`core.api.capacity_file` and :func:`core.formats.read_mesh`),
exactly as a user of the CLI or the service would, and feed it *files* (bytes).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import os
import platform
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tests.shared import meshes_dir as shared_meshes_dir

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "bench" / "results"
KEY = "meshmark-bench-key"
METHODS = ("ellipsoids", "planes")

#: Shared meshes in order of size (vertices after welding, from shared/meshes/README.md).
SHARED_MESHES = [
    "teapot.stl",
    "monkey.glb",
    "sink.3ds",
    "spot.obj",
    "Duck.glb",
    "CesiumMilkTruck.glb",
    "decimated-max.obj",
    "fandisk.off",
    "rocker-arm.obj",
    "beetle.off",
    "bun_zipper.ply",
    "armadillo.obj",
    "horse.ply",
    "dragon.ply",
    "turbineblade.ply",
]
#: Small meshes for the quick slices and the false-positive runs.
QUICK_MESHES = ["sink.3ds", "spot.obj", "fandisk.off"]
SMALL_MEDIUM_MESHES = [
    "teapot.stl",
    "monkey.glb",
    "sink.3ds",
    "spot.obj",
    "Duck.glb",
    "decimated-max.obj",
    "fandisk.off",
]


def json_child(module: str, args: list[str], timeout: float) -> dict[str, Any]:
    """Run ``python -m module *args`` in a fresh process from the repository root and return the
    JSON object on the last line of its output (``{"error": last stderr line}`` when it fails)."""
    p = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, cwd=ROOT,
                       timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT)})
    if p.returncode != 0:
        return {"error": (p.stderr.strip().splitlines() or ["?"])[-1][:300]}
    lines = p.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines else {}


_TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICK


def child_pids(pid: int, recursive: bool = False) -> list[int]:
    """Child processes of ``pid`` (all descendants when ``recursive``), whichever of its threads
    started them."""
    kids = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            continue
    return kids + [g for k in kids for g in child_pids(k, True)] if recursive else kids


def meshes_dir() -> Path:
    """Directory of the shared meshes (:func:`tests.shared.meshes_dir`: ``$MESHMARK_TEST_MESHES``,
    the setting the tests read)."""
    return shared_meshes_dir()


def mesh_path(name: str) -> Path:
    return meshes_dir() / name


def available_meshes(names: list[str] | None = None) -> list[str]:
    """Names of the requested (default: all shared) meshes that exist on this machine."""
    wanted = names if names else SHARED_MESHES
    return [n for n in wanted if mesh_path(n).is_file()]


def engine_ready() -> bool:
    """True when the engine implementation (``core/pipeline.py``) is importable."""
    try:
        import core.pipeline  # noqa: F401
    except ImportError:
        return False
    return True


# ---------------------------------------------------------------------------------------------
# meshes as arrays


@dataclass
class Mesh:
    """All parts of a file merged into one array pair (faces offset per part, no welding)."""

    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    parts: list[tuple[np.ndarray, np.ndarray]]
    names: list[str]

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)


def merge_parts(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(np.asarray(v, np.float64))
        fs.append(np.asarray(f, np.int64) + off)
        off += len(v)
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vs), np.concatenate(fs)


def load_mesh(data: bytes, filename: str) -> Mesh:
    """Parse a file with the engine's own reader (the same welding the engine sees)."""
    from core.formats import read_mesh

    doc = read_mesh(data, filename)
    parts = [(p.vertices, p.faces) for p in doc.parts]
    v, f = merge_parts(parts)
    return Mesh(v, f, parts, [p.name for p in doc.parts])


def load_mesh_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Fallback reader through trimesh (used only where the engine's readers are not needed)."""
    import trimesh

    scene = trimesh.load(str(path), force="scene", process=False)
    mesh = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


# ---------------------------------------------------------------------------------------------
# writers for attacked meshes (topology changes, so the engine's patching writer cannot be used)


def write_ply_double(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """Binary little-endian PLY with ``double`` coordinates: no quantisation added by the writer."""
    v = np.ascontiguousarray(vertices, dtype="<f8").reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment meshmark bench\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    rec = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    return header + v.tobytes() + rec.tobytes()


def write_obj(parts: list[tuple[np.ndarray, np.ndarray]], names: list[str] | None = None) -> bytes:
    """OBJ with ``%.17g`` coordinates (exact round trip of float64), one ``o`` per part."""
    out = io.StringIO()
    out.write("# meshmark bench\n")
    base = 1
    for k, (v, f) in enumerate(parts):
        out.write(f"o {names[k] if names else f'part{k}'}\n")
        np.savetxt(out, np.asarray(v, np.float64), fmt="v %.17g %.17g %.17g")
        np.savetxt(out, np.asarray(f, np.int64) + base, fmt="f %d %d %d")
        base += len(v)
    return out.getvalue().encode("ascii")


def parse_ply_double(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`write_ply_double` (for tests and sanity checks only)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").split("\n")
    nv = int(next(h for h in head if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in head if h.startswith("element face")).split()[-1])
    v = np.frombuffer(data, "<f8", nv * 3, end).reshape(nv, 3)
    rec = np.frombuffer(data, [("n", "u1"), ("i", "<i4", (3,))], nf, end + nv * 24)
    return v.copy(), rec["i"].astype(np.int64)


# ---------------------------------------------------------------------------------------------
# payloads and bit comparisons


def random_payload(rng: np.random.Generator, bits: int = 64) -> str:
    return "".join("1" if b else "0" for b in rng.integers(0, 2, bits))


def bit_error_rate(found: str | None, truth: str) -> float:
    """Fraction of wrong bits; a missing or wrong-length payload counts as chance (0.5)."""
    if not found or len(found) != len(truth):
        return 0.5
    a = np.frombuffer(found.encode(), np.uint8)
    b = np.frombuffer(truth.encode(), np.uint8)
    return float(np.mean(a != b))


# ---------------------------------------------------------------------------------------------
# environment and report headers


def versions() -> dict[str, str]:
    import numpy
    import scipy
    import trimesh

    out = {
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "trimesh": trimesh.__version__,
    }
    try:
        import fast_simplification

        out["fast_simplification"] = getattr(fast_simplification, "__version__", "?")
    except ImportError:
        pass
    return out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"


def environment() -> dict[str, Any]:
    mem = None
    with contextlib.suppress(ValueError, OSError, AttributeError):
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "memory_gib": round(mem, 1) if mem else None,
        "versions": versions(),
        "command": "python -m bench " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "git": git_revision(),
    }


def git_revision() -> str:
    try:  # git itself knows worktrees (where .git is a file) and packed refs
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10)
        if out.returncode == 0:
            return out.stdout.strip()[:12]
    except (OSError, subprocess.SubprocessError):
        pass
    head = ROOT / ".git" / "HEAD"
    try:
        ref = head.read_text().strip()
        if ref.startswith("ref:"):
            path = ROOT / ".git" / ref.split(" ", 1)[1]
            if path.is_file():
                return path.read_text().strip()[:12]
            packed = ROOT / ".git" / "packed-refs"
            for line in packed.read_text().splitlines() if packed.is_file() else []:
                if line.endswith(ref.split(" ", 1)[1]):
                    return line.split()[0][:12]
        return ref[:12]
    except OSError:
        return "?"


def header(title: str, env: dict[str, Any], extra: list[str] | None = None) -> str:
    v = env["versions"]
    lines = [
        f"# {title}",
        "",
        f"- Date: {env['date']}",
        f"- Machine: {env['platform']}, {env['cpu']}, {env['cpu_count']} CPUs"
        + (f", {env['memory_gib']} GiB RAM" if env.get("memory_gib") else ""),
        f"- Python {v['python']}, numpy {v['numpy']}, scipy {v['scipy']}, trimesh {v['trimesh']}"
        + (f", fast-simplification {v['fast_simplification']}" if "fast_simplification" in v else ""),
        f"- Code: git {env['git']} (plus uncommitted changes, if any)",
        f"- Command: `{env['command']}`",
    ]
    lines += extra or []
    return "\n".join(lines) + "\n"


def md_table(headers: list[str], rows: list[list[Any]], align: str | None = None) -> str:
    """Markdown table; ``align`` is one letter per column (``l``/``r``)."""
    align = align or "l" + "r" * (len(headers) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    out = ["| " + " | ".join(headers) + " |", "| " + " | ".join(sep) + " |"]
    for r in rows:
        out.append("| " + " | ".join(fmt_cell(c) for c in r) + " |")
    return "\n".join(out) + "\n"


def fmt_cell(c: Any) -> str:
    if c is None:
        return "–"
    if isinstance(c, bool):
        return "yes" if c else "no"
    if isinstance(c, float):
        if c != c:
            return "–"
        if c == 0:
            return "0"
        if abs(c) >= 1000:
            return f"{c:,.0f}"
        if abs(c) >= 0.01:
            return f"{c:.3g}" if abs(c) < 100 else f"{c:.1f}"
        return f"{c:.2e}"
    if isinstance(c, int):
        return f"{c:,}"
    return str(c)


def save_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, default=_json_default))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))
