"""The machine figures are measured on, named once for every benchmark and report, and its math library set up
for reproducible results (no ROS, no torch)."""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def git_commit(cwd: str | os.PathLike | None = None, length: int = 10) -> str:
    """Short commit of the git checkout at `cwd` (default: the working directory); '' outside one."""
    try:
        return subprocess.run(['git', 'rev-parse', f'--short={length}', 'HEAD'], cwd=cwd, capture_output=True,
                              text=True, check=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ''


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux; the platform's processor name elsewhere)."""
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def memory_gb() -> float:
    """Physical memory in GiB (NaN where the platform does not say)."""
    try:
        return os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2 ** 30
    except (ValueError, OSError, AttributeError):
        return float('nan')


# Intel MKL (torch's CPU BLAS) picks kernels by memory alignment and may change its thread count with the load,
# so the same matrix products can round differently from run to run, and an optimisation of 40 steps ends
# elsewhere. These settings make them reproducible for a fixed number of threads; they act only when set before
# torch is imported.
REPRODUCIBLE_MATH_ENV = {'MKL_CBWR': 'AUTO', 'MKL_DYNAMIC': 'FALSE'}


def reproducible_math() -> bool:
    """Ask MKL for run-to-run reproducible results (`REPRODUCIBLE_MATH_ENV`; values the user set are kept).
    False when torch is already imported (too late to take effect)."""
    import sys
    for key, value in REPRODUCIBLE_MATH_ENV.items():
        os.environ.setdefault(key, value)
    return 'torch' not in sys.modules
