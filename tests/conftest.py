"""Fixtures shared by every test folder.

``one_torch_thread``: a module opts in with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``.
Torch is imported only when a test uses it.
"""

import pytest


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run the module's tests on one torch intra-op thread, then restore the previous count.

    Multi-threaded CPU reductions are not bit-reproducible run to run (exact-resume checks need one thread), and
    on a shared 2-core machine oversubscribed threads make rendering ~20x slower.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
