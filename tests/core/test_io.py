from datetime import datetime, timezone

import numpy as np
import pytest

from calib_core.io import MeasurementError, Measurements, parse_measurements, write_measurements
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


def test_the_sequence_column_round_trips_and_follows_its_rows(seed):
    """`sequence` (the order the poses were measured in) is read, written and kept by subset with its rows."""
    meas = Twin(MODEL, seed).measure(n=20)
    meas.timestamp = None
    meas.sequence = np.random.default_rng(seed).permutation(20) * 2.0 + 100.0
    back = parse_measurements(write_measurements(meas, MODEL), MODEL)
    assert np.array_equal(back.sequence, meas.sequence)
    assert np.array_equal(back.subset(np.arange(20)[::-3]).sequence, meas.sequence[::-3])
    assert parse_measurements(f"{HEADER}\n{ROW}\n", MODEL).sequence is None


def _errors(text, model=MODEL, **kw):
    """The errors parse_measurements names for a CSV it must refuse."""
    with pytest.raises(MeasurementError) as exc:
        parse_measurements(text, model, **kw)
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
    (HEADER + ",sequence\n" + ROW + ",first", 2, "sequence", "first", "not a number"),
    (HEADER + ",sequence\n" + ROW + ",1e13", 2, "sequence", "1e13", "sequence must be at most"),
])
def test_bad_rows_name_row_column_value(text, row, column, value, words):
    errs = _errors(text)
    assert any(e["row"] == row and e["column"] == column and e["value"] == value and words in e["message"]
               for e in errs), errs


@pytest.mark.parametrize("sep, said", [(";", "';'"), ("\t", "tabs")])
def test_a_spreadsheet_export_with_another_separator_is_named_as_such(seed, sep, said):
    """A CSV exported where the decimal point is a comma (';' between fields, '3,14') or as tab-separated text: one
    error on row 1 saying how its fields are separated and what the contract asks, not one per column."""
    text = write_measurements(Twin(MODEL, seed).measure(n=5), MODEL)
    if sep == ";":
        text = "\n".join(";".join(f.replace(".", ",") for f in ln.split(",")) for ln in text.splitlines())
    else:
        text = text.replace(",", sep)
    (e,) = _errors(text)
    assert e["row"] == 1 and e["value"] == text.splitlines()[0] and said in e["message"] and "','" in e["message"]


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


# Issue 10: plausibility ranges, csv.Error, strict numbers, '#' ids, bounded error lists.

def _model_in_metres():
    doc = spray7()
    doc["units"] = {"length": "m", "angle": "deg"}
    for j in doc["joints"]:
        j["a"], j["d"] = j["a"] / 1000, j["d"] / 1000
        j["com"] = [v / 1000 for v in j["com"]]
        if j["type"] == "prismatic":
            j["limits"] = [v / 1000 for v in j["limits"]]
    doc["tool"] = [v / 1000 for v in doc["tool"]]
    return parse_model(doc)


def _with(column, value):
    head, row = HEADER.split(","), ROW.split(",")
    if column in head:
        row[head.index(column)] = value
    else:
        head.append(column)
        row.append(value)
    return ",".join(head) + "\n" + ",".join(row) + "\n"


@pytest.mark.parametrize("column, value, words", [
    ("x", "1e305", "at most 100000 mm"),
    ("y", "-1e30", "at most 100000 mm"),
    ("z", "1e200", "at most 100000 mm"),
    ("x", "1e400", "finite"),
    ("sigma", "1e-300", "between 0.0001 and 100 mm"),
    ("sigma", "1e200", "between 0.0001 and 100 mm"),
    ("sigma", "0", "between"),
    ("payload", "1e308", "between 0 and 10000 kg"),
    ("payload", "-1", "between 0 and 10000 kg"),
    ("temperature", "1e10", "-60..200 deg C"),
    ("timestamp", "9999-12-31T23:59:59+00:00", "1970-01-01 .. 2200-01-01"),
    ("timestamp", "1900-01-01T00:00:00+00:00", "1970-01-01 .. 2200-01-01"),
])
def test_implausible_values_name_row_column_value_and_range(column, value, words):
    errs = _errors(_with(column, value))
    assert any(e["row"] == 2 and e["column"] == column and e["value"] == value and words in e["message"]
               for e in errs), errs


