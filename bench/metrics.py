"""Distortion and detection metrics.

Surface distances
-----------------
``point_surface_distance`` is exact (up to float rounding): for each query point the closest
triangle is found with scipy cKDTrees over triangle centroids, one tree per size class of
triangles (size = largest centroid-to-corner distance R), then the exact point-triangle distance
(``trimesh.triangles.closest_point``) is evaluated on the candidates.  A triangle of class c can
only be closer than the best distance u found so far if its centroid lies within ``u + R_c``
(R_c = largest R of the class), so every class is queried with more neighbours until its k-th
centroid is farther than that: the search is a proof, not a heuristic.  (trimesh's own
``proximity.closest_point`` needs rtree, which is not installed.)

MRMS and Hausdorff sample each surface with ``trimesh.sample.sample_surface`` (area-uniform,
seeded); RMS uses those samples only; Hausdorff additionally uses the vertices that faces use,
where the largest deviations of vertex-displacement schemes are.  Both are divided by the bounding-box
diagonal of the first (original) mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


class SurfaceIndex:
    """Nearest-triangle queries on one triangle mesh."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, n_classes: int = 8) -> None:
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        tri = self.vertices[self.faces]
        self.triangles = tri
        cen = tri.mean(axis=1)
        rad = np.linalg.norm(tri - cen[:, None, :], axis=2).max(axis=1)
        # size classes: geometric bins of the radius, so each class's R_c is within 2x of its members
        rmax = float(rad.max()) if len(rad) else 0.0
        edges = rmax / 2.0 ** np.arange(n_classes)[::-1] if rmax > 0 else np.array([0.0])
        cls = np.searchsorted(edges, rad, side="left").clip(0, len(edges) - 1)
        self.classes = []
        for c in np.unique(cls):
            idx = np.flatnonzero(cls == c)
            self.classes.append((idx, float(rad[idx].max()), cKDTree(cen[idx])))

    def query(self, points: np.ndarray, k0: int = 4, chunk: int = 20000) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the surface and closest point for each of ``points`` (p, 3)."""
        pts = np.asarray(points, np.float64)
        dist = np.empty(len(pts))
        close = np.empty_like(pts)
        for s in range(0, len(pts), chunk):
            d, c = self._query(pts[s : s + chunk], k0)
            dist[s : s + chunk], close[s : s + chunk] = d, c
        return dist, close

    def _eval(self, pts, cand, best, bestp):
        from trimesh.triangles import closest_point

        rows = np.repeat(np.arange(len(pts)), cand.shape[1])
        tri = cand.ravel()
        ok = tri >= 0
        rows, tri = rows[ok], tri[ok]
        if rows.size == 0:
            return
        cp = closest_point(self.triangles[tri], pts[rows])
        d = np.linalg.norm(cp - pts[rows], axis=1)
        order = np.lexsort((d, rows))
        rows, d, cp = rows[order], d[order], cp[order]
        first = np.r_[True, rows[1:] != rows[:-1]]
        r, d, cp = rows[first], d[first], cp[first]
        better = d < best[r]
        best[r[better]] = d[better]
        bestp[r[better]] = cp[better]

    def _query(self, pts, k0):
        n = len(pts)
        best = np.full(n, np.inf)
        bestp = np.zeros((n, 3))
        pending = []
        for idx, rc, tree in self.classes:
            k = min(k0, len(idx))
            dd, ii = tree.query(pts, k=k)
            dd, ii = dd.reshape(n, k), ii.reshape(n, k)
            self._eval(pts, idx[ii], best, bestp)
            pending.append((idx, rc, tree, k, dd[:, -1]))
        # prove optimality: a class is finished for a point when its k-th centroid is beyond u + R_c
        for idx, rc, tree, k, dk in pending:
            todo = np.flatnonzero((dk - rc < best) & (k < len(idx)))
            while todo.size:
                k = min(2 * k, len(idx))
                dd, ii = tree.query(pts[todo], k=k)
                dd, ii = dd.reshape(len(todo), k), ii.reshape(len(todo), k)
                sub_best, sub_p = best[todo].copy(), bestp[todo].copy()
                self._eval(pts[todo], idx[ii], sub_best, sub_p)
                best[todo], bestp[todo] = sub_best, sub_p
                again = (dd[:, -1] - rc < best[todo]) & (k < len(idx))
                todo = todo[again]
        return best, bestp


def point_surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Exact distance from each of ``points`` (p, 3) to the triangle mesh (vertices, faces)."""
    return SurfaceIndex(vertices, faces).query(points)[0]


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int) -> np.ndarray:
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(pts, np.float64)


