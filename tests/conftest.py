import os
from pathlib import Path

import numpy as np
import pytest


def _per_worker_postgres() -> None:
    """Under pytest-xdist (scripts/test runs the suite on every core) each worker gets a PostgreSQL database of its
    own, `<database>_<worker id>` on the server named by CALIB_TEST_POSTGRES_URL, created there when missing: the
    queue tests drop and rebuild the schema of the database they are given, so two workers must never share one.

    Runs when this file is imported, before tests/service/conftest.py reads the variable (its PG_URL)."""
    url, worker = os.environ.get("CALIB_TEST_POSTGRES_URL"), os.environ.get("PYTEST_XDIST_WORKER")
    if not url or not worker:
        return
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    base = make_url(url)
    name = f"{base.database}_{worker}"
    eng = create_engine(base, isolation_level="AUTOCOMMIT")  # CREATE DATABASE may not run in a transaction
    try:
        with eng.connect() as c:
            if not c.execute(text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": name}).first():
                c.execute(text(f'CREATE DATABASE "{name}"'))
    finally:
        eng.dispose()
    os.environ["CALIB_TEST_POSTGRES_URL"] = base.set(database=name).render_as_string(hide_password=False)


_per_worker_postgres()


@pytest.fixture
def seed(request) -> int:
    """A fresh seed per run (not a lucky constant); printed on failure via the assert messages.

    Set CALIB_TEST_SEED to replay a failing draw.
    """
    s = int(os.environ.get("CALIB_TEST_SEED", np.random.SeedSequence().entropy % 2**31))
    request.node.user_properties.append(("seed", s))
    return s


# The suite on several cores: `scripts/test` with no arguments runs pytest-xdist with `--dist loadscope`, whose units of
# work are chosen here. A service test module is one unit, so its module fixtures (a `calib serve` each, whose job,
# parse and plan processes take seconds of CPU to warm) start once; the modules that read the Motoman's `calib demo`
# (the session fixture motoman_demo, a minute of CPU) are one unit together; every other test is a unit of its own.
# (pytest-xdist's own xdist_group marks do nothing under pytest 9.2, which ignores the node ids xdist rewrites.)
MOTOMAN_DEMO = "motoman_demo"


def _scope_of(service_tests: Path):
    together = {f"tests/service/{f.name}" for f in service_tests.glob("test_*.py") if MOTOMAN_DEMO in f.read_text()}

    def scope(nodeid: str) -> str:
        module = nodeid.split("::", 1)[0]
        if module in together:
            return MOTOMAN_DEMO
        return module if module.startswith("tests/service/") else nodeid

    return scope


def pytest_xdist_make_scheduler(config, log):
    if config.getoption("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Scheduling(LoadScopeScheduling):
        """loadscope's (units with more tests first), with the units above."""

        _split_scope = staticmethod(_scope_of(Path(__file__).parent / "service"))

    return Scheduling(config, log)


def pytest_collection_modifyitems(config, items):
    """On an xdist worker: the service's tests first. loadscope hands out the units with more tests first and the rest
    in this order, so the long single-test service modules (schemathesis, the plan pool) start before the core's many
    short tests, which then fill in behind them."""
    if getattr(config, "workerinput", None):
        items.sort(key=lambda item: not item.nodeid.startswith("tests/service/"))