def test_ranges_respect_the_model_length_unit():
    m = _model_in_metres()
    row = "P001,3.098611678,54.315206,-45.791980,73.781843,-76.455800,1.757014212,-70.779606,{x},0.8766147,-0.0163583,"
    text = HEADER + "\n" + row + "2026-11-03T08:00:19+00:00\n"
    assert parse_measurements(text.format(x="99.5"), m).points[0, 0] == 99.5e3  # 99.5 m is plausible
    errs = _errors(text.format(x="1000"), m)  # 1 km is not
    assert [(e["column"], e["value"]) for e in errs] == [("x", "1000")], errs
    assert "at most 100 m" in errs[0]["message"]


def test_revolute_joint_without_limits_is_bounded():
    doc = spray7()
    del doc["joints"][1]["limits"]
    m = parse_model(doc)
    assert parse_measurements(_with("J2", "720"), m).n_poses == 1
    errs = _errors(_with("J2", "1e200"), m)
    assert errs[0]["column"] == "J2" and "36000 deg" in errs[0]["message"]


def test_field_over_csv_limit_names_its_row():
    long = "P" + "9" * 131_073
    errs = _errors(HEADER + "\n" + ROW + "\n" + ROW.replace("P001", long) + "\n")
    assert len(errs) == 1 and errs[0]["row"] == 3 and "131072 characters" in errs[0]["message"], errs
    assert len(str(errs[0]["value"])) < 200  # the value is cut, not echoed whole


@pytest.mark.parametrize("value", ["1_000", "٣", "３", "1e1_0", "0x10", "1.5.2", "١٢٣.٤", "²"])
def test_underscores_and_unicode_digits_are_not_numbers(value):
    errs = _errors(HEADER + "\n" + ROW.replace("-2821.3401", value))
    assert any(e["row"] == 2 and e["column"] == "x" and "not a number" in e["message"] for e in errs), errs


@pytest.mark.parametrize("value", ["1", "-1.", ".5", "+2.5e-3", "1E3", " 7 "])
def test_plain_numbers_still_parse(value):
    assert parse_measurements(HEADER + "\n" + ROW.replace("-2821.3401", value), MODEL).n_poses == 1


def test_a_point_id_starting_with_hash_never_drops_its_row_silently():
    row2 = ROW.replace("P001", "P002")
    errs = _errors("\n".join([HEADER, ROW, "#" + row2]))  # a comment by the contract, but a whole data row
    assert len(errs) == 1 and errs[0]["row"] == 3 and errs[0]["column"] == "point", errs
    assert "comment" in errs[0]["message"] and "quote" in errs[0]["message"]
    quoted = parse_measurements("\n".join([HEADER, ROW, '"#P002"' + row2[4:]]), MODEL)  # a quoted id is data
    assert quoted.point_ids == ["P001", "#P002"]
    commented = parse_measurements("\n".join([HEADER, ROW, "# " + row2, "// " + row2, "#note: tracker warm"]), MODEL)
    assert commented.point_ids == ["P001"]  # '# ' with a space comments a row out, as before


def test_error_lists_are_bounded_and_counted():
    import time
    t = time.perf_counter()
    header = "," * 1_800_000  # a 1.8 MB header of empty columns
    with pytest.raises(MeasurementError) as exc:
        parse_measurements(header + "\n" + ROW, MODEL)
    assert time.perf_counter() - t < 2.0
    assert len(exc.value.errors) == 1 and "columns" in exc.value.errors[0]["message"]
    bad = "\n".join([HEADER] + [ROW.replace("P001", f"P{i}").replace("54.315206", "abc") for i in range(5000)])
    with pytest.raises(MeasurementError) as exc:
        parse_measurements(bad, MODEL)
    assert exc.value.total == 5000 and len(exc.value.errors) <= 1000


def test_nul_anywhere_is_binary():
    assert "binary" in _errors((HEADER + "\n" + ROW + "\n" + " " * 70_000 + "\x00").encode())[0]["message"]


