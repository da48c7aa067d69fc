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


@pytest.fixture(scope="session", autouse=True)
def one_blas_thread():
    """The suite's matrices are small: one BLAS thread is faster, and much faster on a shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture(scope="session")
def null():
    """The null example and its compensation table (50 mm grid): (recording, table)."""
    from mtbudget.compensate import build_table

    rec = read_recording(example_recording("null"))
    return rec, build_table(rec, 50.0)


@pytest.fixture(scope="session")
def reversal():
    """The reversal_y example and its compensation table (50 mm grid): (recording, table)."""
    from mtbudget.compensate import build_table

    rec = read_recording(example_recording("reversal_y"))
    return rec, build_table(rec, 50.0)
