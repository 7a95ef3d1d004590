"""The console script: `calib db upgrade` migrates a fresh database (`calib demo`: see test_demo.py)."""
from __future__ import annotations

import sqlite3
import subprocess
import sys

from .conftest import ROOT, base_env


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
