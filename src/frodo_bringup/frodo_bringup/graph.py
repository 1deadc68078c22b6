"""The FroDO node graph: the one table of nodes (`NODES`) and the parameter YAML generated from their specs.

`frodo launch`, `frodo run`, `frodo params` and the ROS 2 launch file all read this table; parameter
defaults come from each node module's `PARAMS` (plus `COMMON_PARAMS`), imported lazily because some
nodes pull in heavy dependencies (torch).
"""
from __future__ import annotations

import importlib
import os
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import yaml

from frodo_common.params import COMMON_PARAMS, ParamSpec

PACKAGE = 'frodo_bringup'


@dataclass(frozen=True)
class GraphNode:
    """One node of the graph: ROS node name, Python module (exposes `main()` and `PARAMS`), ROS package.

    params_key: the YAML section its parameters come from when that is not its name (optimiser workers
    `optim_node_<k>` read `optim_node:`); parameters: (name, value) pairs set on top of every params file;
    env: (name, value) environment variables of its process.
    """

    name: str
    module: str
    package: str
    params_key: str = ''
    parameters: tuple[tuple[str, Any], ...] = ()
    env: tuple[tuple[str, str], ...] = ()


# The graph, in data-flow order. Node name == console script name == launch file executable.
NODES: tuple[GraphNode, ...] = (
    GraphNode('detection_node', 'frodo_detection.detection_node', 'frodo_detection'),
    GraphNode('association_node', 'frodo_association.association_node', 'frodo_association'),
    GraphNode('shape_node', 'frodo_shape.shape_node', 'frodo_shape'),
    GraphNode('optim_node', 'frodo_optim.optim_node', 'frodo_optim'),
)
# Optional Rerun viewer (`frodo run --viewer rrd`, launch argument `viewer:=true`); not part of NODES.
VIEWER = GraphNode('viewer_node', 'frodo_bringup.viewer_node', 'frodo_bringup')
# Every node whose parameters the shipped YAML holds.
ALL_NODES = NODES + (VIEWER,)
# The node whose diagnostics (`state`, `pending_objects`) say when a bag is fully processed. With several
# workers (`--optim-workers N`) worker 0 keeps this name (it publishes the merged map and reports for every
# worker) and the others are `optim_node_1` ... `optim_node_<N-1>`.
OPTIMISER = 'optim_node'
_WORKER_NAME = re.compile(rf'{OPTIMISER}_\d+')
# `--optim-workers auto`: two workers where there are two CPUs or more. On the 2-core machine this was measured
# on, two single-threaded workers finished the demo walk sooner than one two-threaded optimiser
# (docs/performance.md, `frodo bench --only optim_workers`); more were not measured.
AUTO_OPTIM_WORKERS = 2


def is_optimiser(name: str) -> bool:
    """True for the optimiser node and its workers' names."""
    return name == OPTIMISER or bool(_WORKER_NAME.fullmatch(name))


def optim_worker_count(value: int | str | None, option: str = '--optim-workers') -> int:
    """The number of optimiser workers for `--optim-workers VALUE` (or another `option`, named in errors): a
    positive integer, or 'auto' / None for AUTO_OPTIM_WORKERS capped at the CPUs this process may use."""
    if value is None or value == 'auto':
        return max(1, min(AUTO_OPTIM_WORKERS, len(os.sched_getaffinity(0))))
    try:
        count = int(value)
    except (TypeError, ValueError):
        raise GraphError(f"{option} must be a positive integer or 'auto', got {value!r}") from None
    if count < 1:
        raise GraphError(f'{option} must be at least 1, got {count}')
    return count


