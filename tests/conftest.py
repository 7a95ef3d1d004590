import os

import numpy as np
import pytest


@pytest.fixture
def seed(request) -> int:
    """A fresh seed per run (not a lucky constant); printed on failure via the assert messages.

    Set CALIB_TEST_SEED to replay a failing draw.
    """
    s = int(os.environ.get("CALIB_TEST_SEED", np.random.SeedSequence().entropy % 2**31))
    request.node.user_properties.append(("seed", s))
    return s
