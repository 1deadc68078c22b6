"""Repository-wide pytest setup: every test gets a ROS domain of its own, so parallel test runs (and
other graphs on the machine) never see each other's topics, and node processes that a graph test leaves
shutting down (their stop grace period is up to 20 s) cannot be matched by the tests that follow."""
import os
import random
import time

import pytest

_FIXED_DOMAIN = os.environ.get('FRODO_TEST_DOMAIN_ID')
_DOMAINS = list(range(100, 230))     # Fast DDS accepts ids up to 232
_FIRST = random.Random(os.getpid()).randint(0, len(_DOMAINS) - 1)
# A test that ran this long may have started node processes (an import of rclpy alone takes longer); its domain
# is not handed out again for REUSE_AFTER_S: a run of fast unit tests cycles through all ids within seconds, and a
# CI run once had a later test match the subscriptions of such a test's nodes.
SLOW_TEST_S = 0.5
REUSE_AFTER_S = 60.0
_next = _FIRST
_busy_until: dict[int, float] = {}
os.environ['ROS_DOMAIN_ID'] = _FIXED_DOMAIN or str(_DOMAINS[_FIRST])


def _free_domain() -> int:
    """The next id in the cycle that no slow test used in the last REUSE_AFTER_S (else the one free soonest)."""
    global _next
    now = time.monotonic()
    order = [_DOMAINS[(_next + k) % len(_DOMAINS)] for k in range(len(_DOMAINS))]
    free = [d for d in order if _busy_until.get(d, 0.0) <= now]
    domain = free[0] if free else min(order, key=lambda d: _busy_until[d])
    _next = (_DOMAINS.index(domain) + 1) % len(_DOMAINS)
    return domain


@pytest.fixture(autouse=True)
def _own_ros_domain():
    """One domain per test (see _free_domain); FRODO_TEST_DOMAIN_ID fixes one."""
    if _FIXED_DOMAIN:
        yield
        return
    domain = _free_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    started = time.monotonic()
    yield
    ended = time.monotonic()
    if ended - started >= SLOW_TEST_S:
        _busy_until[domain] = ended + REUSE_AFTER_S