@dataclass(frozen=True)
class SurfaceDistance:
    mrms: float  # max of the two one-way RMS distances / bbox diagonal of mesh A
    rms_ab: float  # one-way RMS from A's samples to B / diagonal
    rms_ba: float
    hausdorff: float  # max of both one-way maxima (samples and vertices) / diagonal
    mean_ab: float
    mean_ba: float
    samples: int


def bbox_diagonal(vertices: np.ndarray) -> float:
    v = np.asarray(vertices, np.float64)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) if len(v) else 0.0


def _referenced(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Vertices used by a face (unreferenced ones are not on the surface)."""
    return np.asarray(vertices, np.float64)[np.unique(np.asarray(faces, np.int64))]


def surface_distance(
    va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray, samples: int = 100_000, seed: int = 0
) -> SurfaceDistance:
    """MRMS and Hausdorff distance between surface A (the original) and B, relative to A's diagonal."""
    diag = bbox_diagonal(va) or 1.0
    pa = np.concatenate([sample_surface(va, fa, samples, seed), _referenced(va, fa)])
    pb = np.concatenate([sample_surface(vb, fb, samples, seed + 1), _referenced(vb, fb)])
    dab = SurfaceIndex(vb, fb).query(pa)[0]
    dba = SurfaceIndex(va, fa).query(pb)[0]
    na = nb = samples
    rab = float(np.sqrt(np.mean(dab[:na] ** 2)))
    rba = float(np.sqrt(np.mean(dba[:nb] ** 2)))
    return SurfaceDistance(
        mrms=max(rab, rba) / diag,
        rms_ab=rab / diag,
        rms_ba=rba / diag,
        hausdorff=float(max(dab.max(), dba.max())) / diag,
        mean_ab=float(dab[:na].mean()) / diag,
        mean_ba=float(dba[:nb].mean()) / diag,
        samples=samples,
    )


def mrms(va, fa, vb, fb, samples: int = 100_000, seed: int = 0) -> float:
    return surface_distance(va, fa, vb, fb, samples, seed).mrms


def hausdorff(va, fa, vb, fb, samples: int = 100_000, seed: int = 0) -> float:
    return surface_distance(va, fa, vb, fb, samples, seed).hausdorff


# ---------------------------------------------------------------------------------------------
# detection metrics


def bit_errors(found: str | None, truth: str) -> int:
    if not found or len(found) != len(truth):
        return len(truth)
    return sum(a != b for a, b in zip(found, truth, strict=True))


def ber(found: str | None, truth: str) -> float:
    """Bit error rate; a missing or wrong-length payload counts as chance, 0.5."""
    if not found or len(found) != len(truth):
        return 0.5
    return bit_errors(found, truth) / len(truth)


def recovered(result, truth: str) -> bool:
    """The detector said 'detected' (CRC verified) and returned exactly the embedded payload."""
    return bool(result.detected) and result.payload == truth


class Reliability:
    """Calibration of the per-bit confidence: reported confidence bins against observed accuracy."""

    EDGES = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 0.999, 1.0000001)

    def __init__(self) -> None:
        n = len(self.EDGES) - 1
        self.count = np.zeros(n, np.int64)
        self.right = np.zeros(n, np.int64)
        self.conf_sum = np.zeros(n)

    def add(self, confidence, found: str | None, truth: str) -> None:
        if not found or len(found) != len(truth) or confidence is None or len(confidence) != len(truth):
            return
        c = np.clip(np.asarray(confidence, np.float64), 0.5, 1.0)
        ok = np.frombuffer(found.encode(), np.uint8) == np.frombuffer(truth.encode(), np.uint8)
        b = np.clip(np.searchsorted(self.EDGES, c, side="right") - 1, 0, len(self.count) - 1)
        self.count += np.bincount(b, minlength=len(self.count))
        self.right += np.bincount(b, ok, minlength=len(self.count)).astype(np.int64)
        self.conf_sum += np.bincount(b, c, minlength=len(self.count))

    def merge(self, other: Reliability) -> None:
        self.count += other.count
        self.right += other.right
        self.conf_sum += other.conf_sum

    def rows(self) -> list[list]:
        out = []
        for i in range(len(self.count)):
            hi = min(self.EDGES[i + 1], 1.0)
            n = int(self.count[i])
            out.append(
                [
                    f"[{self.EDGES[i]:g}, {hi:g}{']' if hi == 1.0 else ')'}",
                    n,
                    self.conf_sum[i] / n if n else None,
                    self.right[i] / n if n else None,
                ]
            )
        return out

    def to_dict(self) -> dict:
        return {
            "edges": list(self.EDGES),
            "count": self.count.tolist(),
            "right": self.right.tolist(),
            "conf_sum": self.conf_sum.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Reliability:
        r = cls()
        r.count = np.asarray(d["count"], np.int64)
        r.right = np.asarray(d["right"], np.int64)
        r.conf_sum = np.asarray(d["conf_sum"], np.float64)
        return r
