"""URDF import over real HTTP and the CLI (issue 30): notes of what was ignored in the 201 answer and on stderr,
`smr=x,y,z[;x,y,z]` / `--smr` for the targets' nominal SMR offsets, one clear 422 for a xacro file, nothing stored
for a bad request, the URDF text kept in the stored model."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calib_core.urdf import XACRO_HINT, parse_urdf

from ..core.test_urdf import TREE, TREE_TARGETS, UR_LIKE
from ..core.test_urdf_import import SMALL_XACRO, arm, j2, model_points_mm, own_products_mm, random_actuated, \
    urdf_values
from .conftest import assert_problem

XML = {"Content-Type": "application/xml"}

# the flange mimics j3 (fixed: ignored), j2 has a <limit> without range (no limits), j3 mimics no joint
LENIENT = arm(j2(limit='<limit effort="1" velocity="1"/>')).replace(
    '<joint name="flange" type="fixed"><parent link="d"/>',
    '<joint name="flange" type="fixed"><mimic joint="j3"/><parent link="d"/>').replace(
    '<joint name="j3" type="revolute">', '<joint name="j3" type="revolute"><mimic joint="j9"/>')
NOTES = [
    "joint 'j2': <limit> gives no lower and no upper (the URDF default is 0): read as a revolute joint without "
    "position limits",
    "joint 'j3' mimics 'j9', which is no joint of the URDF: the <mimic> was ignored and 'j3' read as an independent "
    "(actuated) joint",
    "joint 'flange' is fixed: its <mimic joint='j3'> was ignored (a fixed joint has no value to follow)",
]


def count(c) -> int:
    return int(c.get("/robots?limit=1").headers["X-Total-Count"])


def test_notes_smr_and_source_in_the_stored_model(server):
    c = server.client
    r = c.post("/robots?targets=tool&smr=0.03,0.02,0.05", content=LENIENT.encode(), headers=XML)
    assert r.status_code == 201, r.text
    ext = r.json()["model"]["urdf"]
    assert ext["notes"] == NOTES and ext["smr_m"] == {"tool": [0.03, 0.02, 0.05]} and ext["source"] == LENIENT
    assert r.json()["actuated_joints"] == ["j1", "j2", "j3"]
    stored = c.get(r.headers["location"]).json()["model"]
    assert stored == r.json()["model"] == parse_urdf(LENIENT, None, "tool", smr_m="0.03,0.02,0.05")
    # the stored tool point is the SMR's, in the last MD-H frame
    qs = random_actuated(stored, 10, 1)
    pts = model_points_mm(stored, qs)["tool"]
    for i, qm in enumerate(qs):
        assert np.abs(pts[i] - own_products_mm(LENIENT, "a", "tool", urdf_values(stored, qm), (0.03, 0.02, 0.05))
                      ).max() < 1e-9

    # several targets: one triple each, in the order of targets (`;` sent as is or encoded)
    smr = "0.03,0.02,0.05;-0.01,0,0.2;0,0,0"
    for q in (smr, smr.replace(";", "%3B")):
        t = c.post(f"/robots?base=world&targets={TREE_TARGETS}&smr={q}&length_unit=mm", content=TREE, headers=XML)
        assert t.status_code == 201, t.text
        assert [x["xyz"] for x in t.json()["model"]["targets"]] == [[30.0, 20.0, 50.0], [-10.0, 0.0, 200.0],
                                                                   [0.0, 0.0, 0.0]]
    plain = c.post("/robots?targets=tool0", content=UR_LIKE, headers=XML)
    assert plain.status_code == 201 and plain.json()["model"]["urdf"]["notes"] == []
    assert "smr_m" not in plain.json()["model"]["urdf"]


@pytest.mark.parametrize("query, body, field, value, words", [
    ("targets=tool&smr=0.03,0.02", LENIENT, "smr", "0.03,0.02", "three numbers x,y,z"),
    ("targets=tool&smr=30,20,50", LENIENT, "smr", "30,20,50", "not millimetres"),
    ("targets=tool&smr=0,0,x", LENIENT, "smr", "0,0,x", "three finite numbers"),
    ("targets=tool&smr=0,0,0.1;0,0,0.1", LENIENT, "smr", "0,0,0.1;0,0,0.1", "2 SMR offsets for 1 target link"),
    ("", SMALL_XACRO, "urdf", "<xacro:property>", XACRO_HINT),
    ("", SMALL_XACRO.replace('<xacro:property name="l1" value="0.3"/>', ""),
     "joint[@name='j1']/origin/@xyz", "0 0 ${l1}", XACRO_HINT),
])
def test_bad_request_stores_nothing(server, query, body, field, value, words):
    c = server.client
    before = count(c)
    r = c.post(f"/robots?{query}", content=body.encode(), headers=XML)
    problem = assert_problem(r, 422)
    assert len(problem["errors"]) == 1, problem
    err = problem["errors"][0]
    assert err["field"] == field and err["value"] == value and words in err["message"], err
    assert count(c) == before


def test_cli_prints_notes_and_takes_smr(tmp_path, capsys):
    from service.cli import main

    src = tmp_path / "arm.urdf"
    src.write_text(LENIENT)
    out = tmp_path / "model.json"
    assert main(["import-urdf", str(src), "--target", "tool", "--smr", "0.03,0.02,0.05", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert [ln.split(": note: ", 1)[1] for ln in err.splitlines()] == NOTES
    assert err.splitlines()[0].startswith(f"calib import-urdf: {src}: note: joint 'j2'")
    assert json.loads(out.read_text()) == parse_urdf(LENIENT, None, "tool", smr_m="0.03,0.02,0.05")
    # several targets, a negative first component (argparse needs --smr=...)
    tree = tmp_path / "tree.urdf"
    tree.write_text(TREE)
    assert main(["import-urdf", str(tree), "--base", "world", "--target", TREE_TARGETS,
                 "--smr=-0.03,0.02,0.05;0,0,0.1;0,0,0"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["targets"][0]["xyz"] == [-0.03, 0.02, 0.05] and doc["urdf"]["smr_m"]["r_tool"] == [0.0, 0.0, 0.1]
    # bad values and xacro: exit 1, the parameter / the hint on stderr, nothing written
    out2 = tmp_path / "nothing.json"
    assert main(["import-urdf", str(src), "--target", "tool", "--smr", "0.03,0.02", "-o", str(out2)]) == 1
    assert "calib import-urdf: " + str(src) + ": smr: an SMR offset is three numbers" in capsys.readouterr().err
    xacro = tmp_path / "arm.urdf.xacro"
    xacro.write_text(SMALL_XACRO)
    assert main(["import-urdf", str(xacro), "-o", str(out2)]) == 1
    assert XACRO_HINT in capsys.readouterr().err and not out2.exists()


def test_a_misspelt_key_or_option_is_refused_and_nothing_is_stored(server):
    """Issue 31: a typo never calibrates another robot. A model key (top level, joint, target, units) and a URDF
    upload option each get a 422 naming it and the nearest valid one; nothing is stored."""
    from calib_core.robots import spray7

    c = server.client
    before = count(c)
    doc = spray7()
    doc["convetion"] = "dh"
    doc["joints"][1]["alpah"] = 3.0
    doc["units"]["lenght"] = "m"
    r = c.post("/robots", json=doc)
    assert r.status_code == 422, r.text
    fields = {e["field"]: e["message"] for e in r.json()["errors"]}
    assert "did you mean 'convention'" in fields["convetion"] and "did you mean 'alpha'" in fields["joints[1].alpah"]
    assert "did you mean 'length'" in fields["units.lenght"]
    r = c.post("/robots?target=tool", content=LENIENT.encode(), headers=XML)
    assert r.status_code == 422, r.text
    assert r.json()["errors"][0]["field"] == "query.target" and "'targets'" in r.json()["errors"][0]["message"]
    assert count(c) == before