def test_instrument_preset_sets_the_noise_and_the_answer_names_it():
    """Without a sigma column the named preset weights the fit and the floor; a sigma column wins; unknown names
    are refused naming the choices."""
    from calib_core.diagnosis import noise_floor_mm
    from calib_core.instruments import INSTRUMENTS
    from calib_core.robots import arm6

    model = parse_model(arm6())
    meas = Twin(model, 0).measure(n=20)
    text = write_measurements(meas, model)
    floors = {}
    for name, inst in INSTRUMENTS.items():
        m = parse_measurements(text, model, instrument=name)
        assert np.allclose(m.noise_sigma_mm(), inst.sigma_mm(m.points))
        assert name in m.noise_source() and m.subset([0, 1]).instrument == name
        floors[name], note, _ = noise_floor_mm(m, m.noise_sigma_mm())
        assert name in note
    assert floors["laser_tracker"] < floors["optical"] < floors["motion_capture"] < floors["total_station"]
    default = parse_measurements(text, model)
    assert "assumed" in default.noise_source() and np.allclose(default.noise_sigma_mm(),
                                                                INSTRUMENTS["laser_tracker"].sigma_mm(default.points))
    meas.sigma = np.full(meas.n_poses, 0.05)
    given = parse_measurements(write_measurements(meas, model), model, instrument="total_station")
    assert np.allclose(given.noise_sigma_mm(), 0.05) and "sigma column" in given.noise_source()
    with pytest.raises(MeasurementError, match="unknown instrument"):
        parse_measurements(text, model, instrument="ruler")


def _narrowed(lims: dict) -> "object":
    doc = spray7()
    for j in doc["joints"]:
        if j["name"] in lims:
            j["limits"] = lims[j["name"]]
    return parse_model(doc)


def test_limits_reject_by_default_and_warn_reports_the_extent():
    """Out-of-limit joint values are errors naming row and column by default; limits="warn" accepts them and
    reports per joint how many rows, the column's range and the limits, in the model's units."""
    meas = Twin(MODEL, 3).measure(n=60)
    text = write_measurements(meas, MODEL)
    narrow = _narrowed({"J2": [-40, 40], "J6": [1800, 2300]})
    q2, q6 = np.degrees(meas.joints[:, 1]), meas.joints[:, 5]
    out2, out6 = np.abs(q2) > 40, q6 < 1800
    assert out2.sum() >= 3 and out6.sum() >= 3  # the twin samples the full spray7 ranges
    with pytest.raises(MeasurementError) as exc:
        parse_measurements(text, narrow)
    errs = exc.value.errors
    assert exc.value.total == out2.sum() + out6.sum()
    assert {e["row"] for e in errs if e["column"] == "J2"} == set(np.flatnonzero(out2) + 2)  # line numbers
    assert all("outside the joint limits [-40, 40] deg" in e["message"] for e in errs if e["column"] == "J2")

    got = parse_measurements(text, narrow, limits="warn")
    assert np.allclose(got.joints, parse_measurements(text, MODEL).joints)  # the values as given, not clipped
    assert got.n_poses == 60 and [o["joint"] for o in got.out_of_limits] == ["J2", "J6"]
    j2, j6 = got.out_of_limits
    assert j2["unit"] == "deg" and j2["limits"] == [-40.0, 40.0] and j2["rows"] == out2.sum()
    assert np.isclose(j2["min"], q2.min(), atol=1e-6) and np.isclose(j2["max"], q2.max(), atol=1e-6)
    assert j2["first_rows"] == list(np.flatnonzero(out2) + 2)[:10]
    assert j6["unit"] == "mm" and j6["limits"] == [1800.0, 2300.0] and j6["rows"] == out6.sum()
    assert np.isclose(j6["min"], q6.min(), atol=1e-6)
    assert parse_measurements(text, MODEL, limits="warn").out_of_limits == []  # within the limits: nothing
    assert got.subset([0, 1]).out_of_limits == []  # a report of the parse, not of the poses


def test_limits_warn_keeps_the_other_checks():
    errs = _errors(_with("J2", "1e200"), limits="warn")  # 100 turns is still implausible
    assert errs[0]["column"] == "J2" and "36000 deg" in errs[0]["message"]
    with pytest.raises(MeasurementError, match="unknown limits mode: one of reject, warn"):
        parse_measurements(f"{HEADER}\n{ROW}\n", MODEL, limits="ignore")


@pytest.mark.parametrize("quoted", [False, True])
def test_a_wide_header_is_counted_exactly_without_being_split(quoted):
    """A header of 1001 columns is refused naming its exact count, with or without quotes (the unquoted one is
    counted by its commas, never split into a list)."""
    from calib_core.io import MAX_COLUMNS

    cell = '"c"' if quoted else "c"
    errs = _errors(",".join([cell] * (MAX_COLUMNS + 1)) + "\n" + ROW)
    assert len(errs) == 1 and errs[0]["row"] == 1 and errs[0]["value"] == MAX_COLUMNS + 1, errs
    assert f"the header has {MAX_COLUMNS + 1} columns" in errs[0]["message"]


