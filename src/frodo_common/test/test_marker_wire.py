"""The MarkerArray written from numpy (`marker_wire`) is what the RMW writes: the same length, and read back by
the RMW the same message, for markers of every field kind and alignment (seeded random markers)."""
import numpy as np
import pytest
from geometry_msgs.msg import Point
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray, UVCoordinate

from frodo_common import conversions as conv
from frodo_common.marker_wire import MeshMarker, matches_rmw, read_marker_array, serialize_marker_array


def _random_marker(rng: np.random.Generator) -> Marker:
    def text() -> str:
        return ''.join(rng.choice(list('abcxyz é')) for _ in range(rng.integers(0, 9)))

    m = Marker(ns=text(), id=int(rng.integers(-5, 1000)), type=int(rng.integers(0, 12)), action=int(rng.integers(0, 4)),
               text=text(), texture_resource=text(), mesh_resource=text(), frame_locked=bool(rng.integers(2)),
               mesh_use_embedded_materials=bool(rng.integers(2)))
    m.header.frame_id = text()
    m.header.stamp.sec, m.header.stamp.nanosec = int(rng.integers(0, 2 ** 31)), int(rng.integers(0, 10 ** 9))
    m.lifetime.sec, m.lifetime.nanosec = int(rng.integers(0, 9)), int(rng.integers(0, 10 ** 9))
    p, q = m.pose.position, m.pose.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(v) for v in rng.normal(size=7))
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in rng.random(3))
    m.color = ColorRGBA(r=0.25, g=0.5, b=float(np.float32(rng.random())), a=1.0)
    m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in rng.normal(size=(rng.integers(0, 5), 3))]
    m.colors = [ColorRGBA(r=0.5, g=0.125, b=0.0, a=1.0)] * int(rng.integers(0, 3))
    m.uv_coordinates = [UVCoordinate(u=0.5, v=0.75)] * int(rng.integers(0, 3))
    m.texture.header.frame_id, m.texture.format = text(), text()
    m.texture.data = [int(v) for v in rng.integers(0, 256, rng.integers(0, 6))]
    m.mesh_file.filename = text()
    m.mesh_file.data = [int(v) for v in rng.integers(0, 256, rng.integers(0, 6))]
    return m


def _read(data: bytes) -> MarkerArray:
    return deserialize_message(data, MarkerArray)


def test_random_marker_arrays_read_back_as_the_rmw_writes_them():
    assert matches_rmw()
    rng = np.random.default_rng(7)
    for _ in range(60):
        markers = [_random_marker(rng) for _ in range(rng.integers(0, 5))]
        ours, theirs = serialize_marker_array(markers), serialize_message(MarkerArray(markers=markers))
        assert len(ours) == len(theirs)
        assert _read(ours) == _read(theirs)


def test_mesh_markers_with_array_points_equal_their_messages():
    rng = np.random.default_rng(3)
    vertices, faces = rng.normal(size=(40, 3)), rng.integers(0, 40, size=(25, 3))
    mesh = MeshMarker('estimate', *conv.mesh_marker_parts(vertices, faces, 'dining table', 4, 1_500_000_007, 'world'))
    mesh.restamp(2_000_000_009)
    assert conv.with_points(*mesh.parts()) == conv.mesh_to_marker(vertices, faces, 'dining table', 4, 2_000_000_009,
                                                                  'world')
    delete = conv.delete_marker('chair', 2, 2_000_000_009, 'world')
    for order in ([delete, mesh], [mesh, delete, mesh]):   # a mesh after an odd-length marker: other alignment
        ours = serialize_marker_array([m.parts() if isinstance(m, MeshMarker) else m for m in order])
        theirs = serialize_message(MarkerArray(markers=[conv.with_points(*m.parts()) if isinstance(m, MeshMarker) else m
                                                        for m in order]))
        assert len(ours) == len(theirs) and _read(ours) == _read(theirs)


def test_serialised_arrays_are_read_back_with_their_points_as_arrays():
    rng = np.random.default_rng(11)
    for _ in range(40):
        markers = [_random_marker(rng) for _ in range(rng.integers(0, 5))]
        read = read_marker_array(serialize_message(MarkerArray(markers=markers)))   # the RMW's own bytes
        assert len(read) == len(markers)
        for (marker, points), original in zip(read, markers):
            expected = np.array([(p.x, p.y, p.z) for p in original.points]).reshape(-1, 3)
            assert np.array_equal(points, expected)
            assert marker == _read(serialize_message(MarkerArray(markers=[conv.with_points(original, np.zeros(
                (0, 3)))]))).markers[0]      # every other field, float32 colours as on the wire
    data = serialize_marker_array([_random_marker(rng)])
    for cut in (2, 9, len(data) - 1):
        with pytest.raises(ValueError):
            read_marker_array(data[:cut])
