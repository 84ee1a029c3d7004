import pytest
import torch


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Model tests run torch on one thread: on the shared 2-core CPU, OpenMP threads that spin-wait for
    each other make every render many times slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
