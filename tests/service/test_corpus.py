"""A corpus of broken CSVs and models: every one rejected with a problem document, nothing stored."""
from __future__ import annotations

import copy
import json
import time

import httpx
import pytest

from .conftest import sqlite_count, wait_for
from .test_api import assert_problem

MB = 1024 * 1024


@pytest.fixture(scope="module")
def robot_id(server, model_doc) -> str:
    r = server.client.post("/robots", json=model_doc)
    assert r.status_code == 201
    return r.json()["id"]


def _lines(csv_text: str) -> list[str]:
    return csv_text.strip().splitlines()


def _edit(csv_text: str, row: int, col: str, value: str) -> str:
    ls = _lines(csv_text)
    k = ls[0].split(",").index(col)
    f = ls[row].split(",")
    f[k] = value
    ls[row] = ",".join(f)
    return "\n".join(ls) + "\n"


def _drop_col(csv_text: str, col: str) -> str:
    ls = [ln.split(",") for ln in _lines(csv_text)]
    k = ls[0].index(col)
    return "\n".join(",".join(f[:k] + f[k + 1:]) for f in ls) + "\n"


def _with_timestamps(csv_text: str) -> str:
    ls = _lines(csv_text)
    return "\n".join([ls[0] + ",timestamp"] + [ln + f",2026-11-03T08:{i % 60:02d}:00+00:00"
                                               for i, ln in enumerate(ls[1:])]) + "\n"


def _add_col(csv_text: str, col: str, default: str, row: int, value: str) -> str:
    ls = _lines(csv_text)
    out = [ls[0] + "," + col] + [ln + "," + (value if k + 1 == row else default) for k, ln in enumerate(ls[1:])]
    return "\n".join(out) + "\n"


def _first_rows(csv_text: str, n: int, same: bool = False) -> str:
    ls = _lines(csv_text)
    rows = [ls[1].replace(ls[1].split(",")[0], f"Q{k}", 1) for k in range(n)] if same else ls[1:n + 1]
    return "\n".join([ls[0], *rows]) + "\n"


def _comment_row(csv_text: str, row: int) -> str:
    ls = _lines(csv_text)
    ls[row] = "#" + ls[row]
    return "\n".join(ls) + "\n"


BROKEN_CSV = {
    "empty": lambda c: b"",
    "only_comments": lambda c: b"# nothing here\n// still nothing\n",
    "header_only": lambda c: _lines(c)[0].encode() + b"\n",
    "binary": lambda c: bytes(range(256)) * 40,
    "utf16": lambda c: c.encode("utf-16"),
    "latin1": lambda c: (_lines(c)[0] + "\n" + "P\xe9," + ",".join(_lines(c)[1].split(",")[1:]) + "\n").encode("latin-1"),
    "missing_joint_column": lambda c: _drop_col(c, "J4").encode(),
    "missing_z": lambda c: _drop_col(c, "z").encode(),
    "duplicated_column": lambda c: "\n".join(ln + "," + ln.split(",")[3] for ln in _lines(c)).encode(),
    "unknown_column": lambda c: "\n".join([_lines(c)[0] + ",colour"] + [ln + ",red" for ln in _lines(c)[1:]]).encode(),
    "nan": lambda c: _edit(c, 5, "x", "nan").encode(),
    "inf": lambda c: _edit(c, 7, "J2", "-inf").encode(),
    "not_a_number": lambda c: _edit(c, 9, "y", "12,5").encode(),
    "out_of_limit_joint": lambda c: _edit(c, 3, "J3", "95.0").encode(),
    "out_of_limit_prismatic": lambda c: _edit(c, 4, "J6", "2400").encode(),
    "bad_timestamp": lambda c: _edit(_with_timestamps(c), 2, "timestamp", "yesterday at noon").encode(),
    "short_row": lambda c: ("\n".join(_lines(c)[:10] + [",".join(_lines(c)[10].split(",")[:5])]) + "\n").encode(),
    "duplicated_point_id": lambda c: _edit(c, 6, "point", "P0001").encode(),
    # issue 10: absurd but finite values never reach the numerics
    "coordinate_1e305": lambda c: _edit(c, 5, "x", "1e305").encode(),
    "coordinate_1e155": lambda c: _edit(c, 5, "z", "-1e155").encode(),
    "coordinate_1e30": lambda c: _edit(c, 5, "y", "1e30").encode(),
    "coordinate_overflows": lambda c: _edit(c, 5, "y", "1e400").encode(),
    "sigma_1e-300": lambda c: _add_col(c, "sigma", "0.02", 4, "1e-300").encode(),
    "sigma_1e200": lambda c: _add_col(c, "sigma", "0.02", 4, "1e200").encode(),
    "sigma_zero": lambda c: _add_col(c, "sigma", "0.02", 4, "0").encode(),
    "payload_1e308": lambda c: _add_col(c, "payload", "5", 6, "1e308").encode(),
    "payload_negative": lambda c: _add_col(c, "payload", "5", 6, "-2").encode(),
    "temperature_1e10": lambda c: _add_col(c, "temperature", "21.5", 3, "1e10").encode(),
    "timestamp_year_9999": lambda c: _edit(_with_timestamps(c), 3, "timestamp", "9999-12-31T00:00:00+00:00").encode(),
    "joint_1e200": lambda c: _edit(c, 3, "J4", "1e200").encode(),
    # issue 10: what csv and float() let through
    "field_over_131072_chars": lambda c: _edit(c, 4, "point", "P" * 131_073).encode(),
    "underscore_number": lambda c: _edit(c, 6, "x", "1_000").encode(),
    "unicode_digits": lambda c: _edit(c, 6, "J2", "\u0664\u0665").encode(),
    "fullwidth_digits": lambda c: _edit(c, 6, "z", "\uff13").encode(),
    "hash_point_id": lambda c: _comment_row(c, 7).encode(),
    "header_of_empty_columns": lambda c: b"," * 1_800_000 + b"\n" + _lines(c)[1].encode(),
    "nul_after_64k": lambda c: (c + "#" + " " * 70_000 + "\x00\n").encode(),
    "one_pose": lambda c: _first_rows(c, 1).encode(),
    "two_poses": lambda c: _first_rows(c, 2).encode(),
    "three_identical_poses": lambda c: _first_rows(c, 3, same=True).encode(),
}


