import os

import pytest
import torch

from tests.threads import one_thread


def pytest_configure(config):
    """Under pytest-xdist (the README's ``-n 2``) each worker gets its share of the cores for torch, so that the
    workers' thread pools do not oversubscribe them."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(workers)))


@pytest.fixture
def single_thread():
    """Run the test with one torch thread (see tests/threads.py)."""
    with one_thread():
        yield
