"""POST /v1/detect: blind detection answers, expected payloads, method selection."""

from __future__ import annotations

import dataclasses

import pytest

from core.api import DetectResult
from tests.app.conftest import KEY, assert_problem, detect, embed

DETECT_KEYS = {"detected", "payload", "bit_confidence", "false_positive_probability", "copies", "carriers",
               "crc_ok", "method", "key_derived", "bit_errors", "p_value", "parts", "resampled", "unsmoothed",
               "layer", "geometric_carriers"}


@pytest.fixture(scope="module")
def marked(client, sphere_obj) -> bytes:
    response = embed(client, "sphere.obj", sphere_obj, payload="110010101111", method="planes")
    assert response.status_code == 200, response.text
    return response.content


def test_detects_payload_and_method(client, marked):
    response = detect(client, "sphere.obj", marked)
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/json"
    found = response.json()
    assert set(found) == DETECT_KEYS == {f.name for f in dataclasses.fields(DetectResult)}
    assert found["detected"] and found["crc_ok"] and found["payload"] == "110010101111"
    assert found["method"] in ("ellipsoids", "planes") and found["key_derived"] is False
    assert len(found["bit_confidence"]) == 12 and min(found["bit_confidence"]) > 0.5
    assert found["false_positive_probability"] < 1e-6


def test_method_restricts_the_search(client, marked):
    found = detect(client, "sphere.obj", marked, method="planes").json()
    assert found["detected"] and found["method"] == "planes"


def test_expected_payload_gives_bit_errors(client, marked):
    found = detect(client, "sphere.obj", marked, payload="110010101111").json()
    assert found["bit_errors"] == 0 and found["p_value"] < 1e-3
    wrong = detect(client, "sphere.obj", marked, payload="001101010000").json()
    assert wrong["bit_errors"] > 0 and wrong["p_value"] > found["p_value"]


def test_unmarked_and_wrong_key_are_not_detected(client, sphere_obj, marked):
    assert detect(client, "sphere.obj", sphere_obj).json()["detected"] is False
    found = detect(client, "sphere.obj", marked, key=KEY + "!").json()
    assert found["detected"] is False and found["false_positive_probability"] > 1e-6


def test_detect_problems(client, marked):
    assert_problem(detect(client, "sphere.obj", marked, method="cubes"), 422, "bad-form")
    assert_problem(detect(client, "sphere.obj", marked, payload="2"), 422, "bad-form")
    assert_problem(client.post("/v1/detect", files={"mesh": ("s.obj", marked)}), 422, "bad-form")
    assert_problem(detect(client, "x.obj", b"GIF89a" + bytes(100)), 415, "unsupported-format")
