"""A visualization_msgs/MarkerArray serialised straight from numpy, and read back into numpy: the object map's
meshes without one Python `Point` per vertex (no ROS imports beyond the message types).

Why: `/frodo/objects` carries every object's mesh in every message (CONTRACT.md), and the optimiser republishes
it after each stage of each object. Through rclpy, a mesh of 20,000 triangles became 60,000 `Point` objects
(~0.23 s) and each message was converted to C again on publishing (~0.08 s per such mesh): on the demo walk
about 6 s of the optimiser thread went to this, between stages, and a listener turning each map back into
Point objects (the Rerun viewer node) spent ~8 s of CPU per demo run on it, on the optimiser's cores. Written
here, the points are one `ndarray.tobytes()`, and read, one `np.frombuffer`.

The encoding is the ROS 2 wire format of the message (OMG CDR, XCDR1, little-endian): a 4-byte encapsulation
header, then every field in declaration order at an offset (counted after the header) aligned to its primitive
size, strings as a uint32 length (NUL included) and the bytes with their NUL, sequences as a uint32 count and the
elements. Padding bytes are zeros (the RMW leaves
whatever was in its buffer). `matches_rmw` checks a sample against the running RMW (rclpy.serialization): the same
length and, read back by it, the same message; a middleware that writes the type differently is detected, and the
caller publishes messages instead.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, UVCoordinate

from frodo_common.conversions import ns_to_stamp

CDR_LE_HEADER = b'\x00\x01\x00\x00'      # encapsulation: plain CDR, little-endian, no options


class _CdrWriter:
    """Appends CDR-encoded values, aligning each to its size relative to the start of the payload."""

    def __init__(self) -> None:
        self.parts: list[bytes] = [CDR_LE_HEADER]
        self.offset = 0

    def _align(self, size: int) -> None:
        pad = -self.offset % size
        if pad:
            self.parts.append(b'\x00' * pad)
            self.offset += pad

    def raw(self, data: bytes, align: int = 1) -> None:
        self._align(align)
        self.parts.append(data)
        self.offset += len(data)

    def pack(self, fmt: str, *values, align: int) -> None:
        self.raw(struct.pack('<' + fmt, *values), align)

    def string(self, text: str) -> None:
        data = text.encode('utf-8') + b'\x00'
        self.pack('I', len(data), align=4)
        self.raw(data)

    def octets(self, data) -> None:
        data = bytes(data)
        self.pack('I', len(data), align=4)
        self.raw(data)

    def header(self, header) -> None:
        self.pack('iI', header.stamp.sec, header.stamp.nanosec, align=4)
        self.string(header.frame_id)

    def getvalue(self) -> bytes:
        return b''.join(self.parts)


def _write_marker(w: _CdrWriter, m: Marker, points: np.ndarray | None) -> None:
    """One Marker (Jazzy's definition); `points` (N, 3) replaces m.points when given."""
    w.header(m.header)
    w.string(m.ns)
    w.pack('iii', m.id, m.type, m.action, align=4)
    p, q = m.pose.position, m.pose.orientation
    w.pack('7d', p.x, p.y, p.z, q.x, q.y, q.z, q.w, align=8)
    w.pack('3d', m.scale.x, m.scale.y, m.scale.z, align=8)
    w.pack('4f', m.color.r, m.color.g, m.color.b, m.color.a, align=4)
    w.pack('iI', m.lifetime.sec, m.lifetime.nanosec, align=4)
    w.pack('?', m.frame_locked, align=1)
    if points is None:
        points = np.array([(pt.x, pt.y, pt.z) for pt in m.points], dtype=np.float64).reshape(-1, 3)
    w.pack('I', len(points), align=4)
    if len(points):
        w.raw(np.ascontiguousarray(points, dtype='<f8').tobytes(), align=8)
    w.pack('I', len(m.colors), align=4)
    for c in m.colors:
        w.pack('4f', c.r, c.g, c.b, c.a, align=4)
    w.string(m.texture_resource)
    w.header(m.texture.header)
    w.string(m.texture.format)
    w.octets(m.texture.data)
    w.pack('I', len(m.uv_coordinates), align=4)
    for uv in m.uv_coordinates:
        w.pack('2f', uv.u, uv.v, align=4)
    w.string(m.text)
    w.string(m.mesh_resource)
    w.string(m.mesh_file.filename)
    w.octets(m.mesh_file.data)
    w.pack('?', m.mesh_use_embedded_materials, align=1)


def serialize_marker_array(markers: Sequence[Marker | tuple[Marker, np.ndarray]]) -> bytes:
    """The serialised MarkerArray of `markers`: each a Marker, or (marker, points (N, 3)) whose points stand in
    for the marker's own (a mesh's triangle corners, kept as an array). Publish it with `Publisher.publish`
    (rclpy publishes bytes as they are)."""
    w = _CdrWriter()
    w.pack('I', len(markers), align=4)
    for item in markers:
        marker, points = item if isinstance(item, tuple) else (item, None)
        _write_marker(w, marker, points)
    return w.getvalue()


class _CdrReader:
    """Reads CDR-encoded values written as `_CdrWriter` writes them (little-endian only)."""

    def __init__(self, data: bytes) -> None:
        if len(data) < 4 or data[:2] != CDR_LE_HEADER[:2]:
            raise ValueError(f'not a little-endian CDR message (header {bytes(data[:4]).hex()})')
        self.view = memoryview(data)[4:]
        self.offset = 0

    def _take(self, size: int, align: int) -> memoryview:
        self.offset += -self.offset % align
        if self.offset + size > len(self.view):
            raise ValueError(f'message truncated at byte {self.offset + 4} (needs {size} more)')
        chunk = self.view[self.offset:self.offset + size]
        self.offset += size
        return chunk

    def doubles(self, rows: int) -> np.ndarray:
        """`rows` x 3 float64 values (a sequence of Points' data), as an array of its own."""
        return np.frombuffer(self._take(24 * rows, 8), dtype='<f8').reshape(rows, 3).astype(np.float64)

    def unpack(self, fmt: str, align: int) -> tuple:
        return struct.unpack('<' + fmt, self._take(struct.calcsize('<' + fmt), align))

    def count(self) -> int:
        return self.unpack('I', 4)[0]

    def string(self) -> str:
        data = bytes(self._take(self.count(), 1))
        return data[:-1].decode('utf-8') if data else ''

    def octets(self) -> list[int]:
        return list(bytes(self._take(self.count(), 1)))

    def header(self, header) -> None:
        header.stamp.sec, header.stamp.nanosec = self.unpack('iI', 4)
        header.frame_id = self.string()


def _read_marker(r: _CdrReader) -> tuple[Marker, np.ndarray]:
    """One Marker (Jazzy's definition), its points as an array (N, 3) instead of Point messages."""
    m = Marker()
    r.header(m.header)
    m.ns = r.string()
    m.id, m.type, m.action = r.unpack('iii', 4)
    p, q = m.pose.position, m.pose.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = r.unpack('7d', 8)
    m.scale.x, m.scale.y, m.scale.z = r.unpack('3d', 8)
    m.color.r, m.color.g, m.color.b, m.color.a = r.unpack('4f', 4)
    m.lifetime.sec, m.lifetime.nanosec = r.unpack('iI', 4)
    m.frame_locked = r.unpack('?', 1)[0]
    n = r.count()
    points = r.doubles(n) if n else np.zeros((0, 3))      # no alignment padding before an empty sequence
    m.colors = [ColorRGBA(r=c[0], g=c[1], b=c[2], a=c[3]) for c in (r.unpack('4f', 4) for _ in range(r.count()))]
    m.texture_resource = r.string()
    r.header(m.texture.header)
    m.texture.format = r.string()
    m.texture.data = r.octets()
    m.uv_coordinates = [UVCoordinate(u=u, v=v) for u, v in (r.unpack('2f', 4) for _ in range(r.count()))]
    m.text = r.string()
    m.mesh_resource = r.string()
    m.mesh_file.filename = r.string()
    m.mesh_file.data = r.octets()
    m.mesh_use_embedded_materials = r.unpack('?', 1)[0]
    return m, points


def read_marker_array(data: bytes) -> list[tuple[Marker, np.ndarray]]:
    """The markers of a serialised MarkerArray (a `raw=True` subscription's message), each with its points as an
    array (N, 3) and its own `points` left empty: no Point message per vertex. Raises ValueError on a message
    that is not a little-endian CDR MarkerArray or is cut short."""
    r = _CdrReader(data)
    return [_read_marker(r) for _ in range(r.count())]


@dataclass(eq=False)
class MeshMarker:
    """A TRIANGLE_LIST marker with its points kept as an array (`conversions.mesh_marker_parts`).

    source: what it was built from (its owner's cache key); marker: the marker without points; points: (3F, 3)."""
    source: object
    marker: Marker
    points: np.ndarray

    def restamp(self, stamp_ns: int) -> None:
        self.marker.header.stamp = ns_to_stamp(stamp_ns)

    def parts(self) -> tuple[Marker, np.ndarray]:
        """(marker, points) for `serialize_marker_array`."""
        return self.marker, self.points


def matches_rmw() -> bool:
    """True when the running RMW reads `serialize_marker_array`'s bytes back as the message they encode, and its
    own serialiser gives as many bytes, for a sample covering every field kind (odd string lengths, empty and filled
    sequences, a mesh after a delete)."""
    from geometry_msgs.msg import Point
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    mesh = Marker(ns='dining table', id=7, type=Marker.TRIANGLE_LIST, action=Marker.ADD)
    mesh.header.frame_id, mesh.header.stamp.sec, mesh.header.stamp.nanosec = 'map', 12, 345
    mesh.pose.orientation.w, mesh.scale.x, mesh.color.a = 1.0, 1.0, 0.5
    corners = np.arange(9, dtype=np.float64).reshape(3, 3) / 7.0
    mesh.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in corners]
    delete = Marker(ns='chair', id=3, action=Marker.DELETE, text='ab', frame_locked=True)
    delete.colors = [ColorRGBA(r=0.25, g=0.5, b=0.75, a=1.0)]
    delete.uv_coordinates = [UVCoordinate(u=0.5, v=0.25)]
    delete.texture.format, delete.texture.data = 'png', [1, 2, 3]
    delete.mesh_file.filename, delete.mesh_file.data = 'm.stl', [4, 5]
    sample = [delete, mesh]
    bare = Marker()
    bare.header, bare.ns, bare.id, bare.type = mesh.header, mesh.ns, mesh.id, mesh.type
    bare.pose, bare.scale, bare.color = mesh.pose, mesh.scale, mesh.color
    for ours, message in ((serialize_marker_array([delete, (bare, corners)]), MarkerArray(markers=sample)),
                          (serialize_marker_array([]), MarkerArray())):
        if len(ours) != len(serialize_message(message)) or deserialize_message(ours, MarkerArray) != message:
            return False
    return True
