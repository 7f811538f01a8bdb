"""The constants of the two methods, in one frozen dataclass (trimesh's ``tol``).

How each value was chosen, and what was measured, is in ``core/README.md``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerances:
    """Every constant of the method.  Lengths are in units of the carrier's local scale ``s``
    unless said otherwise.

    Attributes
    ----------
    strength : float
        Default margin ``|z|`` of a carrier after embedding.
    plane_floor : float
        ``planes``: the half-width ``tau`` of the planes is at least ``plane_floor * s``, so that
        bit 1 (inside) is reachable on flat rings, where ``Psi = 0``.
    alpha : float
        ``ellipsoids``: the neighbours' covariance is regularised as ``Sigma + alpha s^2 I`` (flat
        rings have a singular ``Sigma``).
    radius : float
        ``ellipsoids``: the Mahalanobis radius ``K`` of the boundary.
    min_flatness : float
        A neighbourhood with ``l2 <= min_flatness * l3`` is a line, not a surface: no carrier.
    max_scale : float
        A carrier whose scale exceeds ``max_scale`` times the median scale is dropped: its move
        costs the RMS budget more than it buys (core/README.md, "Carriers the budget cannot
        move"; 4 until 2026-12-05).  Meshes of fewer than
        :data:`~core.analysis.TIE_BREAK_FROM` vertices use ``max_scale_small``: every carrier
        counts there (the Sink's largest part lost the 32-bit key code at 2).
    max_scale_small : float
        ``max_scale`` of meshes of fewer than :data:`~core.analysis.TIE_BREAK_FROM` vertices.
    max_local_move : float
        Displacement cap of one carrier.
    max_move : float
        Displacement cap as a fraction of the bounding-box diagonal...
    coarse_move : float
        ...or as this fraction of the median local scale, whichever is larger (coarse meshes).
    max_displacement : float
        Ceiling of every carrier's displacement, as a fraction of the bounding-box diagonal: the
        caps above are widened for coarse meshes, never past this.
    clip_margin : float
        A carrier whose move exceeds its cap is moved as far as the cap allows and kept when it
        then reads its bit with at least ``clip_margin * strength``.
    rms_budget : float
        At the default strength, the RMS displacement over all vertices of a mesh, as a fraction
        of its bounding-box diagonal, is kept within this: the carriers that need the largest moves
        are left unmoved (the code absorbs them) until the rest fit.
    verify_rounds : int
        Embed, re-read after storage rounding, fix: at most this many rounds.
    """

    strength: float = 0.07
    plane_floor: float = 0.07
    alpha: float = 0.05
    radius: float = 0.8
    min_flatness: float = 0.05
    max_scale: float = 2.0
    max_scale_small: float = 4.0
    max_local_move: float = 0.8
    max_move: float = 5e-3
    coarse_move: float = 0.25
    max_displacement: float = 3e-3
    clip_margin: float = 0.3
    rms_budget: float = 2e-4
    verify_rounds: int = 12


TOL = Tolerances()
