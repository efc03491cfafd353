"""The ``ros`` fixture of the DDS tests: one :class:`node_harness.Harness` per test."""

from node_harness import Harness
import pytest


@pytest.fixture
def ros(tmp_path):
    """Yield a harness with the test's own context and namespace; close it afterwards."""
    harness = Harness(tmp_path)
    yield harness
    harness.close()
