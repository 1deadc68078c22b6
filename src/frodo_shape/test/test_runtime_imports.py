"""A robot install runs shape_node (and optim_node, which uses this package's prior) without the renderer:
their modules must not import frodo_datasets, and no dependency leads to it (training and prior evaluation
import it inside their functions)."""
import json
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


def test_a_robot_build_of_the_runtime_nodes_does_not_pull_frodo_datasets():
    """Neither package.xml (any dependency type: colcon builds test dependencies too) nor colcon.meta's extra
    dependencies lead from the four node packages to frodo_datasets."""
    runtime = ('frodo_detection', 'frodo_association', 'frodo_shape', 'frodo_optim', 'frodo_common')
    meta = json.loads((PACKAGES.parent / 'colcon.meta').read_text())['names']
    for package in runtime:
        root = ET.parse(PACKAGES / package / 'package.xml').getroot()
        declared = {e.text for e in root if e.tag.endswith('depend')}
        assert 'frodo_datasets' not in declared, package
        assert 'frodo_datasets' not in meta.get(package, {}).get('dependencies', []), package


def test_the_offline_pipeline_and_the_optimiser_do_not_import_torchvision():
    """torchvision (with torch._dynamo, ~1 s) is needed only by the Mask R-CNN backend, imported when it is built."""
    code = ('import sys, frodo_bringup.pipeline, frodo_optim.optim_node, frodo_shape.shape_node; '
            'print(sorted(m for m in sys.modules if m.startswith("torchvision")))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == '[]', out.stdout