def test_a_data_row_of_commas_is_counted_and_a_quoted_one_refused_unread():
    from calib_core.io import MAX_QUOTED_COMMAS

    errs = _errors("\n".join([HEADER, ROW, "," * 2_000_000, ROW.replace("P001", "P002")]))
    assert [(e["row"], e["value"]) for e in errs] == [(3, 2_000_001)], errs
    assert "expected 12 fields like the header, found 2000001" in errs[0]["message"]
    errs = _errors("\n".join([HEADER, ROW, '"a"' + "," * MAX_QUOTED_COMMAS]))
    assert len(errs) == 1 and errs[0]["row"] == 3 and errs[0]["column"] is None, errs
    assert "quotes" in errs[0]["message"] and str(MAX_QUOTED_COMMAS) in errs[0]["message"]
    assert len(str(errs[0]["value"])) < 200


def test_split_is_csv_reader_on_lines_without_quotes():
    """_split's str.split path gives exactly what csv.reader(skipinitialspace=True) gives, on random lines of
    commas, spaces, tabs and text; its long-field test agrees with measuring every piece."""
    import csv
    import random

    from calib_core.io import _longest_over, _split

    rng = random.Random(7)
    for _ in range(3000):
        line = "".join(rng.choice([",", " ", "\t", "a", "1", ".", "-", "  "]) for _ in range(rng.randrange(0, 40)))
        if not line.strip():
            continue
        assert _split(line) == next(csv.reader([line], skipinitialspace=True)), repr(line)
    for _ in range(300):
        pieces = [rng.choice(["", "x" * rng.randrange(0, 40)]) for _ in range(rng.randrange(1, 12))]
        line = ",".join(pieces)
        limit = rng.randrange(1, 45)
        assert _longest_over(line, limit) == (max(map(len, pieces)) > limit), (line, limit)


@pytest.mark.parametrize("limits", ["reject", "warn"])
def test_the_column_at_a_time_path_gives_the_per_value_answer(monkeypatch, seed, limits):
    """Numeric columns are parsed a column at a time when nothing is wrong with them; the per value loop (used at
    the first doubt, naming every problem) must give the same Measurements bit for bit: sigma, payload,
    temperature, spaces around numbers, values beyond the joint limits (limits="warn")."""
    from calib_core import io as csvio

    meas = Twin(MODEL, seed).measure(n=40)
    rng = np.random.default_rng(seed)
    meas.payload = rng.uniform(0, 10, 40)
    meas.sigma = rng.uniform(0.005, 0.05, 40)
    meas.temperature = rng.uniform(15, 30, 40)
    lines = write_measurements(meas, MODEL).splitlines()
    lines[3] = lines[3].replace(",", ", ")  # spaces after commas
    if limits == "warn":  # J2 beyond its limits on two rows
        for k in (5, 9):
            f = lines[k].split(",")
            f[2] = "80.5"
            lines[k] = ",".join(f)
    text = "\n".join(lines) + "\n"
    fast = parse_measurements(text, MODEL, limits=limits)
    monkeypatch.setattr(csvio, "_numeric_columns", lambda *a, **k: None)
    slow = parse_measurements(text, MODEL, limits=limits)
    for name in ("joints", "points", "payload", "sigma", "temperature", "timestamp"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name)), name
    assert fast.point_ids == slow.point_ids and fast.out_of_limits == slow.out_of_limits
    assert (fast.out_of_limits[0]["first_rows"] == [6, 10]) if limits == "warn" else not fast.out_of_limits


def test_written_points_keep_a_nanometre_in_metres_too():
    """write_measurements gives x, y, z to 1 nm in the model's unit: 6 decimals in mm, 9 in m (6 in m were 1 um,
    a thousand times a laser interferometer's noise)."""
    rng = np.random.default_rng(3)
    for unit, scale in (("mm", 1.0), ("m", 1000.0)):
        model = parse_model({"units": {"length": unit, "angle": "deg"}, "tool": [0.1 * 1000 / scale, 0, 0],
                             "joints": [{"name": "J1", "a": 0.0}, {"name": "J2", "a": 300.0 / scale}]})
        points = rng.uniform(-2000.0, 2000.0, (6, 3))
        text = write_measurements(Measurements(joints=rng.uniform(-1, 1, (6, 2)), points=points), model)
        assert np.abs(parse_measurements(text, model).points - points).max() < 1e-6
