"""Every src/frodo_*/package.xml declares what its package imports, and imports what it declares.

`rosdep install --from-paths src` and a robot's colcon build know a package's dependencies only from its
package.xml; an import missing there works in this workspace (the venv has everything) and fails on the robot.
So the imports of each package's modules (all non-test .py files of the package folder: its Python package and
launch files; setup.py is the build's and needs only setuptools) are read with `ast`, every import statement,
module level or inside a function, and each third-party module is mapped to its rosdep key through KEYS below.

Conventions (the package.xml comments say the same):
- rosdep keys where rosdistro has one (python3-numpy, ...); pip-only modules have `python3-<pip name>-pip` keys,
  rosdistro's convention for pip packages; those rosdistro lacks are defined in the repository's rosdep.yaml
  (LOCAL_PIP_KEYS, checked against that file).
- ROS packages (rclpy, message packages, launch) and frodo packages are declared by their package name.
- an import guarded by `try: ... except ImportError` is declared like any other (the guard is for a pip-only
  install without the ROS share; a ROS install has it).
- deliberate exceptions are listed, each with its reason, in NOT_DECLARED (imported, on purpose not declared)
  and NOT_IMPORTED (declared, never imported).
"""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / 'src'
PACKAGES = sorted(p.name for p in SRC.glob('frodo_*') if (p / 'package.xml').is_file())

# Import name (top-level module) -> the package.xml key that installs it. One table for every package.
KEYS = {
    # rosdistro rosdep keys (system packages)
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'yaml': 'python3-yaml',
    'cv2': 'python3-opencv',
    'matplotlib': 'python3-matplotlib',
    'skimage': 'python3-skimage',
    'PIL': 'python3-pil',
    'tqdm': 'python3-tqdm',
    'psutil': 'python3-psutil',
    'torch': 'python3-torch',
    'torchvision': 'python3-torchvision',
    'pytest': 'python3-pytest',
    'hypothesis': 'python3-hypothesis',
    # rosdistro pip keys
    'trimesh': 'python3-trimesh-pip',
    'rosbags': 'python3-rosbags-pip',
    # pip keys rosdistro lacks: defined in rosdep.yaml
    'mcap': 'python3-mcap-pip',
    'rerun': 'python3-rerun-sdk-pip',
    'manifold3d': 'python3-manifold3d-pip',
}
# Submodules that need a package of their own besides their top-level module's.
SUBMODULE_KEYS = {
    'trimesh.ray.ray_pyembree': 'python3-embreex-pip',   # trimesh's embree ray engine imports embreex
}
# ROS packages: import name == package.xml key.
ROS_PACKAGES = {
    'rclpy', 'launch', 'launch_ros', 'ament_index_python',
    'std_msgs', 'std_srvs', 'geometry_msgs', 'sensor_msgs', 'visualization_msgs', 'diagnostic_msgs',
    'rcl_interfaces', 'builtin_interfaces', 'rosgraph_msgs',
}
# Keys that rosdistro does not define: rosdep.yaml does (see its header for the sources.list.d line).
LOCAL_PIP_KEYS = {'python3-mcap-pip', 'python3-rerun-sdk-pip', 'python3-manifold3d-pip', 'python3-embreex-pip'}

# (package, import) imported but on purpose not declared: only inside functions (checked), never by a node.
NOT_DECLARED = {
    # The renderer is not part of a robot install of the runtime nodes (test_runtime_imports in both packages):
    # only the evaluation's rendered-furniture scenes (synthetic.py) import it, inside a function.
    ('frodo_association', 'frodo_datasets'): 'evaluation scenes only; a robot install has no renderer',
    # Training and prior evaluation (train.py, evaluate_prior.py) import it inside their functions.
    ('frodo_shape', 'frodo_datasets'): 'training and prior evaluation only; a robot install has no renderer',
}
# (package, key) declared as exec_depend but imported by none of its modules, each with why it is needed.
NOT_IMPORTED: dict[tuple[str, str], str] = {}

DEPEND_TAGS = {'depend', 'exec_depend', 'build_export_depend'}   # what the installed package needs at run time


@dataclass(frozen=True)
class Import:
    """One imported module as written (`trimesh.ray.ray_pyembree`), where, and how."""

    module: str
    path: str
    line: int
    lazy: bool = False      # inside a function: needed only when that function runs
    guarded: bool = False   # inside `try:` with an `except ImportError` (or ModuleNotFoundError)

    @property
    def top(self) -> str:
        return self.module.split('.')[0]

    def where(self) -> str:
        return f'{self.path}:{self.line}'


