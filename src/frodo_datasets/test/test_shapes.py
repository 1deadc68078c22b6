"""Tests of the procedural shape library, the canonical frame and the user mesh loader."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from frodo_datasets.scene import family_pool
from frodo_datasets.shapes import (CANONICAL_RADIUS, ShapeRecord, axes_to_canonical, denormalise, eval_families,
                                   extra_families, families, generate, library, load_user_meshes, normalise)
from frodo_datasets.shapes.gallery import save_gallery

FAMILY_CASES = [(class_name, family) for class_name in ('chair', 'dining table')
                for family in families(class_name) + extra_families(class_name)]
HELDOUT_CASES = [(class_name, family) for class_name in ('chair', 'dining table') for family in eval_families(class_name)]
SEEDS = range(12)

# (min, max) metres of height (z), depth (x) and width (y) per family.
SIZE_RANGES = {
    ('chair', 'four_leg'): {'height': (0.75, 1.0), 'depth': (0.38, 0.6), 'width': (0.38, 0.6)},
    ('chair', 'office'): {'height': (0.9, 1.3), 'depth': (0.5, 0.9), 'width': (0.5, 0.8)},
    ('chair', 'stool'): {'height': (0.45, 0.8), 'depth': (0.25, 0.6), 'width': (0.25, 0.6)},
    ('chair', 'armchair'): {'height': (0.75, 1.0), 'depth': (0.7, 1.05), 'width': (0.65, 1.05)},
    ('dining table', 'four_leg'): {'height': (0.72, 0.77), 'depth': (0.75, 1.0), 'width': (1.2, 2.0)},
    ('dining table', 'pedestal'): {'height': (0.72, 0.76), 'depth': (0.7, 1.2), 'width': (0.7, 1.2)},
    ('dining table', 'trestle'): {'height': (0.72, 0.77), 'depth': (0.8, 1.0), 'width': (1.6, 2.4)},
    ('dining table', 'coffee'): {'height': (0.35, 0.5), 'depth': (0.5, 0.8), 'width': (0.9, 1.4)},
    ('chair', 'shell'): {'height': (0.75, 0.9), 'depth': (0.45, 0.6), 'width': (0.44, 0.62)},
    ('chair', 'upholstered'): {'height': (0.85, 1.1), 'depth': (0.5, 0.68), 'width': (0.45, 0.62)},
    ('chair', 'spindle'): {'height': (0.8, 1.05), 'depth': (0.42, 0.55), 'width': (0.42, 0.58)},
    ('dining table', 'panel_end'): {'height': (0.72, 0.77), 'depth': (0.7, 1.0), 'width': (1.2, 2.2)},
    ('dining table', 'x_base'): {'height': (0.72, 0.77), 'depth': (0.75, 1.2), 'width': (0.8, 2.2)},
    ('dining table', 'side'): {'height': (0.45, 0.7), 'depth': (0.35, 0.65), 'width': (0.35, 0.65)},
    ('chair', 'cantilever'): {'height': (0.7, 1.0), 'depth': (0.4, 0.7), 'width': (0.4, 0.52)},
    ('chair', 'tub'): {'height': (0.65, 0.9), 'depth': (0.55, 0.85), 'width': (0.55, 0.85)},
    ('dining table', 'desk'): {'height': (0.72, 0.77), 'depth': (0.6, 0.85), 'width': (1.1, 1.8)},
    ('dining table', 'round_four_leg'): {'height': (0.72, 0.77), 'depth': (0.9, 1.75), 'width': (0.9, 1.75)},
}


@pytest.mark.parametrize('class_name,family', HELDOUT_CASES)
def test_heldout_families_are_watertight_sized_and_outside_the_training_library(class_name, family):
    for seed in SEEDS:
        mesh = generate(class_name, seed, family)
        assert mesh.is_watertight and mesh.is_volume and mesh.body_count == 1, (family, seed)
        assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        depth, width, height = mesh.extents
        ranges = SIZE_RANGES[(class_name, family)]
        assert ranges['height'][0] <= height <= ranges['height'][1], (family, seed, height)
        assert ranges['depth'][0] <= depth <= ranges['depth'][1] and ranges['width'][0] <= width <= ranges['width'][1], \
            (family, seed, depth, width)
    assert family not in families(class_name)
    assert all(r.family != family for r in library(class_name, 12, seed=0))
    assert np.array_equal(generate(class_name, 5, family).vertices, generate(class_name, 5, family).vertices)


def shapenet_frame(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A canonical mesh as ShapeNetCore v2 stores it: y up, front -z, bounding-box diagonal 1."""
    transform = np.eye(4)
    transform[:3, :3] = axes_to_canonical('y', '-z').T
    converted = mesh.copy()
    converted.apply_transform(transform)
    converted.apply_scale(1.0 / np.linalg.norm(converted.extents))
    return converted


