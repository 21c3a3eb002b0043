"""One torch thread for tests of tiny models: faster, and immune to OpenMP oversubscription when the
2-core machine is busy. The previous thread count is restored afterwards."""

from contextlib import contextmanager

import torch


@contextmanager
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
