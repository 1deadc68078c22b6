"""A robot install runs shape_node (and optim_node, which uses this package's prior) without the renderer:
their modules must not import frodo_datasets, and package.xml must not depend on it at run time (training
and prior evaluation import it inside their functions)."""
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

PACKAGES = Path(__file__).resolve().parents[2]


def test_shape_and_optim_nodes_do_not_import_frodo_datasets():
    code = ('import sys, frodo_shape.shape_node, frodo_shape.prior, frodo_shape.train, frodo_shape.evaluate_prior, '
            'frodo_optim.optim_node; print(sorted(m for m in sys.modules if m.startswith("frodo_datasets")))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == '[]', out.stdout


def test_runtime_node_packages_do_not_depend_on_frodo_datasets_at_run_time():
    for package in ('frodo_detection', 'frodo_association', 'frodo_shape', 'frodo_optim', 'frodo_common'):
        root = ET.parse(PACKAGES / package / 'package.xml').getroot()
        run_time = {e.text for tag in ('depend', 'exec_depend', 'build_export_depend') for e in root.iter(tag)}
        assert 'frodo_datasets' not in run_time, package