def open_sphere() -> trimesh.Trimesh:
    """A sphere (radius 0.5) with its top cap cut away: a hole too large for trimesh's hole filling."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    sphere.update_faces(sphere.triangles_center[:, 2] < 0.4)
    return sphere


@pytest.mark.parametrize('class_name, family', FAMILY_CASES)
def test_every_family_is_a_single_watertight_volume(class_name: str, family: str) -> None:
    for seed in SEEDS:
        mesh = generate(class_name, seed, family)
        assert mesh.is_watertight and mesh.is_volume, (class_name, family, seed)
        assert mesh.body_count == 1, (class_name, family, seed)


@pytest.mark.parametrize('class_name, family', FAMILY_CASES)
def test_generation_is_deterministic_and_varies_with_the_seed(class_name: str, family: str) -> None:
    first, again, other = generate(class_name, 7, family), generate(class_name, 7, family), generate(class_name, 8, family)
    assert np.array_equal(first.vertices, again.vertices) and np.array_equal(first.faces, again.faces)
    assert first.vertices.shape != other.vertices.shape or not np.allclose(first.vertices, other.vertices)


def test_default_family_cycles_with_the_seed() -> None:
    for class_name in ('chair', 'dining table'):
        names = families(class_name)
        for seed in range(len(names)):
            assert np.array_equal(generate(class_name, seed).vertices,
                                  generate(class_name, seed, names[seed % len(names)]).vertices)


@pytest.mark.parametrize('class_name, family', FAMILY_CASES)
def test_canonical_frame_and_realistic_sizes(class_name: str, family: str) -> None:
    ranges = SIZE_RANGES[(class_name, family)]
    for seed in SEEDS:
        mesh = generate(class_name, seed, family)
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        depth, width, height = mesh.extents
        assert mesh.bounds[0, 2] == pytest.approx(-height / 2)
        for name, value in (('height', height), ('depth', depth), ('width', width)):
            low, high = ranges[name]
            assert low - 0.03 <= value <= high + 0.03, (family, seed, name, value)


@pytest.mark.parametrize('family', ['four_leg', 'office', 'armchair', 'shell', 'upholstered', 'spindle'])
def test_chair_back_is_behind_the_seat_at_minus_x(family: str) -> None:
    for seed in SEEDS:
        mesh = generate('chair', seed, family)
        top_of_back = mesh.vertices[np.argmax(mesh.vertices[:, 2])]
        assert top_of_back[0] < -0.2 * mesh.extents[0], (family, seed)


@pytest.mark.parametrize('family', ['four_leg', 'trestle', 'coffee', 'panel_end'])
def test_rectangular_tables_have_their_long_side_along_y(family: str) -> None:
    for seed in SEEDS:
        depth, width, _ = generate('dining table', seed, family).extents
        assert width > depth


def test_library_cycles_families_and_regenerates() -> None:
    records = library('chair', 9, seed=5)
    names = families('chair')
    assert [r.family for r in records] == [names[i % len(names)] for i in range(9)]
    assert len({r.name for r in records}) == 9 and len({r.seed for r in records}) == 9
    assert all(isinstance(r, ShapeRecord) and r.class_name == 'chair' and r.watertight for r in records)
    again = library('chair', 9, seed=5)
    assert [r.seed for r in again] == [r.seed for r in records]
    assert np.array_equal(generate('chair', records[4].seed, records[4].family).vertices, records[4].mesh.vertices)


def test_extra_families_only_join_the_library_when_asked() -> None:
    for class_name in ('chair', 'dining table'):
        base, extra = families(class_name), extra_families(class_name)
        assert extra and not set(extra) & set(base) and not set(extra) & set(eval_families(class_name))
        assert not set(extra) & set(family_pool(class_name, 'all'))  # synthetic scenes never draw them
        names = base + extra
        records = library(class_name, 2 * len(names), seed=3, extra=True)
        assert [r.family for r in records] == [names[i % len(names)] for i in range(2 * len(names))]
        assert [r.family for r in library(class_name, 8, seed=3)] == [base[i % len(base)] for i in range(8)]
        record = records[len(base)]
        assert np.array_equal(generate(class_name, record.seed, record.family).vertices, record.mesh.vertices)


def test_unknown_class_or_family_is_rejected() -> None:
    with pytest.raises(ValueError, match='known classes'):
        generate('toaster', 0)
    with pytest.raises(ValueError, match='families'):
        generate('chair', 0, 'rocking')


def test_normalise_round_trip() -> None:
    mesh = generate('dining table', 2)
    normalised, scale = normalise(mesh)
    half_diagonal = 0.5 * np.linalg.norm(normalised.extents)
    assert half_diagonal == pytest.approx(CANONICAL_RADIUS)
    assert scale == pytest.approx(0.5 * np.linalg.norm(mesh.extents) / CANONICAL_RADIUS)
    np.testing.assert_allclose(normalised.bounds.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(denormalise(normalised, scale).vertices, mesh.vertices, atol=1e-12)


def test_axes_to_canonical_maps_shapenet_axes() -> None:
    rotation = axes_to_canonical('y', '-z')
    np.testing.assert_allclose(rotation @ [0, 1, 0], [0, 0, 1])
    np.testing.assert_allclose(rotation @ [0, 0, -1], [1, 0, 0])
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    with pytest.raises(ValueError, match='perpendicular'):
        axes_to_canonical('y', '-y')
    with pytest.raises(ValueError, match='axis names'):
        axes_to_canonical('up', 'x')


def test_load_shapenet_layout(tmp_path: Path) -> None:
    chair, table = generate('chair', 0, 'four_leg'), generate('dining table', 1, 'pedestal')
    for synset, model, mesh in (('03001627', 'chair_a', chair), ('04379243', 'table_a', table),
                                ('02691156', 'plane_a', chair)):
        folder = tmp_path / synset / model / 'models'
        folder.mkdir(parents=True)
        shapenet_frame(mesh).export(folder / 'model_normalized.obj')

    with pytest.warns(RuntimeWarning, match='02691156'):
        records = load_user_meshes(tmp_path, target_height={'chair': chair.extents[2], 'dining table': table.extents[2]})
    assert [(r.name, r.class_name, r.family, r.seed) for r in records] == [
        ('shapenet-03001627-chair_a', 'chair', 'shapenet', -1), ('shapenet-04379243-table_a', 'dining table', 'shapenet', -1)]
    for record, original in zip(records, (chair, table)):
        assert record.watertight and record.mesh.is_volume
        np.testing.assert_allclose(record.mesh.bounds, original.bounds, atol=1e-5)  # back in metres, front +x
        assert record.mesh.volume == pytest.approx(original.volume, rel=1e-4)

    with pytest.warns(RuntimeWarning):
        only_tables = load_user_meshes(tmp_path, class_name='04379243')
    assert [r.class_name for r in only_tables] == ['dining table']
    assert np.linalg.norm(only_tables[0].mesh.extents) == pytest.approx(1.0)  # no target height: unit diagonal
    synset_folder = load_user_meshes(tmp_path / '03001627', target_height=chair.extents[2])
    np.testing.assert_allclose(synset_folder[0].mesh.bounds, chair.bounds, atol=1e-5)


def test_load_plain_folder_with_class_subfolders(tmp_path: Path) -> None:
    chair, table = generate('chair', 1, 'stool'), generate('dining table', 0, 'four_leg')
    (tmp_path / 'chair').mkdir()
    (tmp_path / 'dining_table' / 'nested').mkdir(parents=True)
    chair.export(tmp_path / 'chair' / 'stool.ply')
    chair.export(tmp_path / 'chair' / 'stool_copy.stl')
    scene = trimesh.Scene([table, trimesh.creation.box((0.1, 0.1, 0.1), trimesh.transformations.translation_matrix([0, 0, 1]))])
    scene.export(tmp_path / 'dining_table' / 'nested' / 'with_box.glb')
    (tmp_path / 'chair' / 'notes.txt').write_text('not a mesh')

    records = load_user_meshes(tmp_path, up_axis='z', front_axis='x')
    assert [(r.name, r.class_name, r.family) for r in records] == [
        ('chair/stool', 'chair', 'user'), ('chair/stool_copy', 'chair', 'user'),
        ('dining_table/nested/with_box', 'dining table', 'user')]
    np.testing.assert_allclose(records[0].mesh.bounds, chair.bounds, atol=1e-6)
    assert records[2].mesh.extents[2] == pytest.approx(1.05 + table.extents[2] / 2)  # both scene nodes kept
    assert all(r.watertight for r in records[:2])
    assert [r.name for r in load_user_meshes(tmp_path, class_name='table', up_axis='z', front_axis='x')] == [
        'dining_table/nested/with_box']


def test_load_plain_folder_of_files_rotates_axes(tmp_path: Path) -> None:
    chair = generate('chair', 0, 'armchair')
    shapenet_frame(chair).export(tmp_path / 'armchair.off')
    records = load_user_meshes(tmp_path, class_name='chair', target_height=chair.extents[2])
    assert records[0].source == tmp_path / 'armchair.off'
    np.testing.assert_allclose(records[0].mesh.bounds, chair.bounds, atol=1e-5)
    with pytest.raises(ValueError, match='class_name'):
        load_user_meshes(tmp_path)


def test_open_mesh_is_flagged_or_remeshed(tmp_path: Path) -> None:
    sphere = open_sphere()
    sphere.export(tmp_path / 'open.stl')
    with pytest.warns(RuntimeWarning, match='not watertight'):
        flagged = load_user_meshes(tmp_path, class_name='chair', up_axis='z', front_axis='x')
    assert not flagged[0].watertight
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        remeshed = load_user_meshes(tmp_path, class_name='chair', up_axis='z', front_axis='x', remesh_resolution=24)
    assert remeshed[0].watertight and remeshed[0].mesh.is_volume
    np.testing.assert_allclose(remeshed[0].mesh.extents, sphere.extents, rtol=1e-6)


def test_bad_paths_raise_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match='ShapeNetCore v2'):
        load_user_meshes(tmp_path / 'missing')
    with pytest.raises(FileNotFoundError, match='no meshes found'):
        load_user_meshes(tmp_path)
    (tmp_path / 'chair').mkdir()
    (tmp_path / 'chair' / 'readme.txt').write_text('no meshes here')
    with pytest.raises(FileNotFoundError, match='expected'):
        load_user_meshes(tmp_path)
    generate('chair', 0).export(tmp_path / 'chair' / 'a.ply')
    with pytest.raises(FileNotFoundError, match="class 'dining table'"):
        load_user_meshes(tmp_path, class_name='dining table')


def test_unreadable_file_is_skipped_with_a_warning(tmp_path: Path) -> None:
    (tmp_path / 'broken.ply').write_bytes(b'not a ply file')
    generate('chair', 0).export(tmp_path / 'good.ply')
    with pytest.warns(RuntimeWarning, match='broken.ply'):
        records = load_user_meshes(tmp_path, class_name='chair', up_axis='z', front_axis='x')
    assert [r.name for r in records] == ['good']


def test_save_gallery_writes_a_png(tmp_path: Path) -> None:
    path = save_gallery(tmp_path / 'gallery.png', shapes_per_family=1)
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    extra = save_gallery(tmp_path / 'extra.png', shapes_per_family=1, extra=True)
    assert extra.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and extra.read_bytes() != path.read_bytes()
