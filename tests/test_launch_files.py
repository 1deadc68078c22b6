"""The shipped ROS 2 launch file and parameter YAML agree with the node table and the nodes' own specs."""
from __future__ import annotations

import ast
from pathlib import Path

import yaml

from frodo_bringup.graph import ALL_NODES, NODES, VIEWER, node_params, params_yaml, share_file, source_config_path
from frodo_common.params import COMMON_PARAMS

PACKAGE_DIR = Path(source_config_path()).parents[1]


def _launch_file_tuples() -> dict[str, object]:
    tree = ast.parse(share_file('launch/frodo.launch.py').read_text())
    return {target.id: ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
            for target in node.targets if isinstance(target, ast.Name) and target.id in ('NODES', 'VIEWER')}


def test_shipped_yaml_is_the_generated_one():
    """No drift: regenerate with `frodo params --write` after changing a node's PARAMS."""
    assert source_config_path().read_text() == params_yaml()


def test_shipped_yaml_holds_every_parameter_default():
    document = yaml.safe_load(source_config_path().read_text())
    assert document['/**']['ros__parameters'] == {s.name: s.default for s in COMMON_PARAMS}
    for node in ALL_NODES:
        assert document[node.name]['ros__parameters'] == {s.name: s.default for s in node_params(node)}


def test_launch_file_names_the_graph_nodes():
    tuples = _launch_file_tuples()
    assert tuples['NODES'] == tuple((n.package, n.name) for n in NODES)
    assert tuples['VIEWER'] == (VIEWER.package, VIEWER.name)
    source = share_file('launch/frodo.launch.py').read_text()
    assert 'def generate_launch_description' in source and "'config', 'frodo.yaml'" in source


def test_setup_installs_launch_and_config_files():
    setup = (PACKAGE_DIR / 'setup.py').read_text()
    assert "'/launch', ['launch/frodo.launch.py']" in setup
    assert "'/config', ['config/frodo.yaml']" in setup


def test_shipped_parameter_files_resolve_by_name():
    from frodo_bringup.graph import resolve_params_file, shipped_presets
    assert shipped_presets() == ['frodo']
    assert resolve_params_file('frodo') == share_file('config/frodo.yaml')
    assert resolve_params_file('my.yaml') == Path('my.yaml')   # a file name is never taken for a shipped one
