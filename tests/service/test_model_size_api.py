"""Issue 33 over real HTTP against `calib serve` (SQLite): a documented maximum model size (joints, rows, targets)
enforced at `POST /robots`, JSON and URDF alike: a clear 422, nothing stored. A 1000-joint model used to be stored
with 201 (and a 3-pose plan on it took 51 s and 5 GB); real robots, up to a two-arm humanoid with hands, still fit."""
from __future__ import annotations

import time

import pytest

from service.robots.service import MAX_MODEL_JOINTS, MAX_MODEL_ROWS, MAX_MODEL_TARGETS

from .conftest import assert_problem, sqlite_count


def chain(n_joints: int, n_fixed: int = 0, n_targets: int = 0) -> dict:
    """A serial MD-H chain in mm/deg with `n_fixed` mount plates after the joints and `n_targets` targets."""
    rows = [{"name": f"J{i + 1}", "type": "revolute", "a": 100.0, "alpha": (-90, 0, 90)[i % 3], "d": 50.0,
             "theta": 0, "beta": 0, "limits": [-170, 170]} for i in range(n_joints)]
    rows += [{"name": f"F{i + 1}", "type": "fixed", "a": 0, "alpha": 0, "d": 10.0, "theta": 0} for i in range(n_fixed)]
    doc = {"name": f"chain{n_joints}", "convention": "mdh", "units": {"length": "mm", "angle": "deg"}, "joints": rows}
    if n_targets:
        doc["targets"] = [{"name": f"T{k}", "parent": rows[-1]["name"], "xyz": [100.0, 10.0 * k, 0]}
                          for k in range(n_targets)]
    else:
        doc["tool"] = [100.0, 0, 50.0]
    return doc


def urdf_chain(n: int) -> bytes:
    links = "".join(f'<link name="l{i}"/>' for i in range(n + 1))
    joints = "".join(f'<joint name="j{i + 1}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/>'
                     f'<origin xyz="0.1 0 0.05" rpy="0 0 0"/><axis xyz="0 0 1"/>'
                     f'<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>' for i in range(n))
    return f'<?xml version="1.0"?><robot name="big">{links}{joints}</robot>'.encode()


@pytest.mark.parametrize("doc, counts", [
    (chain(1000), {"joints": 1000, "rows": 1000}),
    (chain(MAX_MODEL_JOINTS + 1), {"joints": MAX_MODEL_JOINTS + 1}),
    (chain(80, n_fixed=MAX_MODEL_ROWS - 79), {"rows": MAX_MODEL_ROWS + 1}),
    (chain(7, n_targets=MAX_MODEL_TARGETS + 1), {"targets": MAX_MODEL_TARGETS + 1}),
], ids=["1000_joints", "one_joint_too_many", "one_row_too_many", "one_target_too_many"])
def test_a_model_over_the_maximum_size_is_422_nothing_stored(server, doc, counts):
    before = sqlite_count(server.db_path, "robots")
    t = time.perf_counter()
    body = assert_problem(server.client.post("/robots", json=doc), 422)
    assert time.perf_counter() - t < 5.0
    assert body["max_joints"] == MAX_MODEL_JOINTS and body["max_rows"] == MAX_MODEL_ROWS
    assert body["max_targets"] == MAX_MODEL_TARGETS and "nothing was stored" in body["detail"], body
    got = {}
    for e in body["errors"]:
        kind = "targets" if e["field"] == "targets" else "rows" if "rows" in e["message"] else "joints"
        got[kind] = e["value"]
        assert "at most" in e["message"], e
    assert got == counts, body
    assert sqlite_count(server.db_path, "robots") == before


def test_a_urdf_over_the_maximum_is_422_too(server):
    before = sqlite_count(server.db_path, "robots")
    r = server.client.post("/robots", content=urdf_chain(MAX_MODEL_JOINTS + 20),
                           headers={"content-type": "application/xml"})
    body = assert_problem(r, 422)
    assert body["errors"][0]["field"] == "joints" and body["errors"][0]["value"] == MAX_MODEL_JOINTS + 20, body
    assert sqlite_count(server.db_path, "robots") == before
    r = server.client.post("/robots", content=urdf_chain(20), headers={"content-type": "application/xml"})
    assert r.status_code == 201, r.text


def test_models_at_the_maximum_are_stored(server):
    """A two-arm humanoid with two hands has 60-80 joints; the maxima themselves are taken."""
    for doc in (chain(80, n_fixed=40, n_targets=20), chain(MAX_MODEL_JOINTS, n_fixed=MAX_MODEL_ROWS - MAX_MODEL_JOINTS,
                                                            n_targets=MAX_MODEL_TARGETS)):
        r = server.client.post("/robots", json=doc)
        assert r.status_code == 201, r.text