def optimiser_workers(nodes: Sequence[GraphNode], count: int | str | None) -> tuple[GraphNode, ...]:
    """`nodes` with the optimiser split into `count` workers (`optim_worker_count`) that share the objects by id
    (parameters `worker_index`, `worker_count`): worker 0 keeps the name `optim_node`, the others are
    `optim_node_1..count-1` reading the `optim_node` parameters. One worker keeps the graph as it is.

    Each worker gets 1/count of the CPUs as torch threads (OMP_NUM_THREADS): with every worker on all of them,
    their OpenMP teams spin against each other (2 workers on 2 CPUs: the demo walk took 284.8 s instead of
    54.8 s with one; docs/experiments/frodo_optim_history.md, "One OpenMP team per process")."""
    count = optim_worker_count(count)
    if count == 1:
        return tuple(nodes)
    threads = str(max(1, len(os.sched_getaffinity(0)) // count))
    out: list[GraphNode] = []
    for node in nodes:
        if node.name != OPTIMISER:
            out.append(node)
            continue
        out += [GraphNode(OPTIMISER if k == 0 else f'{OPTIMISER}_{k}', node.module, node.package,
                          params_key='' if k == 0 else OPTIMISER,
                          parameters=node.parameters + (('worker_index', k), ('worker_count', count)),
                          env=node.env + (('OMP_NUM_THREADS', threads),))
                for k in range(count)]
    return tuple(out)


def with_optimiser_parameters(nodes: Sequence[GraphNode], **parameters: Any) -> tuple[GraphNode, ...]:
    """`nodes` with `parameters` (None values left out) set on the optimiser and its workers."""
    extra = tuple((k, v) for k, v in parameters.items() if v is not None)
    return tuple(replace(n, parameters=n.parameters + extra) if is_optimiser(n.name) and extra else n for n in nodes)


def section_parameters(params_files: Iterable[str | os.PathLike], key: str) -> dict[str, Any]:
    """The `ros__parameters` of node `key` (`key:` or `/key:`) across params files, later files winning."""
    merged: dict[str, Any] = {}
    for path in params_files:
        try:
            document = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as err:
            raise GraphError(f'parameter file {path}: {err}') from err
        for name in (key, f'/{key}'):
            section = document.get(name) if isinstance(document, dict) else None
            if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
                merged.update(section['ros__parameters'])
    return merged


def ros_parameter_arguments(node: GraphNode, params_files: Sequence[str | os.PathLike]) -> list[str]:
    """`-p name:=value` arguments of a node running under another name than its params section, then its own."""
    values = section_parameters(params_files, node.params_key) if node.params_key else {}
    values.update(dict(node.parameters))
    return [arg for name, value in values.items() for arg in ('-p', f'{name}:={_yaml_scalar(value)}')]


class GraphError(RuntimeError):
    """A node name, node module or parameter file of the graph is invalid."""


def select_nodes(names: Iterable[str] | None, nodes: Sequence[GraphNode] = NODES) -> tuple[GraphNode, ...]:
    """The nodes named in `names` (all when None), in graph order; raises GraphError on unknown names."""
    if names is None:
        return tuple(nodes)
    wanted = [n.strip() for n in names if n.strip()]
    known = {n.name for n in nodes}
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise GraphError(f'unknown node(s) {", ".join(unknown)}; the graph has {", ".join(sorted(known))}')
    return tuple(n for n in nodes if n.name in wanted)


def parse_node_spec(spec: str) -> GraphNode:
    """A GraphNode from `NAME=MODULE` (an extra node for `--add-node`); raises GraphError on bad syntax."""
    name, sep, module = spec.partition('=')
    if not sep or not name.strip() or not module.strip():
        raise GraphError(f'bad node {spec!r}: expected NAME=MODULE, e.g. my_detector=my_pkg.detector_node')
    return GraphNode(name.strip(), module.strip(), module.strip().split('.')[0])


def with_nodes(nodes: Sequence[GraphNode], extra: Sequence[GraphNode]) -> tuple[GraphNode, ...]:
    """`nodes` with `extra` added; an extra node named like a graph node replaces it in place."""
    replacements = {n.name: n for n in extra}
    merged = [replacements.pop(n.name, n) for n in nodes]
    return tuple(merged) + tuple(n for n in extra if n.name in replacements)


def node_params(node: GraphNode) -> tuple[ParamSpec, ...]:
    """The node's own parameter specs (its module's `PARAMS`); raises GraphError when it cannot be imported."""
    try:
        module = importlib.import_module(node.module)
    except ImportError as err:
        raise GraphError(f'{node.name}: cannot import {node.module} ({err})') from err
    specs = getattr(module, 'PARAMS', None)
    if specs is None:
        raise GraphError(f'{node.name}: {node.module} has no module-level PARAMS')
    return tuple(specs)


def _yaml_scalar(value: Any) -> str:
    """One value in YAML flow style (lists inline), as a params file wants it."""
    return yaml.safe_dump(value, default_flow_style=True, width=1 << 16).strip().removesuffix('\n...').strip()


def _params_block(key: str, specs: Sequence[ParamSpec]) -> list[str]:
    lines = [f'{key}:', '  ros__parameters:']
    lines += [f'    {s.name}: {_yaml_scalar(s.default)}  # {s.description}' for s in specs]
    return lines


def params_yaml(nodes: Sequence[GraphNode] = ALL_NODES) -> str:
    """ROS 2 params file with every parameter's default and description: common ones under `/**`."""
    lines = ['# FroDO parameter defaults, generated from the nodes\' PARAMS by `frodo params --write`.',
             '# Do not edit by hand: change the ParamSpec in the node and regenerate. Override values in your',
             '# own file and pass it with `frodo launch --params FILE` (later files win).', '']
    lines += _params_block("'/**'", COMMON_PARAMS)
    for node in nodes:
        lines += [''] + _params_block(node.name, node_params(node))
    return '\n'.join(lines) + '\n'


def _share_dirs() -> Iterator[Path]:
    """Where shipped files may be: the source tree (editable install), the ament index, the pip prefix."""
    yield Path(__file__).resolve().parents[1]
    try:
        from ament_index_python.packages import get_package_share_directory
        yield Path(get_package_share_directory(PACKAGE))
    except (ImportError, LookupError, OSError):  # not installed / package unknown / AMENT_PREFIX_PATH unset
        pass
    yield Path(sys.prefix) / 'share' / PACKAGE


def share_file(relative: str) -> Path:
    """Path of a shipped file (`config/frodo.yaml`, `launch/frodo.launch.py`) in the source tree or install."""
    searched = []
    for base in _share_dirs():
        if (base / relative).is_file():
            return base / relative
        searched.append(str(base))
    raise GraphError(f'{PACKAGE}: shipped file {relative} not found (looked in {", ".join(searched)})')


def resolve_params_file(name: str | os.PathLike) -> Path:
    """A parameter file path, or the name of a shipped parameter file (`frodo` -> `config/frodo.yaml`)."""
    path = Path(name)
    if path.is_file() or path.suffix or len(path.parts) > 1:
        return path
    try:
        return share_file(f'config/{path.name}.yaml')
    except GraphError:
        return path


def shipped_presets() -> list[str]:
    """Names of the shipped parameter files (`config/*.yaml`; `frodo`: the defaults)."""
    folder = share_file('config/frodo.yaml').parent
    return sorted(p.stem for p in folder.glob('*.yaml'))


def source_config_path() -> Path:
    """Where `frodo params --write` writes the shipped YAML: the package's source tree."""
    return Path(__file__).resolve().parents[1] / 'config' / 'frodo.yaml'
