"""How far an attack moves the geometric layer's frame, in cells of the mesh's own rung.

    .venv/bin/python -m bench.frameshift [--meshes NAME ...] [--seed 1]

For every mesh (default: the shared meshes of >= 10k vertices) the surface frame
(:func:`core.geosync.surface_frame`) of the mesh as read, and of the mesh after each attack of
:data:`ATTACKS`: the shift of the area centroid, the relative change of ``rho`` and the largest
turn of an axis (of the detector's candidate rotation nearest the original), each divided by the
cell size of the rung the embedder would choose (a shift of a good fraction of a cell changes
which vertex is nearest most cells' centres), and the change of the surface's area; then the same
shifts for a frame weighted by enclosed volume instead of area (:func:`volume_frame`, not used by
the engine: what a frame that roughening leaves alone would give; each mesh's own area centroid
is the origin of its cones, as a blind detector would have it; its axes column means nothing for
a degenerate pair, the gear's and the counter's, whose angle the engine takes from the angular
spectrum).  Prints a markdown table; nothing
is written.  ``core/README.md``, the speed section: the area weights are
what moves.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.attacks import simplify, simplify_meshopt, uniform_noise
from bench.common import load_mesh, md_table, mesh_path

MESHES = ["rocker-arm.obj", "beetle.off", "bun_zipper.ply", "armadillo.obj", "horse.ply", "dragon.ply",
          "turbineblade.ply", "cycloidal.ply", "counter.unitsmm.STL"]
ATTACKS = [("noise 0.1 %", uniform_noise, 0.001), ("noise 0.3 %", uniform_noise, 0.003),
           ("quadric 30 %", simplify, 0.3), ("meshopt 10 %", simplify_meshopt, 0.1)]


def volume_frame(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray
                 ) -> tuple[float, np.ndarray, float, np.ndarray]:
    """Volume, centroid, RMS radius and principal axes (rows, largest moment first) of the solid the
    surface encloses, as the sum of the signed cones from ``origin`` over its faces (exact for a
    closed surface, whatever the origin; an open one depends on it)."""
    a, b, c = (vertices[faces[:, k]] - origin for k in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    s = a + b + c
    total = float(vol.sum())
    mean = (vol[:, None] * s).sum(axis=0) / 4.0 / total
    # the integral of x x^T over a cone with apex at the origin: V / 20 (sum p_i p_i^T + s s^T)
    second = sum((q * vol[:, None]).T @ q for q in (a, b, c, s)) / 20.0 / total - np.outer(mean, mean)
    lam, vec = np.linalg.eigh(second)
    return total, origin + mean, float(np.sqrt(max(float(lam.sum()), 0.0))), vec[:, ::-1].T


def shift(name: str, seed: int) -> list[list[str]]:
    from core import geosync
    from core.analysis import prepare

    mesh = load_mesh(mesh_path(name).read_bytes(), name)
    v, f = mesh.vertices, mesh.faces
    frame = geosync.surface_frame(v, f)
    if frame is None:
        return [[name, "-", "no frame"] + [""] * 7]
    (adj, _), = prepare([v], [f])
    rung, _ = geosync.choose_rung(v, adj, frame, frame.axes, "frameshift")
    h = geosync.rung_size(rung)
    vol0, vc0, vr0, vax0 = volume_frame(v, f, frame.centroid)
    rows = []
    for label, attack, level in ATTACKS:
        va, fa = attack(v, f, level, np.random.default_rng(seed))
        got = geosync.surface_frame(va, fa)
        if got is None:
            rows.append([name, str(rung), label, "no frame"] + [""] * 6)
            continue
        centroid = np.linalg.norm(got.centroid - frame.centroid) / frame.rho / h
        rho = abs(got.rho / frame.rho - 1.0) / h
        # the detector's candidate rotation nearest the original axes (a degenerate pair's turn)
        axes = max(geosync.frame_candidates(got), key=lambda r: float(np.trace(r @ frame.axes.T)))
        cos = float(np.abs((axes * frame.axes).sum(axis=1)).min())
        turn = np.sqrt(max(0.0, 2.0 * (1.0 - cos))) / h
        vol, vc, vr, vax = volume_frame(va, fa, got.centroid)
        vcos = float(np.abs((vax * vax0).sum(axis=1)).min())
        rows.append([name, str(rung), label, f"{centroid:.3f}", f"{rho:.3f}", f"{turn:.3f}",
                     f"{got.area / frame.area - 1.0:+.2%}",
                     f"{np.linalg.norm(vc - vc0) / frame.rho / h:.3f}", f"{abs(vr / vr0 - 1.0) / h:.3f}",
                     f"{np.sqrt(max(0.0, 2.0 * (1.0 - vcos))) / h:.3f}", f"{vol / vol0 - 1.0:+.2%}"])
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.frameshift", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="+", metavar="NAME", default=MESHES,
                   help="shared mesh file names (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="seed of the random attacks (default: %(default)s)")
    a = p.parse_args(argv)
    rows = [r for name in a.meshes if mesh_path(name).exists() for r in shift(name, a.seed)]
    headers = ["mesh", "rung", "attack", "centroid (cells)", "rho (cells)", "axes (cells)", "area",
               "volume frame: centroid", "rho", "axes", "volume"]
    print(md_table(headers, rows))


if __name__ == "__main__":
    main()
