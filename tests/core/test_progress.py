"""Progress of the file-level calls: from 0 to 1, never backwards, in steps a progress bar shows
(read, prepared, moved, verified, measured, written), retries included."""

from __future__ import annotations

import pytest

from core import api
from tests.conftest import shared_mesh_path


@pytest.mark.parametrize("name", ["spot.obj", "bun_zipper.ply", "Duck.glb", "sink.3ds"])
def test_progress_rises_from_0_to_1(name):
    data = shared_mesh_path(name).read_bytes()
    calls = {
        "embed": lambda p: api.embed(data, api.Options(key="k", method="planes"), filename=name, progress=p),
        # no method: where ellipsoids are refused, planes and the relaxed pass map their own stages
        "embed-auto": lambda p: api.embed(data, api.Options(key="k", payload="01" * 16), filename=name,
                                          progress=p),
        "detect": lambda p: api.detect(data, api.Options(key="k"), filename=name, progress=p),
        "capacity": lambda p: api.capacity(data, api.Options(), filename=name, progress=p),
    }
    least_steps = {"embed": 7, "embed-auto": 7, "detect": 4, "capacity": 4}
    for kind, call in calls.items():
        seen: list[float] = []
        call(seen.append)
        assert seen[0] == 0.0 and seen[-1] == 1.0, (kind, seen)
        assert seen == sorted(seen), (kind, seen)
        assert len(set(seen)) >= least_steps[kind], (kind, seen)


def test_a_multi_part_detection_reports_each_part():
    """The milk truck's parts are analysed one after the other: progress moves between them."""
    data = shared_mesh_path("CesiumMilkTruck.glb").read_bytes()
    seen: list[float] = []
    api.detect(data, api.Options(key="k"), filename="truck.glb", progress=seen.append)
    assert [f for f in seen if 0.25 < f < 0.6], seen
