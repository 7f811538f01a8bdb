"""How far an attack moves the geometric layer's frame, in cells of the mesh's own rung.

    .venv/bin/python -m bench.frameshift [--meshes NAME ...] [--seed 1]

For every mesh (default: the shared meshes of >= 10k vertices) the surface frame
(:func:`core.geosync.surface_frame`) of the mesh as read, and of the mesh after each attack of
:data:`ATTACKS`: the shift of the area centroid, the relative change of ``rho`` and the largest
turn of an axis (of the detector's candidate rotation nearest the original), each divided by the
cell size of the rung the embedder would choose (a shift of a good fraction of a cell changes
which vertex is nearest most cells' centres), and the change of the surface's area.  Prints a
markdown table; nothing is written.  ``core/README.md``, the speed section: the area weights are
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


def shift(name: str, seed: int) -> list[list[str]]:
    from core import geosync
    from core.analysis import prepare

    mesh = load_mesh(mesh_path(name).read_bytes(), name)
    v, f = mesh.vertices, mesh.faces
    frame = geosync.surface_frame(v, f)
    if frame is None:
        return [[name, "-", "no frame", "", "", "", ""]]
    (adj, _), = prepare([v], [f])
    rung, _ = geosync.choose_rung(v, adj, frame, frame.axes, "frameshift")
    h = geosync.rung_size(rung)
    rows = []
    for label, attack, level in ATTACKS:
        va, fa = attack(v, f, level, np.random.default_rng(seed))
        got = geosync.surface_frame(va, fa)
        if got is None:
            rows.append([name, str(rung), label, "no frame", "", "", ""])
            continue
        centroid = np.linalg.norm(got.centroid - frame.centroid) / frame.rho / h
        rho = abs(got.rho / frame.rho - 1.0) / h
        # the detector's candidate rotation nearest the original axes (a degenerate pair's turn)
        axes = max(geosync.frame_candidates(got), key=lambda r: float(np.trace(r @ frame.axes.T)))
        cos = float(np.abs((axes * frame.axes).sum(axis=1)).min())
        turn = np.sqrt(max(0.0, 2.0 * (1.0 - cos))) / h
        rows.append([name, str(rung), label, f"{centroid:.3f}", f"{rho:.3f}", f"{turn:.3f}",
                     f"{got.area / frame.area - 1.0:+.2%}"])
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.frameshift", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="+", metavar="NAME", default=MESHES,
                   help="shared mesh file names (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="seed of the random attacks (default: %(default)s)")
    a = p.parse_args(argv)
    rows = [r for name in a.meshes if mesh_path(name).exists() for r in shift(name, a.seed)]
    headers = ["mesh", "rung", "attack", "centroid (cells)", "rho (cells)", "axes (cells)", "area"]
    print(md_table(headers, rows))


if __name__ == "__main__":
    main()