@pytest.mark.parametrize("case", sorted(BROKEN_CSV))
def test_broken_csv_rejected_nothing_stored(server, robot_id, csv_text, case):
    before = sqlite_count(server.db_path, "measurement_sets")
    data = BROKEN_CSV[case](csv_text)
    r = server.client.post(f"/robots/{robot_id}/measurements", files={"file": (f"{case}.csv", data, "text/csv")})
    body = assert_problem(r, 422)
    assert body["errors"], body
    for e in body["errors"]:
        assert set(e) == {"row", "column", "value", "message"}, e
        assert e["message"]
    assert body["error_count"] >= len(body["errors"]) and len(body["errors"]) <= 50, body
    assert len(r.content) < 16384, len(r.content)  # bounded whatever the input
    assert sqlite_count(server.db_path, "measurement_sets") == before


def test_every_error_is_listed(server, robot_id, csv_text):
    bad = _edit(_edit(_edit(csv_text, 2, "J1", "-5"), 4, "x", "NaN"), 8, "J7", "abc")
    body = assert_problem(server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("b.csv", bad)}), 422)
    got = {(e["row"], e["column"]) for e in body["errors"]}
    assert got == {(3, "J1"), (5, "x"), (9, "J7")}  # row = line number in the file (header on line 1)


def test_upload_without_file_field(server, robot_id, csv_text):
    for r in (server.client.post(f"/robots/{robot_id}/measurements", files={"other": ("a.csv", csv_text)}),
              server.client.post(f"/robots/{robot_id}/measurements", content=b"x")):
        assert assert_problem(r, 422)["status"] == 422


def test_upload_to_missing_robot(server, csv_text):
    before = sqlite_count(server.db_path, "measurement_sets")
    assert_problem(server.client.post("/robots/nope/measurements", files={"file": ("a.csv", csv_text)}), 404)
    assert sqlite_count(server.db_path, "measurement_sets") == before


def _multipart_stream(total_bytes: int, boundary: str):
    """A multipart body with a CSV of total_bytes, generated on the fly (never held in memory)."""
    yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"huge.csv\"\r\n"
           "Content-Type: text/csv\r\n\r\n").encode()
    yield b"point,J1,J2,J3,J4,J5,J6,J7,x,y,z\n"
    line = b"P0001,1000,0,0,0,0,2000,0,1,2,3\n" * 2048
    sent = 0
    while sent < total_bytes:
        yield line
        sent += len(line)
    yield f"\r\n--{boundary}--\r\n".encode()


