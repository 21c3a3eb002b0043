import pytest

from tests.threads import one_thread


@pytest.fixture
def single_thread():
    """Run the test with one torch thread (see tests/threads.py)."""
    with one_thread():
        yield
