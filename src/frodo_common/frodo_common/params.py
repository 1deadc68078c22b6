"""Parameter specifications: the single source of every node's parameter names, defaults and descriptions.

Nodes declare their parameters from a tuple of `ParamSpec`; `frodo launch` and the ROS 2 launch file's
YAML (`frodo_bringup/config/frodo.yaml`) are generated from the same specs, so they cannot drift.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ParamSpec:
    """One ROS parameter: name, default value (its type fixes the parameter type) and description."""

    name: str
    default: Any
    description: str


# Parameters every FroDO node has.
COMMON_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec('world_frame', 'world', 'World frame id (gravity aligned, z up).'),
    ParamSpec('diagnostics_period', 0.5, 'Seconds between /diagnostics reports (0.5: a listener on a loaded machine, '
              'whose own scheduling delays what it receives, still gets one well within every second).'),
    ParamSpec('frame_cache_size', 400, 'Frames kept in the stamp-matched cache (oldest dropped first).'),
)


def defaults(specs: tuple[ParamSpec, ...]) -> dict[str, Any]:
    """{name: default} for a spec tuple."""
    return {s.name: s.default for s in specs}