@pytest.mark.parametrize("declared", [True, False], ids=["content-length", "chunked"])
def test_100_mb_upload_is_413_and_streamed(server, robot_id, declared):
    """The limit is enforced while streaming: 413 long before the 100 MB are read, nothing stored."""
    before = sqlite_count(server.db_path, "measurement_sets")
    boundary = "calibtestboundary"
    total = 100 * MB
    headers = {"content-type": f"multipart/form-data; boundary={boundary}"}
    sent = {"n": 0}

    def body():
        for chunk in _multipart_stream(total, boundary):
            sent["n"] += len(chunk)
            yield chunk

    if declared:
        size = sum(len(c) for c in _multipart_stream(total, boundary))
        headers["content-length"] = str(size)
    with httpx.Client(base_url=server.url, timeout=60) as c:
        r = c.post(f"/robots/{robot_id}/measurements", content=body(), headers=headers)
    body_ = assert_problem(r, 413)
    assert "limit" in body_["detail"]
    assert sqlite_count(server.db_path, "measurement_sets") == before
    assert server.client.get("/health").status_code == 200


BROKEN_MODELS = {
    "empty_object": lambda m: {},
    "no_joints": lambda m: {**m, "joints": []},
    "joints_not_a_list": lambda m: {**m, "joints": "J1"},
    "bad_convention": lambda m: {**m, "convention": "euler"},
    "bad_units": lambda m: {**m, "units": {"length": "furlong", "angle": "deg"}},
    "duplicate_joint_names": lambda m: {**m, "joints": [m["joints"][0], m["joints"][0]]},
    "bad_joint_type": lambda m: {**m, "joints": [{**m["joints"][0], "type": "spherical"}]},
    "limits_reversed": lambda m: {**m, "joints": [{**m["joints"][1], "limits": [60, -60]}]},
    "prismatic_without_limits": lambda m: {**m, "joints": [{k: v for k, v in m["joints"][0].items() if k != "limits"}]},
    "string_length": lambda m: {**m, "joints": [{**m["joints"][1], "a": "long"}]},
    "negative_mass": lambda m: {**m, "joints": [{**m["joints"][1], "mass": -3}]},
    "tool_wrong_size": lambda m: {**m, "tool": [1, 2]},
    "joint_is_number": lambda m: {**m, "joints": [5]},
    "name_empty": lambda m: {**m, "name": "  "},
    # issue 10: plausibility ranges of the model
    "a_1e200": lambda m: {**m, "joints": [{**m["joints"][1], "a": 1e200}]},
    "d_1e305": lambda m: {**m, "joints": [{**m["joints"][1], "d": -1e305}]},
    "theta_1e200": lambda m: {**m, "joints": [{**m["joints"][1], "theta": 1e200}]},
    "mass_1e308": lambda m: {**m, "joints": [{**m["joints"][1], "mass": 1e308}]},
    "com_1e200": lambda m: {**m, "joints": [{**m["joints"][1], "com": [0, 1e200, 0]}]},
    "tool_1e305": lambda m: {**m, "tool": [1e305, 0, 0]},
    "gravity_in_mm_s2": lambda m: {**m, "gravity": [0, 0, -9810]},
    "gravity_1e300": lambda m: {**m, "gravity": [1e300, 0, 0]},
    "limits_1e9": lambda m: {**m, "joints": [{**m["joints"][0], "limits": [0, 1e9]}]},
    # issue 10: joint names that clash with CSV columns or cannot be headers
    "joint_named_x": lambda m: {**m, "joints": [{**m["joints"][1], "name": "x"}]},
    "joint_named_point": lambda m: {**m, "joints": [{**m["joints"][1], "name": "point"}]},
    "joint_named_timestamp": lambda m: {**m, "joints": [{**m["joints"][1], "name": "timestamp"}]},
    "joint_named_sigma": lambda m: {**m, "joints": [{**m["joints"][1], "name": "sigma"}]},
    "joint_with_comma": lambda m: {**m, "joints": [{**m["joints"][1], "name": "J,2"}]},
    "joint_with_quote": lambda m: {**m, "joints": [{**m["joints"][1], "name": 'J"2'}]},
    "joint_with_newline": lambda m: {**m, "joints": [{**m["joints"][1], "name": "J\n2"}]},
    "joint_with_spaces_around": lambda m: {**m, "joints": [{**m["joints"][1], "name": " J2 "}]},
    "joint_name_empty": lambda m: {**m, "joints": [{**m["joints"][1], "name": ""}]},
    "joint_name_is_a_list": lambda m: {**m, "joints": [{**m["joints"][1], "name": ["J2"]}]},
    # issue 10: strings a database cannot hold, JSON that only Python accepts, shapes beyond reason
    "name_201_chars": lambda m: {**m, "name": "r" * 201},
    "name_with_nul": lambda m: {**m, "name": "spray\x007"},
    "nan_in_extra_field": lambda m: {**m, "note": float("nan")},
    "infinity_in_extra_field": lambda m: {**m, "note": [float("-inf")]},
    "nul_in_extra_field": lambda m: {**m, "note": "a\x00b"},
    "nested_900_deep": lambda m: {**m, "note": _nested(900)},
    "joints_nested_900_deep": lambda m: {**m, "joints": _nested(900)},
    "units_are_lists": lambda m: {**m, "units": {"length": ["mm"], "angle": ["deg"]}},
}


