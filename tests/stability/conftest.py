# One torch thread for these tests too (the reason is in tests/model/conftest.py).
from tests.model.conftest import one_torch_thread  # noqa: F401
