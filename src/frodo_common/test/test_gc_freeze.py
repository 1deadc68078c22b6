"""run_node freezes the objects built at startup: a full garbage collection, which holds the GIL and so delays
the /diagnostics thread, then no longer traverses them (optim_node: ~400k objects, 0.5-1 s per collection)."""
import gc

from frodo_common.node import freeze_startup_objects


def test_startup_objects_leave_the_collected_generations():
    startup = [[i] for i in range(50_000)]          # stand-in for modules, models and priors loaded at startup
    try:
        before = len(gc.get_objects())
        frozen = freeze_startup_objects()
        after = len(gc.get_objects())                      # what a full collection traverses from now on
        assert frozen >= len(startup) and before - after >= len(startup)
        later = [[i] for i in range(1000)]            # objects made while running are still collected
        assert len(gc.get_objects()) >= after + len(later) - 10
    finally:
        gc.unfreeze()
