"""A corpus of broken CSVs and models: every one rejected with a problem document, nothing stored."""
from __future__ import annotations

import copy
import json

import httpx
import pytest

from .conftest import sqlite_count
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
}


@pytest.mark.parametrize("case", sorted(BROKEN_MODELS))
def test_broken_model_rejected_nothing_stored(server, model_doc, case):
    before = sqlite_count(server.db_path, "robots")
    r = server.client.post("/robots", json=BROKEN_MODELS[case](copy.deepcopy(model_doc)))
    body = assert_problem(r, 422)
    assert body["errors"] and all({"field", "value", "message"} <= set(e) for e in body["errors"]), body
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
