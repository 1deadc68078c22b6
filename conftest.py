"""Repository-wide pytest setup: each test process gets its own ROS domain, so parallel test runs
(and other graphs on the machine) never see each other's topics."""
import os
import random

os.environ['ROS_DOMAIN_ID'] = os.environ.get('FRODO_TEST_DOMAIN_ID') or str(random.Random(os.getpid()).randint(100, 200))
