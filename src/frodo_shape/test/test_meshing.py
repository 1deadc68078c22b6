"""Dense SDF grids (`frodo_shape.meshing`): the coarse-to-fine grid, the narrow-band update, marching cubes."""
import numpy as np

from frodo_shape.meshing import grid_points, marching_cubes, sdf_grid, update_band


def _sphere(radius: float):
    return lambda p: (np.linalg.norm(p, axis=-1) - radius).astype(np.float32)


def test_coarse_to_fine_grid_gives_the_full_grid_mesh():
    """Only points near the surface are evaluated on the fine grid, yet the mesh is the full grid's."""
    calls = []

    def counted(p):
        calls.append(len(p))
        return _sphere(0.6)(p)

    full = _sphere(0.6)(grid_points(48).reshape(-1, 3)).reshape((48,) * 3)
    grid = sdf_grid(counted, 48, coarse=4)
    assert sum(calls) < 0.4 * 48 ** 3                                # a third of the grid
    near = np.abs(full) < 2 / 47
    assert np.allclose(grid[near], full[near], atol=1e-6)          # every cell marching cubes reads is exact
    assert np.array_equal(np.sign(grid), np.sign(full))
    a, b = marching_cubes(grid), marching_cubes(full)
    assert np.allclose(a.vertices, b.vertices, atol=1e-6) and len(a.faces) == len(b.faces)
    assert abs(np.linalg.norm(a.vertices, axis=1).mean() - 0.6) < 0.01


def test_band_update_re_evaluates_only_near_the_surface_and_reports_the_change():
    old = sdf_grid(_sphere(0.5), 32, coarse=1)
    calls = []

    def grown(p):
        calls.append(len(p))
        return _sphere(0.52)(p)

    new, change = update_band(grown, old, band=0.25)
    near = np.abs(old) < 0.25
    assert sum(calls) == near.sum() < 0.5 * 32 ** 3
    assert np.allclose(new[near], grown(grid_points(32)[near]), atol=1e-6)
    assert np.array_equal(new[~near], old[~near])                    # kept as they were
    assert abs(change - 0.02) < 1e-5
    assert update_band(grown, np.ones((8, 8, 8), np.float32), band=0.25)[1] == 0.0   # nothing near: nothing evaluated


def test_level_by_level_grid_gives_the_full_grid_mesh_of_the_shipped_prior():
    """With a factor of 4 the grid is built 64 <- 32 <- 16; on real codes of the shipped prior its mesh is the
    full grid's, from about a tenth of the decoder queries."""
    from frodo_shape.prior import ShapePrior
    prior = ShapePrior.load('furniture_broad')
    for i in (0, len(prior.training_codes) // 2, len(prior.training_codes) - 1):
        code = prior.training_codes[i]
        calls = []

        def counted(p):
            calls.append(len(p))
            return prior.sdf_numpy(p, code)

        grid = sdf_grid(counted, 64, coarse=4)
        full = prior.sdf_numpy(grid_points(64).reshape(-1, 3), code).reshape((64,) * 3)
        assert len(calls) == 3 and sum(calls) < 0.15 * 64 ** 3
        a, b = marching_cubes(grid), marching_cubes(full)
        assert len(a.faces) == len(b.faces) > 0 and np.allclose(a.vertices, b.vertices, atol=1e-6)
