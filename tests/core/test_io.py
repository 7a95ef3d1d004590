from datetime import datetime, timezone

import numpy as np
import pytest

from calib_core.io import MeasurementError, parse_measurements, write_measurements
from calib_core.model import parse_model
from calib_core.robots import spray7
from calib_core.twin import Twin

MODEL = parse_model(spray7())
HEADER = "point,J1,J2,J3,J4,J5,J6,J7,x,y,z,timestamp"
ROW = "P001,3098.611678,54.315206,-45.791980,73.781843,-76.455800,1757.014212,-70.779606,-2821.3401,876.6147,-16.3583,2026-11-03T08:00:19+00:00"


def test_contract_example_parses():
    m = parse_measurements(f"{HEADER}\n{ROW}\n", MODEL)
    assert m.n_poses == 1 and m.point_ids == ["P001"]
    assert np.isclose(m.joints[0, 1], np.radians(54.315206)) and m.joints[0, 0] == 3098.611678
    assert m.timestamp[0] == datetime(2026, 11, 3, 8, 0, 19, tzinfo=timezone.utc).timestamp()


def test_round_trip_with_columns_in_any_order(seed):
    tw = Twin(MODEL, seed)
    meas = tw.measure(n=30)
    meas.payload = np.random.default_rng(seed).uniform(0, 10, 30)
    text = write_measurements(meas, MODEL)
    back = parse_measurements(text, MODEL)
    assert np.allclose(back.points, meas.points, atol=1e-6) and np.allclose(back.joints, meas.joints, atol=1e-9)
    # reverse the column order and add comments: same data
    lines = text.splitlines()
    rows = [ln.split(",")[::-1] for ln in lines]
    shuffled = "# tracker export\n// second comment\n" + "\n".join(",".join(r) for r in rows) + "\n"
    again = parse_measurements(shuffled.encode(), MODEL)
    assert np.allclose(again.joints, back.joints) and np.allclose(again.payload, back.payload)


def _errors(text):
    with pytest.raises(MeasurementError) as exc:
        parse_measurements(text, MODEL)
    return exc.value.errors


@pytest.mark.parametrize("text, row, column, value, words", [
    ("", None, None, None, "no header"),
    (HEADER + "\n", 1, None, None, "no data"),
    (HEADER.replace(",J4", "") + "\n" + ROW, 1, "J4", None, "missing column"),
    (HEADER.replace("J5", "J4") + "\n" + ROW, 1, "J4", "J4", "duplicated column"),
    (HEADER + ",paylod\n" + ROW + ",3", 1, "paylod", "paylod", "unknown column"),
    (HEADER + "\n" + ROW.replace("54.315206", "nan"), 2, "J2", "nan", "finite"),
    (HEADER + "\n" + ROW.replace("-2821.3401", "inf"), 2, "x", "inf", "finite"),
    (HEADER + "\n" + ROW.replace("54.315206", "abc"), 2, "J2", "abc", "not a number"),
    (HEADER + "\n" + ROW.replace("54.315206", "75"), 2, "J2", "75", "outside the joint limits"),
    (HEADER + "\n" + ROW.replace("1757.014212", "1600"), 2, "J6", "1600", "outside the joint limits"),
    (HEADER + "\n" + ROW.replace("2026-11-03T08:00:19+00:00", "yesterday"), 2, "timestamp", "yesterday", "ISO 8601"),
    (HEADER + "\n" + ROW + ",extra", 2, None, 13, "expected 12 fields"),
])
def test_bad_rows_name_row_column_value(text, row, column, value, words):
    errs = _errors(text)
    assert any(e["row"] == row and e["column"] == column and e["value"] == value and words in e["message"]
               for e in errs), errs


def test_every_error_is_listed_and_nothing_half_parsed():
    bad = ROW.replace("54.315206", "75")
    text = "\n".join([HEADER, ROW, bad, ROW.replace("P001", "P002"), bad.replace("P001", "P003")])
    errs = _errors(text)
    assert [e["row"] for e in errs] == [3, 5]


def test_binary_and_wrong_encoding_are_rejected():
    assert "binary" in _errors(b"\x00\x01\x02PK")[0]["message"]
    assert "UTF-8" in _errors((HEADER + "\n" + ROW.replace("P001", "Pü")).encode("latin-1"))[0]["message"]


def test_duplicated_point_ids():
    errs = _errors("\n".join([HEADER, ROW, ROW]))
    assert errs[0]["row"] == 3 and errs[0]["column"] == "point"
