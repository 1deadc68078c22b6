"""Repository-wide pytest setup: every test gets a ROS domain of its own, so parallel test runs (and
other graphs on the machine) never see each other's topics, and node processes that a graph test leaves
shutting down (their stop grace period is up to 20 s) cannot be matched by the tests that follow."""
import os
import random

import pytest

_FIXED_DOMAIN = os.environ.get('FRODO_TEST_DOMAIN_ID')
_FIRST = random.Random(os.getpid()).randint(0, 129)
_next_test = 0
os.environ['ROS_DOMAIN_ID'] = _FIXED_DOMAIN or str(100 + _FIRST)


@pytest.fixture(autouse=True)
def _own_ros_domain():
    """Domains 100-229 (Fast DDS accepts up to 232), one per test, cycling; FRODO_TEST_DOMAIN_ID fixes one."""
    global _next_test
    if not _FIXED_DOMAIN:
        os.environ['ROS_DOMAIN_ID'] = str(100 + (_FIRST + _next_test) % 130)
        _next_test += 1
    yield