def _nested(depth: int):
    v: list = []
    for _ in range(depth):
        v = [v]
    return v


@pytest.mark.parametrize("case", sorted(BROKEN_MODELS))
def test_broken_model_rejected_nothing_stored(server, model_doc, case):
    before = sqlite_count(server.db_path, "robots")
    raw = json.dumps(BROKEN_MODELS[case](copy.deepcopy(model_doc))).encode()  # NaN and Infinity as Python writes them
    r = server.client.post("/robots", content=raw, headers={"content-type": "application/json"})
    body = assert_problem(r, 422)
    assert body["errors"] and all({"field", "value", "message"} <= set(e) for e in body["errors"]), body
    assert body["error_count"] >= len(body["errors"]) and len(r.content) < 8192, body
    for e in body["errors"]:
        assert not any(w in e["message"] for w in ("unhashable", "Error", "Traceback", "'list'")), e
    assert sqlite_count(server.db_path, "robots") == before


@pytest.mark.parametrize("raw,status", [(b"", 422), (b"[]", 422), (b"null", 422), (b"\xff\xfe\x00", 400),
                                        (b'{"name": NaN}', 422), (json.dumps([1, 2]).encode(), 422)])
def test_non_object_models_rejected(server, raw, status):
    """Bytes that are not JSON text at all get FastAPI's 400; everything else 422; both problem documents."""
    before = sqlite_count(server.db_path, "robots")
    assert_problem(server.client.post("/robots", content=raw, headers={"content-type": "application/json"}), status)
    assert sqlite_count(server.db_path, "robots") == before


def test_nan_in_model_is_rejected(server, model_doc):
    raw = json.dumps(model_doc).replace('"d": 626', '"d": NaN').encode()
    body = assert_problem(server.client.post("/robots", content=raw, headers={"content-type": "application/json"}), 422)
    assert any("finite" in e["message"] for e in body["errors"]), body


# Issue 10: hostile input from the red team. Every answer a small problem document naming the field, never a 500.

@pytest.mark.parametrize("name", ["point", "x", "y", "z", "timestamp", "temperature", "payload", "payload_kg",
                                  "sigma", "target", "setup", "qw", "qx", "qy", "qz", "tau_J1", "#J2", "J\r2"])
def test_joint_names_that_clash_with_csv_columns_are_rejected(server, model_doc, name):
    before = sqlite_count(server.db_path, "robots")
    doc = copy.deepcopy(model_doc)
    doc["joints"][1]["name"] = name
    body = assert_problem(server.client.post("/robots", json=doc), 422)
    assert [e["field"] for e in body["errors"]] == ["joints[1].name"], body
    assert sqlite_count(server.db_path, "robots") == before


def test_error_responses_are_small_and_quick(server, robot_id):
    """A 1.8 MB header of empty columns and 100k rows of "x" for a calibration that does not exist: a few kB."""
    t = time.perf_counter()
    r = server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("h.csv", b"," * 1_800_000 + b"\n1\n")})
    body = assert_problem(r, 422)
    assert len(r.content) < 4096 and body["error_count"] >= 1, len(r.content)
    r = server.client.post("/calibrations/nope/predict", json={"joints": [["x"]] * 100_000})
    body = assert_problem(r, 413)  # over MAX_PREDICT_ROWS: refused before parsing (test_health_isolation.py)
    assert len(r.content) < 16384, len(r.content)
    assert body["items"] == 100_000 and body["field"] == "body.joints", body
    r = server.client.post("/calibrations/nope/predict", json={"joints": [["x"]] * 10_000})
    body = assert_problem(r, 422)
    assert len(r.content) < 16384, len(r.content)
    assert body["error_count"] == 10_000 and body["errors_truncated"] is True and len(body["errors"]) == 50
    assert time.perf_counter() - t < 15.0
    assert server.client.get("/health").status_code == 200


