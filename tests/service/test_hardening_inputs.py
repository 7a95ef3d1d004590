"""Issue 33's low items on inputs, over real HTTP against `calib serve`: an absurd URDF angle, empty URDFs and a CSV
of one setup per row are 422s naming what is wrong at upload, with nothing stored.

Before: `rpy="1e300 0 0"` was accepted (201), a URDF with a link but no joint said "0 leaf links below 'a' ()", and
a CSV whose every row was a setup of its own was stored (201) and failed only at job time."""
from __future__ import annotations

import pytest

from .conftest import Server, assert_problem

URDF = """<?xml version="1.0"?>
<robot name="two">
  <link name="base"/><link name="l1"/><link name="tip"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="{rpy}"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="tip"/>
    <origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/></joint>
</robot>
"""
XML = {"Content-Type": "application/xml"}


@pytest.fixture(scope="module")
def input_server(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log", CALIB_EMBEDDED_WORKERS="0",
               CALIB_PLAN_PROCESSES="0", CALIB_COMPUTE_PROCESSES="0")
    yield s
    s.stop()


def _robots(s) -> int:
    return int(s.client.get("/robots").headers["x-total-count"])


def test_an_absurd_urdf_angle_is_a_422_naming_the_joint(input_server):
    s = input_server
    assert s.client.post("/robots", content=URDF.format(rpy="0 0 1.5707963"), headers=XML).status_code == 201
    n = _robots(s)
    for rpy in ("1e300 0 0", "0 -1e300 0", "0 0 1e9"):
        body = assert_problem(s.client.post("/robots", content=URDF.format(rpy=rpy), headers=XML), 422)
        (e,) = body["errors"]
        assert e["field"] == "joint[@name='j1']/origin/@rpy" and e["value"] == rpy, e
        assert "rad" in e["message"], e
    assert _robots(s) == n


@pytest.mark.parametrize("urdf, says", [
    ('<robot name="empty"/>', "no <link>"),
    ('<robot name="empty">\n  <!-- nothing yet -->\n</robot>', "no <link>"),
    ('<robot name="one"><link name="a"/></robot>', "no joint below the base link 'a'"),
])
def test_an_empty_urdf_says_there_is_nothing_in_it(input_server, urdf, says):
    body = assert_problem(input_server.client.post("/robots", content=urdf, headers=XML), 422)
    messages = " ".join(e["message"] for e in body["errors"])
    assert says in messages and "root links" not in messages and "()" not in messages, body


def test_one_setup_per_row_is_refused_at_upload(input_server, model_doc, csv_text):
    s = input_server
    rid = s.client.post("/robots", json=model_doc).json()["id"]
    lines = csv_text.splitlines()
    own = [lines[0] + ",setup"] + [f"{line},S{i:03d}" for i, line in enumerate(lines[1:])]
    body = assert_problem(s.client.post(f"/robots/{rid}/measurements",
                                        files={"file": ("setups.csv", "\n".join(own) + "\n")}), 422)
    (e,) = body["errors"]
    assert e["column"] == "setup" and e["value"] == "S000", e
    assert "fewer than three distinct measured positions" in e["message"] and "150 of the 150 setups" in e["message"]
    assert s.client.get(f"/robots/{rid}/measurements").json() == []

    two = [lines[0] + ",setup"] + [f"{line},{'A' if i % 2 else 'B'}" for i, line in enumerate(lines[1:])]
    r = s.client.post(f"/robots/{rid}/measurements", files={"file": ("two.csv", "\n".join(two) + "\n")})
    assert r.status_code == 201, r.text  # two setups of 75 poses each still upload
