"""Optimiser parameters: `OptimConfig` (per-object stage policy) holding a `SparseConfig` and a `DenseConfig`,
and the node's ROS parameters (`PARAMS`) generated from them, so every default lives in one dataclass field.

`optim_config(values)` builds the configuration from a {parameter name: value} dict (a node's parameters, a
params YAML section); unknown names raise. The node adds its topic, worker and map parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from frodo_common.params import ParamSpec
from frodo_optim.dense import DenseConfig
from frodo_optim.sparse import SparseConfig
from frodo_shape.prior import DEFAULT_PRIOR


@dataclass(frozen=True)
class OptimConfig:
    """What the object reconstructor does per object (paper Sec. 5.3: fused -> sparse -> dense)."""

    prior: str = DEFAULT_PRIOR
    device: str = 'auto'
    mesh_resolution: int = 96
    fused_mesh_resolution: int = 64
    min_views: int = 2
    fill_views: int = 16
    code_change_tolerance: float = 0.02
    sparse_enabled: bool = True
    dense_enabled: bool = True
    dense_starts: int = 3
    dense_rerun_growth: float = 1.25
    views_stored: int = 64
    crop_size: int = 96
    facing_max_gap: float = 0.3
    sparse: SparseConfig = field(default_factory=SparseConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)

    @property
    def dense_on(self) -> bool:
        """The dense stage runs (it needs the sparse one)."""
        return self.sparse_enabled and self.dense_enabled


# (parameter name, where it goes: 'field' of OptimConfig, 'sparse.field' / 'dense.field', or several, description)
_TABLE: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ('prior', ('prior',), 'Shipped prior name (frodo_shape/priors/<name>) or path to a prior folder.'),
    ('device', ('device',), "Torch device: 'auto' (cuda if available), 'cpu' or 'cuda'."),
    ('mesh_resolution', ('mesh_resolution',), 'Marching-cubes grid resolution of the sparse and dense stages\' meshes.'),
    ('fused_mesh_resolution', ('fused_mesh_resolution',), 'Marching-cubes grid of the fused stage\'s mesh (an '
     'object\'s first, shown until its sparse stage ends: coarser, so that it comes sooner; at most mesh_resolution).'),
    ('min_views', ('min_views',), 'Views (kept, associated detections) an object needs before it is reconstructed.'),
    ('fill_views', ('fill_views',), 'An object with fewer kept views than this is optimised with its pruned '
     'associated views too (truncated or overlapping; evenly spread) up to this many; 0: kept views only.'),
    ('code_change_tolerance', ('code_change_tolerance',),
     'Re-decode the mesh only when the fused code moved by more than this (relative L2); box updates alone just '
     're-place the cached mesh.'),
    ('sparse_enabled', ('sparse_enabled',), 'Run the sparse stage (Sec. 5.3: yaw search + silhouette/SLAM-point '
     'optimisation) after the fused stage; false publishes the fused placement only.'),
    ('sparse_iterations', ('sparse.iterations',), 'Adam iterations of the sparse stage per object and pass.'),
    ('sparse_views', ('sparse.max_views',), 'Views (spread evenly over the kept ones) used by the sparse stage.'),
    ('sparse_views_stored', ('views_stored',), 'Views remembered per object (thinned evenly beyond this; bounded '
     'memory).'),
    ('sparse_mask_samples', ('sparse.mask_samples',), 'Pixels sampled on each mask for the mask-to-points chamfer half.'),
    ('sparse_point_samples', ('sparse.point_samples',), 'Decoded points (of 2048) matched against the mask samples.'),
    ('sparse_yaw_candidates', ('sparse.yaw_candidates',), 'Yaw angles of the exhaustive initial search about gravity.'),
    ('sparse_w_silhouette', ('sparse.w_silhouette',), 'Weight of the silhouette energy Es (2D chamfer, box diagonals).'),
    ('sparse_w_geometry', ('sparse.w_geometry',), 'Weight of the SLAM-point energy Eg (truncated 3D chamfer); 0 disables.'),
    ('sparse_depth_points', ('sparse.depth_points',), 'Registered-depth points of the object\'s masks (when a depth '
     'image comes) added to the SLAM points of Eg, at most this many (beyond the paper; 0: landmarks only).'),
    ('sparse_free_space', ('sparse.free_space',), 'With a registered depth image, a decoded point that projects off '
     'the mask costs the sparse silhouette nothing where the depth there measures a surface in front of it (hidden '
     'by clutter, a missed detection, another object); false: it costs its distance to the mask, as without depth.'),
    ('free_space_margin', ('sparse.free_space_margin', 'dense.free_space_margin'), 'Metres: a surface measured less '
     'than this in front of a point (sparse) or ray sample (dense) does not hide it (depth noise).'),
    ('sparse_w_code', ('sparse.w_code',), 'Weight of the code regulariser Er (squared code z-score w.r.t. training codes).'),
    ('sparse_optimise_code', ('sparse.optimise_code',), 'Optimise the shape code too (false: pose only).'),
    ('sparse_lr_code', ('sparse.lr_code',), 'Adam step size of the shape code in the sparse stage.'),
    ('sparse_w_photometric', ('sparse.w_photometric',), 'Weight of the sparse photometric energy Ep (Eq. 4, '
     'visibility-aware; needs dense_enabled for the colour crops); 0 disables.'),
    ('sparse_placement_search', ('sparse.placement_search',), 'Also start the sparse stage from placement hypotheses '
     '(placement.py: ray-crossing centres, silhouette scales) for a badly wrong association box; a hypothesis replaces '
     'the box start only when clearly better on common landmarks and silhouettes.'),
    ('sparse_code_restarts', ('sparse.code_restarts',), "Also start the sparse stage from the best of this many "
     "lowest-energy training codes of the object's class (beyond the paper; 0: off)."),
    ('sparse_restart_screen_views', ('sparse.restart_screen_views',), 'The code restarts\' candidates (training '
     'codes, then their yaws) are first ranked by the energy on this many of the views and a subset of the points; '
     'only the best sparse_restart_screen_keep x sparse_code_restarts get the exact energy (0: every candidate '
     'exact).'),
    ('sparse_restart_screen_keep', ('sparse.restart_screen_keep',), 'How many times sparse_code_restarts screened '
     'candidates get the exact energy.'),
    ('sparse_landmark_filter', ('sparse.landmark_filter',), "Only landmarks in the detections' visual hull enter Eg, "
     "in the sparse and the dense stage; false: every landmark near the box (the paper's setting)."),
    ('support_w_floor', ('sparse.w_floor', 'dense.w_floor'), 'Weight of the floor prior E_floor in the sparse and '
     'dense stages (beyond the paper: the lowest points on the floor estimated from the boxes and landmarks; '
     'support.py); 0 disables.'),
    ('support_w_height', ('sparse.w_height', 'dense.w_height'), 'Weight of the class height prior E_size in the '
     'sparse and dense stages (beyond the paper: height inside Category.height_range; support.py); 0 disables.'),
    ('support_w_facing', ('sparse.w_facing', 'dense.w_facing'), 'Weight of the facing prior E_facing in the sparse '
     'and dense stages (beyond the paper: a chair whose box is within facing_max_gap of a table\'s faces that table; '
     'it breaks the tie between facing it and turning away when the table hides the seat; support.py), scaled by how '
     'one-sided the views are: times 1 - (arc of directions holding the cameras) / 180 deg; 0 disables.'),
    ('facing_max_gap', ('facing_max_gap',), 'Metres between the footprints of a chair\'s and a table\'s association '
     'boxes within which the chair is taken to stand at the table (E_facing).'),
    ('dense_enabled', ('dense_enabled',), 'Run the dense stage (Sec. 5.3 Dense Optimization: SDF decoder, code + '
     '7-DoF pose) after a successful sparse stage.'),
    ('dense_iterations', ('dense.iterations',), 'Adam iterations of the dense stage per object and pass.'),
    ('dense_starts', ('dense_starts',), "Dense stage from the sparse result and up to N - 1 end states of the sparse "
     "stage's other runs (box, placement hypothesis, code restart); the lowest dense energy wins (1: the sparse "
     "result only, a third of the dense cost)."),
    ('dense_screen_iterations', ('dense.screen_iterations',), 'With several dense starts: run each this many '
     'iterations, then only those within dense_screen_margin of the lowest energy the rest (0: every start in full).'),
    ('dense_screen_margin', ('dense.screen_margin',), 'Check-energy margin above the lowest start within which a '
     'screened dense start goes on (0: only the lowest).'),
    ('dense_start_separation', ('dense.start_separation',), 'Metres: a dense start whose placed surface (mean '
     'chamfer) lies within this of an earlier start\'s is not run (0: every start runs).'),
    ('dense_max_seconds', ('dense.max_seconds',), 'Wall-clock bound of one dense run (per object and start; best '
     'state kept).'),
    ('dense_views', ('dense.max_views',), 'Views (spread evenly over the kept ones) used by the dense stage.'),
    ('dense_grid_resolution', ('dense.grid_resolution',), 'Resolution of the adaptive SDF volume / proxy mesh per '
     'iteration.'),
    ('dense_grid_band', ('dense.grid_band',), 'Between full evaluations of the SDF volume, re-evaluate only its '
     'points within this normalised distance of the surface (the code moves a little per iteration; 0: the whole '
     'adaptive volume every iteration).'),
    ('dense_rays_per_view', ('dense.rays_per_view',), 'Pixels (rays) per view and pyramid level of the dense '
     'silhouette.'),
    ('dense_surface_points', ('dense.surface_points',), 'Proxy-mesh vertices used by the dense photometric term.'),
    ('dense_sharpness', ('dense.sharpness',), 'zeta: SDF-to-logit scale of the ray-accumulated silhouette (per '
     'normalised unit).'),
    ('dense_crop_size', ('crop_size',), 'Side of the stored label/colour crop per detection (bounded memory).'),
    ('dense_w_silhouette', ('dense.w_silhouette',), 'Weight of the dense silhouette energy (Eq. 7/8).'),
    ('dense_w_photometric', ('dense.w_photometric',), 'Weight of the dense photometric energy (Eq. 4 on the proxy '
     'surface).'),
    ('dense_w_geometry', ('dense.w_geometry',), 'Weight of the landmark term (|SDF| at SLAM points, truncated).'),
    ('dense_w_depth', ('dense.w_depth',), 'Weight of the registered-depth term (|SDF| at masked depth pixels), when '
     'depth is present.'),
    ('dense_free_space', ('dense.free_space',), 'With a registered depth image, a pixel off the mask that measures '
     'a surface is background in the dense silhouette only in front of that surface (the object may be hidden '
     'behind it: clutter, a missed detection, a hole in its mask); false: the whole ray, as without depth.'),
    ('dense_w_code', ('dense.w_code',), 'Weight of the code regulariser in the dense stage.'),
    ('dense_lr_code', ('dense.lr_code',), 'Adam step size of the shape code in the dense stage.'),
    ('dense_upright', ('dense.upright',), "Dense stage rotates objects about gravity (world z) only; false: any "
     "rotation (the paper's 7-DoF pose)."),
    ('dense_rerun_growth', ('dense_rerun_growth',), "While other objects wait, re-run an object's dense stage only "
     "when its views grew by this factor; the rest are caught up when the queue is empty."),
)
_TARGETS = {name: targets for name, targets, _ in _TABLE}


def _default(path: str, config: OptimConfig) -> Any:
    owner, _, name = path.rpartition('.')
    return getattr(getattr(config, owner) if owner else config, name)


PARAMS: tuple[ParamSpec, ...] = tuple(ParamSpec(name, _default(targets[0], OptimConfig()), doc)
                                      for name, targets, doc in _TABLE)
"""The reconstructor's parameters, with the defaults of `OptimConfig` (and its SparseConfig / DenseConfig)."""


def optim_config(values: dict[str, Any], base: OptimConfig | None = None) -> OptimConfig:
    """`base` (default: the defaults) with the named parameters set; values are cast to the field's type.
    Raises ValueError for a name that is no reconstructor parameter."""
    config = base or OptimConfig()
    unknown = sorted(set(values) - set(_TARGETS))
    if unknown:
        raise ValueError(f'unknown optimiser parameter(s) {", ".join(unknown)}')
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {'sparse': {}, 'dense': {}}
    for name, value in values.items():
        for path in _TARGETS[name]:
            owner, _, attr = path.rpartition('.')
            cast = type(_default(path, OptimConfig()))
            (nested[owner] if owner else top)[attr] = cast(value)
    return replace(config, **top, sparse=replace(config.sparse, **nested['sparse']),
                   dense=replace(config.dense, **nested['dense']))