def _catches_import_error(node: ast.Try) -> bool:
    names = set()
    for handler in node.handlers:
        if handler.type is None:
            return True
        for n in ast.walk(handler.type):
            if isinstance(n, ast.Name):
                names.add(n.id)
            elif isinstance(n, ast.Attribute):
                names.add(n.attr)
    return bool(names & {'ImportError', 'ModuleNotFoundError', 'Exception', 'BaseException'})


def scan_source(source: str, path: str = '<string>') -> list[Import]:
    """Every absolute import of `source` (relative imports are the package's own), with its context."""
    found: list[Import] = []

    def visit(node: ast.AST, lazy: bool, guarded: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend(Import(a.name, path, node.lineno, lazy, guarded) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append(Import(node.module, path, node.lineno, lazy, guarded))
            # `from trimesh.ray import ray_pyembree` imports trimesh.ray.ray_pyembree
            found.extend(Import(f'{node.module}.{a.name}', path, node.lineno, lazy, guarded)
                         for a in node.names if f'{node.module}.{a.name}' in SUBMODULE_KEYS)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            lazy = True
        if isinstance(node, ast.Try) and _catches_import_error(node):
            for child in node.body:
                visit(child, lazy, True)
            for child in node.handlers + node.orelse + node.finalbody:
                visit(child, lazy, guarded)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, lazy, guarded)

    visit(ast.parse(source, path), False, False)
    return found


def package_modules(package: str) -> list[Path]:
    """The package's non-test Python files: its Python package(s), launch files, scripts; not setup.py."""
    root = SRC / package
    return sorted(p for p in root.rglob('*.py')
                  if p.relative_to(root).parts[0] not in ('test', 'build', 'install')
                  and not p.relative_to(root).parts[0].endswith('.egg-info') and p != root / 'setup.py')


def own_modules(package: str) -> set[str]:
    """Top-level import names the package provides itself (its Python packages and modules)."""
    root = SRC / package
    names = {p.name for p in root.iterdir() if (p / '__init__.py').is_file()}
    return names | {package}


def package_imports(package: str) -> list[Import]:
    root = SRC / package
    return [imp for path in package_modules(package)
            for imp in scan_source(path.read_text(), str(path.relative_to(root)))]


def key_of(module: str) -> str | None:
    """The package.xml key of an import name, None when the table does not know it."""
    if module in ROS_PACKAGES or module in PACKAGES:
        return module
    return KEYS.get(module)


def declared_keys(package_xml: str, tags: set[str] = DEPEND_TAGS) -> set[str]:
    root = ET.fromstring(package_xml)
    return {(e.text or '').strip() for e in root if e.tag in tags}


def problems(package: str, declared: set[str], imports: list[Import], own: set[str],
             not_declared: dict = NOT_DECLARED, not_imported: dict = NOT_IMPORTED) -> list[str]:
    """What is wrong with `package`'s declared run-time keys against its imports; [] when nothing is."""
    out = []
    needed: dict[str, list[Import]] = {}
    for imp in imports:
        if imp.top in own or imp.top in sys.stdlib_module_names or imp.top == '__future__':
            continue
        if (package, imp.top) in not_declared:
            if not imp.lazy:
                out.append(f'{package}: {imp.where()} imports {imp.top} at module level, but NOT_DECLARED '
                           f'allows it only inside functions ({not_declared[package, imp.top]})')
            continue
        key = key_of(imp.top)
        if key is None:
            out.append(f'{package}: {imp.where()} imports {imp.top}, which the KEYS table of tests/test_packaging.py '
                       'does not map to a package.xml key: add it there (rosdep key, or python3-<pip name>-pip)')
            continue
        needed.setdefault(key, []).append(imp)
        for prefix, extra in SUBMODULE_KEYS.items():
            if imp.module == prefix or imp.module.startswith(prefix + '.'):
                needed.setdefault(extra, []).append(imp)
    for key, uses in sorted(needed.items()):
        if key not in declared:
            first = uses[0]
            out.append(f'{package}: imports {first.module} ({first.where()}'
                       f'{f" and {len(uses) - 1} more" if len(uses) > 1 else ""}) but package.xml does not declare '
                       f'<exec_depend>{key}</exec_depend>')
    for key in sorted(declared - set(needed)):
        if (package, key) not in not_imported:
            out.append(f'{package}: package.xml declares {key} but no module of the package imports it: remove it, '
                       'or list it with the reason in NOT_IMPORTED of tests/test_packaging.py')
    return out


# ---------------------------------------------------------------- the scanner itself
TINY = '''
from __future__ import annotations
import os, numpy as np
import xml.etree.ElementTree as ET
from scipy.spatial import cKDTree
from . import sibling
from .core import thing
from frodo_tiny.core import other
from trimesh.ray.ray_pyembree import RayMeshIntersector

def render():
    import cv2
    return cv2

try:
    import rerun as rr
except ImportError:
    rr = None
'''


def test_scanner_finds_every_import_with_its_context():
    found = {imp.module: imp for imp in scan_source(TINY, 'tiny.py')}
    assert set(found) == {'__future__', 'os', 'numpy', 'xml.etree.ElementTree', 'scipy.spatial', 'frodo_tiny.core',
                          'trimesh.ray.ray_pyembree', 'cv2', 'rerun'}
    assert found['cv2'].lazy and not found['cv2'].guarded and found['cv2'].where() == 'tiny.py:12'
    assert found['rerun'].guarded and not found['rerun'].lazy
    assert not found['numpy'].lazy and not found['numpy'].guarded


def test_problems_name_package_import_and_missing_key():
    imports = scan_source(TINY, 'tiny.py')
    declared = {'python3-numpy', 'python3-scipy', 'python3-opencv', 'python3-rerun-sdk-pip', 'python3-trimesh-pip'}
    assert problems('frodo_tiny', declared, imports, {'frodo_tiny'}) == [
        'frodo_tiny: imports trimesh.ray.ray_pyembree (tiny.py:9) but package.xml does not declare '
        '<exec_depend>python3-embreex-pip</exec_depend>']
    out = problems('frodo_tiny', declared - {'python3-opencv'} | {'python3-yaml'}, imports, {'frodo_tiny'})
    assert 'frodo_tiny: imports cv2 (tiny.py:12) but package.xml does not declare ' \
           '<exec_depend>python3-opencv</exec_depend>' in out
    assert any(p.startswith('frodo_tiny: package.xml declares python3-yaml but no module') for p in out)
    unknown = problems('frodo_tiny', set(), scan_source('import leftpad\n', 'x.py'), {'frodo_tiny'})
    assert unknown == ['frodo_tiny: x.py:1 imports leftpad, which the KEYS table of tests/test_packaging.py does not '
                       'map to a package.xml key: add it there (rosdep key, or python3-<pip name>-pip)']
    # An allowed undeclared import must stay inside functions.
    eager = scan_source('import frodo_common\n', 'y.py')
    assert problems('frodo_tiny', set(), eager, {'frodo_tiny'}, {('frodo_tiny', 'frodo_common'): 'why'})[0] \
        .startswith('frodo_tiny: y.py:1 imports frodo_common at module level')
    assert problems('frodo_tiny', set(), scan_source('def f():\n    import frodo_common\n'), {'frodo_tiny'},
                    {('frodo_tiny', 'frodo_common'): 'why'}) == []


def test_declared_keys_reads_run_time_tags_only():
    xml = ('<package format="3"><name>x</name><exec_depend>a</exec_depend><depend>b</depend>'
           '<test_depend>c</test_depend><!-- <exec_depend>d</exec_depend> --></package>')
    assert declared_keys(xml) == {'a', 'b'}


# ---------------------------------------------------------------- the workspace
@pytest.mark.parametrize('package', PACKAGES)
def test_package_xml_declares_what_the_package_imports(package):
    declared = declared_keys((SRC / package / 'package.xml').read_text())
    found = problems(package, declared, package_imports(package), own_modules(package))
    assert not found, '\n'.join(found)


def test_every_package_is_scanned():
    assert len(PACKAGES) >= 7 and all(package_modules(p) for p in PACKAGES)


def test_local_pip_keys_are_defined_in_rosdep_yaml_and_every_key_is_known():
    """A key rosdep cannot resolve fails `rosdep install`: every declared key (any tag) is a ROS or frodo
    package, a key of the table, or one rosdep.yaml defines (as pip packages)."""
    local = yaml.safe_load((REPO / 'rosdep.yaml').read_text())
    assert set(local) == LOCAL_PIP_KEYS
    for key, rules in local.items():
        assert key.endswith('-pip') and all('pip' in rule for rule in rules.values()), key
    known = set(KEYS.values()) | set(SUBMODULE_KEYS.values()) | ROS_PACKAGES | set(PACKAGES)
    tags = DEPEND_TAGS | {'test_depend', 'build_depend', 'buildtool_depend'}
    for package in PACKAGES:
        unknown = declared_keys((SRC / package / 'package.xml').read_text(), tags) - known
        assert not unknown, f'{package}: package.xml keys not in tests/test_packaging.py KEYS: {sorted(unknown)}'


def test_exceptions_are_still_needed():
    """NOT_DECLARED / NOT_IMPORTED entries that no longer apply are removed, so the lists stay true."""
    for package, module in NOT_DECLARED:
        assert any(imp.top == module for imp in package_imports(package)), (package, module)
    for package, key in NOT_IMPORTED:
        assert key in declared_keys((SRC / package / 'package.xml').read_text()), (package, key)
