import numpy as np
import pytest

from mtbudget.config import example_recording, load_config
from mtbudget.recording import read_recording

EXAMPLES = ("null", "thermal_x", "reversal_y", "tracker_drift")


@pytest.fixture(scope="session")
def null_recording():
    return read_recording(example_recording("null"))


@pytest.fixture(scope="session")
def default_config():
    return load_config()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
