"""The machine's name and memory, as every benchmark and report states them."""
import math

from frodo_common import host


def test_the_cpu_is_named_and_memory_is_positive():
    assert host.cpu_model().strip()
    memory = host.memory_gb()
    assert math.isnan(memory) or memory > 0.1


def test_without_cpuinfo_the_platform_name_is_used(monkeypatch):
    monkeypatch.setattr(host, 'Path', lambda path: type('Missing', (), {'read_text': lambda self: (_ for _ in ()).throw(OSError)})())
    monkeypatch.setattr(host.platform, 'processor', lambda: 'test-cpu')
    assert host.cpu_model() == 'test-cpu'


def test_reproducible_math_sets_mkl_once_and_keeps_the_users_values(monkeypatch):
    monkeypatch.delenv('MKL_CBWR', raising=False)
    monkeypatch.setenv('MKL_DYNAMIC', 'TRUE')               # the user's choice stays
    import sys
    in_time = host.reproducible_math()
    assert host.os.environ['MKL_CBWR'] == 'AUTO' and host.os.environ['MKL_DYNAMIC'] == 'TRUE'
    assert in_time == ('torch' not in sys.modules)
