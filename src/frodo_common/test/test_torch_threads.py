"""call_in_passing_thread: result and exceptions come back, and the OpenMP team torch work starts in it ends
with it (counted as the process's OS threads, in a fresh interpreter)."""
import os
import subprocess
import sys
import textwrap

import pytest

from frodo_common.torch_threads import call_in_passing_thread


def test_returns_the_result_and_raises_the_error():
    assert call_in_passing_thread(lambda: 41 + 1) == 42

    def fail():
        raise ValueError('no prior')
    with pytest.raises(ValueError, match='no prior'):
        call_in_passing_thread(fail)


THREAD_COUNT = textwrap.dedent("""
    import os, sys, time, torch
    from frodo_common.torch_threads import call_in_passing_thread
    torch.set_num_threads(2)
    def work():
        x = torch.randn(256, 256)
        for _ in range(20):
            x = torch.tanh(x @ x)
        return float(x.sum())
    before = len(os.listdir('/proc/self/task'))
    if sys.argv[1] == 'passing':
        call_in_passing_thread(work)
    else:
        work()
    # the ended team's helper leaves a moment after the join (later on a loaded machine): wait up to 5 s
    deadline = time.monotonic() + 5.0
    while len(os.listdir('/proc/self/task')) > before and time.monotonic() < deadline:
        time.sleep(0.05)
    print(len(os.listdir('/proc/self/task')) - before)
""")


@pytest.mark.skipif(not os.path.isdir('/proc/self/task'), reason='needs Linux /proc')
def test_openmp_team_ends_with_the_passing_thread():
    def added_threads(mode: str) -> int:
        out = subprocess.run([sys.executable, '-c', THREAD_COUNT, mode], capture_output=True, text=True,
                             check=True, env=dict(os.environ, OMP_NUM_THREADS='2'))
        return int(out.stdout.split()[-1])
    assert added_threads('main') >= 1      # the main thread's team stays: its helper thread lives on
    assert added_threads('passing') == 0   # the passing thread's team went with it
