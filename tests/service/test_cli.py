"""The console script: `calib db upgrade` migrates a fresh database (`calib demo`: see test_demo.py)."""
from __future__ import annotations

import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from .conftest import PG_URL, ROOT, base_env


def calib(*args, env=None):
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)


def test_db_upgrade_creates_the_schema(tmp_path):
    db = tmp_path / "m.db"
    r = calib("db", "upgrade", env=base_env(f"sqlite:///{db}"))
    assert r.returncode == 0, r.stderr
    with sqlite3.connect(db) as c:
        tables = {t for (t,) in c.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        assert c.execute("PRAGMA journal_mode").fetchone()[0] in ("wal", "delete")
    assert {"robots", "measurement_sets", "jobs", "calibrations", "alembic_version"} <= tables
    assert calib("db", "upgrade", env=base_env(f"sqlite:///{db}")).returncode == 0  # idempotent


@pytest.mark.parametrize("kind", ["sqlite", "postgres"])
def test_migration_0003_keeps_old_sets_and_matches_the_models(kind, tmp_path):
    """0002 -> head on a database holding a measurement set: the new columns are null (read as no instrument,
    limits=reject), the schema equals the ORM models, and downgrade/upgrade round-trips."""
    from alembic import command
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext
    from sqlalchemy import create_engine, text

    from service.cli import alembic_config
    from service.models import Base

    if kind == "sqlite":
        url = f"sqlite:///{tmp_path / 'm.db'}"
    else:
        if not PG_URL:
            pytest.skip("CALIB_TEST_POSTGRES_URL is not set (.ci/run starts a PostgreSQL server)")
        url = PG_URL
        eng = create_engine(url)
        with eng.begin() as c:
            c.execute(text("DROP SCHEMA IF EXISTS public CASCADE"))
            c.execute(text("CREATE SCHEMA public"))
        eng.dispose()
    cfg = alembic_config(url)
    command.upgrade(cfg, "0002")
    eng = create_engine(url)
    try:
        with eng.begin() as c:
            c.execute(text("INSERT INTO robots (id, name, model_json, joint_names, created_at) "
                           "VALUES ('r1', 'old', '{}', '[]', 0)"))
            c.execute(text("INSERT INTO measurement_sets (id, robot_id, filename, n_poses, columns, size_bytes, "
                           "sha256, raw, created_at) VALUES ('m1', 'r1', NULL, 3, '[]', 1, 'x', :raw, 0)"),
                      {"raw": b"x"})
        command.upgrade(cfg, "head")
        with eng.connect() as c:
            assert c.execute(text("SELECT instrument, limits, out_of_limits FROM measurement_sets")).all() == \
                [(None, None, None)]
            assert compare_metadata(MigrationContext.configure(c), Base.metadata) == []
        command.downgrade(cfg, "0002")
        command.upgrade(cfg, "head")
    finally:
        eng.dispose()


def test_demo_takes_instrument_and_limits(tmp_path):
    from calib_core.instruments import INSTRUMENTS
    from service import cli

    assert tuple(INSTRUMENTS) == cli.INSTRUMENTS
    r = calib("demo", "--instrument", "ruler", env=base_env(f"sqlite:///{tmp_path / 'd.db'}"))
    assert r.returncode == 2 and "--instrument" in r.stderr and "motion_capture" in r.stderr
    r = calib("demo", "--limits", "ignore", env=base_env(f"sqlite:///{tmp_path / 'd.db'}"))
    assert r.returncode == 2 and "--limits" in r.stderr and "warn" in r.stderr


def test_demo_reads_local_data_with_the_same_limits_mode(tmp_path, model_doc, csv_text):
    """`calib demo --data` parses the CSV locally (for its hold-out split) with --limits too."""
    import json

    from service import demo

    doc = {**model_doc, "joints": [dict(j, limits=[-40, 40]) if j["name"] == "J2" else j for j in model_doc["joints"]]}
    (tmp_path / "m.json").write_text(json.dumps(doc))
    (tmp_path / "d.csv").write_text(csv_text)
    with pytest.raises(demo.DemoError, match="outside the joint limits"):
        demo.from_files(tmp_path / "m.json", tmp_path / "d.csv", 0)
    camp = demo.from_files(tmp_path / "m.json", tmp_path / "d.csv", 0, "motion_capture", "warn")
    assert camp.cal.n_poses + camp.val.n_poses == 150 and camp.cal.instrument == "motion_capture"
    (tmp_path / "s.csv").write_text(csv_text.replace(",", ";"))  # one error, on the header's row: said so
    with pytest.raises(demo.DemoError, match=r"\(1 error\):\n    row 1: the fields are separated by ';'"):
        demo.from_files(tmp_path / "m.json", tmp_path / "s.csv", 0)


def test_a_stopped_server_leaves_nothing_in_the_temporary_directory(tmp_path):
    """`calib serve` stopped by SIGTERM (systemd, docker stop) shuts down gracefully and then runs its exit handlers:
    the fork server's socket directory (pymp-*) used to stay behind in /tmp at every stop."""
    from .conftest import Server

    tmp = Path(tempfile.mkdtemp(prefix="calib-t"))  # short: the fork server's socket path must fit in 107 bytes, and
    s = Server(f"sqlite:///{tmp_path / 'calib.db'}", tmp_path / "server.log", TMPDIR=tmp)  # tmp_path grows with
    # pytest's run count (a clean clone's run 103 of this machine made it 109: the server refused to start)
    assert [p.name for p in tmp.iterdir() if p.name.startswith("pymp-")], "the fork server's directory, while up"
    s.stop()
    assert s.p.returncode == 128 + 15, (s.p.returncode, s.output()[-2000:])
    assert not list(tmp.iterdir()), list(tmp.iterdir())
    tmp.rmdir()


def test_a_temporary_directory_too_long_for_the_fork_servers_socket_is_said(tmp_path):
    """A TMPDIR whose path leaves no room for the fork server's socket (a Unix socket's path holds 107 bytes) stops
    `calib serve` with one line saying so and what to do, not a traceback."""
    tmp = tmp_path / ("t" * 90)
    tmp.mkdir()
    r = calib("serve", "--port", "0", env={**base_env(f"sqlite:///{tmp_path / 'c.db'}"), "TMPDIR": str(tmp)})
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert f"the temporary directory {tmp} ({len(str(tmp))} characters) is too long" in r.stderr, r.stderr[-2000:]
    assert "set TMPDIR to a shorter directory" in r.stderr