def test_csv_errors_are_capped_with_the_total(server, robot_id, csv_text):
    bad = csv_text
    for row in range(1, 121):
        bad = _edit(bad, row, "J2", "abc")
    body = assert_problem(server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("b.csv", bad)}), 422)
    assert len(body["errors"]) == 50 and body["error_count"] == 120 and body["errors_truncated"] is True
    assert body["total_errors"] == 120  # the older name stays
    assert "120 errors" in body["detail"]


def test_long_values_are_cut_in_errors(server, robot_id, csv_text):
    bad = _edit(csv_text, 3, "x", "9" * 100_000 + "x")
    r = server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("b.csv", bad)})
    body = assert_problem(r, 422)
    assert body["errors"][0]["row"] == 4 and body["errors"][0]["column"] == "x"
    assert len(r.content) < 4096


def test_field_over_the_csv_limit_names_its_row(server, robot_id, csv_text):
    body = assert_problem(server.client.post(f"/robots/{robot_id}/measurements", files={
        "file": ("b.csv", _edit(csv_text, 4, "point", "P" * 131_073))}), 422)
    assert [e["row"] for e in body["errors"]] == [5] and "131072" in body["errors"][0]["message"]


def test_too_few_poses_are_rejected_at_upload(server, robot_id, csv_text):
    for n in (1, 2):
        body = assert_problem(server.client.post(f"/robots/{robot_id}/measurements",
                                                 files={"file": ("few.csv", _first_rows(csv_text, n))}), 422)
        assert "at least 3" in body["detail"], body
    r = server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("three.csv", _first_rows(csv_text, 3))})
    assert r.status_code == 201, r.text


def test_second_file_part_is_rejected(server, robot_id, csv_text):
    before = sqlite_count(server.db_path, "measurement_sets")
    r = server.client.post(f"/robots/{robot_id}/measurements",
                           files=[("file", ("a.csv", csv_text)), ("file", ("b.csv", _edit(csv_text, 2, "x", "1")))])
    body = assert_problem(r, 422)
    assert "one" in body["detail"] and body["errors"][0]["field"] == "file"
    assert sqlite_count(server.db_path, "measurement_sets") == before


def _multipart(filename: bytes, data: bytes, boundary: str = "calibcorpus") -> tuple[bytes, dict]:
    """A multipart body written by hand: httpx would percent-encode a NUL in the filename."""
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"".encode() + filename
            + b"\"\r\nContent-Type: text/csv\r\n\r\n" + data + f"\r\n--{boundary}--\r\n".encode())
    return body, {"content-type": f"multipart/form-data; boundary={boundary}"}


@pytest.mark.parametrize("filename", [b"f" * 500 + b".csv", b"a\x00b.csv", b"a\x1bb.csv"])
def test_filenames_the_database_cannot_hold_are_rejected(server, robot_id, csv_text, filename):
    before = sqlite_count(server.db_path, "measurement_sets")
    content, headers = _multipart(filename, csv_text.encode())
    r = server.client.post(f"/robots/{robot_id}/measurements", content=content, headers=headers)
    body = assert_problem(r, 422)
    assert body["errors"][0]["field"] == "file.filename", body
    assert sqlite_count(server.db_path, "measurement_sets") == before


@pytest.mark.parametrize("path", ["/robots", "/jobs", "/calibrations/nope/predict", "/calibrations/nope/compensate"])
def test_json_nested_900_deep_is_422(server, path):
    raw = b'{"joints": ' + b"[" * 900 + b"]" * 900 + b', "measurement_set_id": ' + b"[" * 900 + b"]" * 900 + b"}"
    r = server.client.post(path, content=raw, headers={"content-type": "application/json"})
    assert_problem(r, 422)
    assert len(r.content) < 8192


@pytest.mark.parametrize("path, raw", [
    ("/robots", b'{"name": "r", "joints": [{"name": "J1", "a": Infinity}]}'),
    ("/jobs", b'{"measurement_set_id": NaN}'),
    ("/calibrations/nope/predict", b'{"joints": [[NaN]]}'),
    ("/calibrations/nope/predict", b'{"joints": [["1", "2"]]}'),
    ("/calibrations/nope/compensate", b'{"program_joints": [[-Infinity]]}'),
])
def test_nan_infinity_and_number_strings_are_422(server, path, raw):
    body = assert_problem(server.client.post(path, content=raw, headers={"content-type": "application/json"}), 422)
    assert body["errors"] and body["errors"][0]["field"], body


