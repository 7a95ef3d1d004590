"""calib_core.units_check (issue 33): the nominal model registered to the points judges whether the points and the
joint columns are in the model's units. Thresholds against the real cells and small legitimate sets."""
from __future__ import annotations

import math

import numpy as np
import pytest

from calib_core import Twin, datasets, parse_model, write_measurements
from calib_core.io import parse_measurements
from calib_core.robots import arm6, spray7
from calib_core.units_check import RATIO_LIMIT, fit_ratio, unit_problems

READERS = {
    "motoman_leica": lambda: datasets.motoman_leica(),
    "iiwa7_payload": lambda: datasets.iiwa7_payload(None, orientation=True, torques=True),
    "iiwa7_exp2": lambda: datasets.iiwa7_run("exp2"),
    "dlr_agile_justin": lambda: datasets.agile_justin_tree(),
    "hilti_trailblazer": lambda: datasets.hilti_trailblazer(),
    "hilti_by_station": lambda: datasets.hilti_trailblazer(setup_by="station"),
    "agile_justin_right": lambda: datasets.agile_justin("right"),
}


@pytest.mark.skipif(not (datasets.available() and datasets.justin_available() and datasets.hilti_available()),
                    reason="the shared real datasets are not present")
@pytest.mark.parametrize("name", sorted(READERS))
def test_real_cells_fit_well_within_the_limit(name):
    """Measured: 0.003 (Motoman) .. 0.088 (iiwa exp2, the nominal DH of an iiwa whose SMR is only roughly known):
    the limit of 1/3 leaves a factor of 3.8."""
    ds = READERS[name]()
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model, instrument=ds.instrument)
    assert fit_ratio(model, meas) < RATIO_LIMIT / 3
    assert unit_problems(model, meas) == []


@pytest.mark.parametrize("make", [spray7, arm6])
@pytest.mark.parametrize("seed", range(6))
def test_joints_that_barely_move_are_no_unit_mistake(make, seed):
    """Some revolute joints within +-2.5 deg (numbers a column in rad could hold), 3, 5 or 30 poses: nothing said."""
    model = parse_model(make())
    twin = Twin(model, seed)
    q = twin.sample_joints(30)
    rng = np.random.default_rng(seed)
    rev = [int(j) for j in model.actuated if not model.prismatic[j]]
    for j in rng.choice(rev, size=int(rng.integers(1, len(rev) + 1)), replace=False):
        q[:, j] = np.radians(rng.uniform(-1.5, 1.5) + rng.uniform(-1, 1, len(q)))
    for n in (3, 5, 30):
        meas = parse_measurements(write_measurements(twin.measure(q[:n]), model), model, limits="warn")
        assert unit_problems(model, meas) == [], (n, seed)


def test_wrong_units_are_named_with_what_to_do():
    model = parse_model(spray7())
    meas = Twin(model, 1).measure(n=60)
    assert unit_problems(model, meas) == []
    m = meas.subset(np.arange(60))
    m.points = m.points / 1000
    errors = unit_problems(model, m)
    assert [e["column"] for e in errors] == ["x", "y", "z"]
    assert "look like metres" in errors[0]["message"] and "multiply them by 1000" in errors[0]["message"]
    m = meas.subset(np.arange(60))
    m.joints = m.joints.copy()
    m.joints[:, 4] *= math.pi / 180  # J5 written in rad: read as deg
    assert fit_ratio(model, m) < RATIO_LIMIT  # within the points' check: only the joint's reading finds it
    errors = unit_problems(model, m)
    assert [e["column"] for e in errors] == ["J5"] and "J5 looks like radians" in errors[0]["message"]
    spread = errors[0]["message"]
    assert "read with J5 as rad" in spread, spread
