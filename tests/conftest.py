"""Test-wide fixtures."""
import logging

import pytest


@pytest.fixture(autouse=True)
def restore_root_logging():
    """Give each test back the root logger's handlers and level as they were.

    ``companion run`` called in-process (``cli.main``) installs its own stderr handler, bound to
    the stream pytest captured for that test; left in place, a later test's daemon thread would
    log into the closed stream ("--- Logging error ---").
    """
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