@pytest.mark.parametrize("path", ["/robots/a%00b", "/measurements/a%00b", "/jobs/a%00b", "/calibrations/a%00b",
                                  "/robots/" + "x" * 5000])
def test_ids_no_row_can_have_are_404(server, path):
    r = server.client.get(path)
    assert_problem(r, 404)
    assert len(r.content) < 4096


@pytest.fixture(scope="module")
def calibration_id(server, robot_id, csv_text) -> str:
    r = server.client.post(f"/robots/{robot_id}/measurements", files={"file": ("c.csv", csv_text)})
    assert r.status_code == 201, r.text
    j = server.client.post("/jobs", json={"measurement_set_id": r.json()["id"], "model": "geometric"}).json()

    def done():
        s = server.client.get(f"/jobs/{j['id']}").json()
        return s if s["status"] in ("succeeded", "failed") else None

    job = wait_for(done, 60, "the geometric job")
    assert job["status"] == "succeeded", job
    return job["calibration_id"]


POSE = [2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]


@pytest.mark.parametrize("call, body, field, words", [
    ("predict", {"joints": [["2000", 10, -20, 30, -40, 2000, 15]]}, "body.joints.0.0", "number"),
    ("predict", {"joints": [[True, 10, -20, 30, -40, 2000, 15]]}, "body.joints.0.0", "number"),
    ("predict", {"joints": [POSE[:2] + [1e200] + POSE[3:]]}, "body.joints[0][2]", "far outside"),
    ("predict", {"joints": [POSE[:2] + [150.0] + POSE[3:]]}, "body.joints[0][2]", "far outside"),
    ("predict", {"joints": [POSE], "payload": -1.0}, "body.payload", "between 0 and 10000 kg"),
    ("predict", {"joints": [POSE], "payload": 1e308}, "body.payload", "between 0 and 10000 kg"),
    ("predict", {"joints": [POSE], "temperature": 1e10}, "body.temperature", "deg C"),
    ("predict", {"joints": [POSE], "timestamp": "9999-01-01T00:00:00+00:00"}, "body.timestamp[0]", "2200"),
    ("predict", {"joints": [POSE, POSE], "sequence": [3, 1e13]}, "body.sequence[1]", "measurement order"),
    ("predict", {"joints": [POSE, POSE], "sequence": [3]}, "body.sequence", "one value per pose"),
    ("compensate", {"program_joints": [POSE], "payload": -5.0}, "body.payload", "between 0 and 10000 kg"),
    ("compensate", {"targets": [[1e305, 0, 0]], "seed_joints": [POSE]}, "body.targets[0][0]", "100 m"),
    ("compensate", {"targets": [[0, 0, 0]], "seed_joints": [POSE[:6] + [1e9]]}, "body.seed_joints[0][6]", "far outside"),
    ("compensate", {"program_joints": [["1"] * 7]}, "body.program_joints.0.0", "number"),
    ("compensate", {"tau": None, "program_joints": [], "target": []}, "body.program_joints", "at least 1"),
    ("compensate", {"targets": [], "seed_joints": []}, "body.targets", "at least 1"),
])
def test_predict_and_compensate_take_plausible_numbers_only(server, calibration_id, call, body, field, words):
    r = server.client.post(f"/calibrations/{calibration_id}/{call}", json=body)
    doc = assert_problem(r, 422)
    assert any(e["field"] == field and words in e["message"] for e in doc["errors"]), doc


def test_predict_within_the_widened_limits_still_answers(server, calibration_id):
    pose = POSE[:2] + [-84.0] + POSE[3:]  # J3 limits [-80, 80]: 4 deg beyond is within 10 % of the range
    r = server.client.post(f"/calibrations/{calibration_id}/predict", json={"joints": [pose], "payload": 0})
    assert r.status_code == 200, r.text


def test_validation_errors_are_plain_words(server):
    r = server.client.post("/robots", json={"name": "r", "units": {"length": ["mm"]}, "joints": [{"name": "J1"}]})
    body = assert_problem(r, 422)
    assert "unhashable" not in r.text and "Traceback" not in r.text, body
