"""ROS message <-> numpy conversions: the one place in the project that converts messages.

Images, camera info, poses, point clouds, record tables (PointCloud2 used as a stamped typed table),
and meshes/boxes as visualization_msgs markers.
"""
from __future__ import annotations

import copy

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker

from frodo_common.geometry import Box3D, make_transform, matrix_to_quat, quat_to_matrix, yaw_matrix


class ConversionError(ValueError):
    """A message cannot be converted: wrong encoding, size mismatch, NaNs, ..."""


# ---------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Time) -> int:
    """Nanoseconds since epoch of a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """builtin_interfaces/Time from nanoseconds."""
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def make_header(stamp_ns: int, frame_id: str) -> Header:
    """std_msgs/Header with a stamp in nanoseconds."""
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


# ---------------------------------------------------------------- images
_IMAGE_DTYPES = {
    'rgb8': (np.uint8, 3), 'bgr8': (np.uint8, 3), 'rgba8': (np.uint8, 4), 'bgra8': (np.uint8, 4),
    'mono8': (np.uint8, 1), '8UC1': (np.uint8, 1), 'mono16': (np.uint16, 1), '16UC1': (np.uint16, 1),
    '32FC1': (np.float32, 1),
}


# Largest image side accepted (pixels): beyond it a frame is rejected rather than exhausting memory
# (a 10000-pixel-wide RGB frame is ~200 MB as float per channel in the encoders).
MAX_IMAGE_SIDE = 8192
# Colour encodings of the contract, and those converted to RGB on the way in (the caller reports it).
COLOUR_ENCODINGS = ('rgb8', 'bgr8')
CONVERTED_COLOUR_ENCODINGS = ('rgba8', 'bgra8', 'mono8', '8UC1')


def image_to_numpy(msg: Image, max_side: int = MAX_IMAGE_SIDE) -> np.ndarray:
    """Image message -> array (H, W) or (H, W, C) in the message's own channel order.

    Raises ConversionError for unsupported encodings, zero or oversized dimensions, a step shorter than a
    row, and a data size other than step * height.
    """
    if msg.encoding not in _IMAGE_DTYPES:
        raise ConversionError(f'unsupported image encoding {msg.encoding!r}; supported: {sorted(_IMAGE_DTYPES)}')
    dtype, channels = _IMAGE_DTYPES[msg.encoding]
    dtype = np.dtype(dtype).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.height == 0 or msg.width == 0:
        raise ConversionError('image has zero width or height')
    if max(msg.width, msg.height) > max_side:
        raise ConversionError(f'image is {msg.width}x{msg.height}: larger than {max_side} pixels on a side '
                              '(rejected to bound memory; downscale it before publishing)')
    if msg.step < row_bytes:
        raise ConversionError(f'image step {msg.step} is shorter than a row ({msg.width} x {channels} x '
                              f'{dtype.itemsize} = {row_bytes} bytes for {msg.encoding})')
    if len(msg.data) != msg.step * msg.height:
        raise ConversionError(f'image data has {len(msg.data)} bytes, expected step x height = '
                              f'{msg.step} x {msg.height} = {msg.step * msg.height} ({msg.width}x{msg.height} '
                              f'{msg.encoding}); data too short or too long')
    buf = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.height, msg.step)
    arr = buf[:, :row_bytes].copy().view(dtype).reshape(msg.height, msg.width, channels)
    arr = arr.astype(dtype.newbyteorder('='), copy=False)
    return arr[..., 0] if channels == 1 else arr


def image_to_rgb(msg: Image) -> np.ndarray:
    """Colour image message -> RGB uint8 (H, W, 3).

    rgb8/bgr8 (the contract's encodings) convert directly; rgba8/bgra8 (alpha dropped) and mono8 (grey
    replicated) are converted too, see `CONVERTED_COLOUR_ENCODINGS`; anything else (16UC1, 32FC1: an
    instance or depth image on the colour topic?) raises ConversionError.
    """
    if msg.encoding not in COLOUR_ENCODINGS + CONVERTED_COLOUR_ENCODINGS:
        raise ConversionError(f'colour image must be rgb8 or bgr8 (rgba8, bgra8, mono8 are converted), got '
                              f'{msg.encoding!r}' + (' (an instance or depth image on the colour topic?)'
                                                     if msg.encoding in ('16UC1', 'mono16', '32FC1') else ''))
    arr = image_to_numpy(msg)
    if arr.ndim == 2:
        return np.repeat(arr[..., None], 3, axis=2)
    arr = arr[..., :3]
    return arr[..., ::-1].copy() if msg.encoding.startswith('bgr') else arr


def image_size(msg: Image | CameraInfo) -> tuple[int, int]:
    """(width, height) of an Image or CameraInfo message."""
    return int(msg.width), int(msg.height)


def check_same_size(size: tuple[int, int], expected: tuple[int, int], what: str, reference: str) -> None:
    """Raise ConversionError naming both when `size` (w, h) of `what` differs from `expected` of `reference`."""
    if tuple(size) != tuple(expected):
        raise ConversionError(f'{what} is {size[0]}x{size[1]} but {reference} is {expected[0]}x{expected[1]}')


def numpy_to_image(arr: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> Image:
    """Array -> Image message with the given encoding (little endian, packed rows)."""
    if encoding not in _IMAGE_DTYPES:
        raise ConversionError(f'unsupported image encoding {encoding!r}')
    dtype, channels = _IMAGE_DTYPES[encoding]
    arr = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder('<'))
    if (arr.ndim == 2 and channels != 1) or (arr.ndim == 3 and arr.shape[2] != channels):
        raise ConversionError(f'array of shape {arr.shape} does not fit encoding {encoding}')
    h, w = arr.shape[:2]
    return Image(header=make_header(stamp_ns, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
                 step=w * channels * arr.dtype.itemsize, data=arr.tobytes())


# ---------------------------------------------------------------- camera and pose
def camera_info_to_K(msg: CameraInfo) -> np.ndarray:
    """Intrinsics (3, 3) from CameraInfo; raises ConversionError when k is unusable."""
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ConversionError(f'camera_info has invalid intrinsics k={list(msg.k)} (fx, fy must be finite and > 0)')
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ConversionError(f'camera_info k={list(msg.k)} is not an upper-triangular pinhole matrix '
                              '(last row must be 0 0 1)')
    if msg.width == 0 or msg.height == 0:
        raise ConversionError('camera_info has zero width/height')
    if max(msg.width, msg.height) > MAX_IMAGE_SIDE:
        raise ConversionError(f'camera_info size {msg.width}x{msg.height} exceeds {MAX_IMAGE_SIDE} pixels')
    if not np.all(np.isfinite(np.asarray(msg.d, dtype=np.float64))):
        raise ConversionError(f'camera_info distortion d={list(msg.d)} contains NaN or inf')
    return K


def make_camera_info(K: np.ndarray, width: int, height: int, stamp_ns: int, frame_id: str) -> CameraInfo:
    """CameraInfo for an undistorted pinhole camera (plumb_bob, d = 0)."""
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CameraInfo(header=make_header(stamp_ns, frame_id), width=int(width), height=int(height),
                      distortion_model='plumb_bob', d=[0.0] * 5, k=K.ravel().tolist(),
                      r=np.eye(3).ravel().tolist(), p=P.ravel().tolist())


# A quaternion whose norm is further than this from 1 is rejected (closer ones are normalised: rounding).
QUATERNION_NORM_TOLERANCE = 1e-2


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """4x4 transform from geometry_msgs/Pose; raises ConversionError on NaN/inf or a non-unit quaternion."""
    t = np.array([pose.position.x, pose.position.y, pose.position.z])
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ConversionError('pose contains NaN or inf')
    with np.errstate(over='ignore'):   # a huge quaternion's norm is inf: rejected below
        norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ConversionError(f'pose quaternion (x, y, z, w) = {q.tolist()} has norm {norm:.4g}, not 1 '
                              f'(tolerance {QUATERNION_NORM_TOLERANCE})')
    try:
        return make_transform(quat_to_matrix(q), t)
    except ValueError as err:
        raise ConversionError(str(err)) from None


def matrix_to_pose(T: np.ndarray) -> Pose:
    """geometry_msgs/Pose from a 4x4 rigid transform (scale, if any, is dropped)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3] / np.linalg.norm(T[:3, 0])
    q = matrix_to_quat(R)
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def make_pose_stamped(T: np.ndarray, stamp_ns: int, frame_id: str) -> PoseStamped:
    """PoseStamped from a 4x4 transform."""
    return PoseStamped(header=make_header(stamp_ns, frame_id), pose=matrix_to_pose(T))


# ---------------------------------------------------------------- point clouds and tables
_FIELD_TYPES = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8, PointField.INT16: np.int16, PointField.UINT16: np.uint16,
    PointField.INT32: np.int32, PointField.UINT32: np.uint32, PointField.FLOAT32: np.float32,
    PointField.FLOAT64: np.float64,
}
_DTYPE_TO_FIELD = {np.dtype(v): k for k, v in _FIELD_TYPES.items()}


def table_to_cloud(table: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """Structured array (N,) -> PointCloud2 (height 1). Sub-array fields become PointFields with count > 1."""
    fields = []
    for name in table.dtype.names:
        ftype, offset = table.dtype.fields[name][:2]
        base, count = (ftype.base, int(np.prod(ftype.shape))) if ftype.shape else (ftype, 1)
        if np.dtype(base) not in _DTYPE_TO_FIELD:
            raise ConversionError(f'field {name!r} has unsupported dtype {base}')
        fields.append(PointField(name=name, offset=offset, datatype=_DTYPE_TO_FIELD[np.dtype(base)], count=count))
    data = np.ascontiguousarray(table).tobytes()
    return PointCloud2(header=make_header(stamp_ns, frame_id), height=1, width=len(table), fields=fields,
                       is_bigendian=False, point_step=table.dtype.itemsize, row_step=table.dtype.itemsize * len(table),
                       data=data, is_dense=True)


def cloud_to_table(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 -> structured array (height*width,) with every field (count > 1 -> sub-array)."""
    if msg.is_bigendian:
        raise ConversionError('big-endian PointCloud2 is not supported')
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _FIELD_TYPES:
            raise ConversionError(f'field {f.name!r} has unknown datatype {f.datatype}')
        if f.count < 1 or f.name in names:
            raise ConversionError(f'field {f.name!r}: count {f.count} < 1 or a repeated name')
        end = f.offset + np.dtype(_FIELD_TYPES[f.datatype]).itemsize * f.count
        if end > msg.point_step:
            raise ConversionError(f'field {f.name!r} ends at byte {end}, beyond point_step {msg.point_step}')
        names.append(f.name)
        formats.append((_FIELD_TYPES[f.datatype], (f.count,)) if f.count > 1 else _FIELD_TYPES[f.datatype])
        offsets.append(f.offset)
    try:
        dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': msg.point_step})
    except (ValueError, TypeError) as err:   # e.g. overlapping fields
        raise ConversionError(f'PointCloud2 fields do not form a record: {err}') from None
    n = msg.width * msg.height
    if len(msg.data) < n * msg.point_step:
        raise ConversionError(f'PointCloud2 data too short: {len(msg.data)} < {n} x {msg.point_step}')
    return np.frombuffer(bytes(msg.data), dtype=dtype, count=n).copy()


def xyz_to_cloud(points: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """Points (N, 3) -> PointCloud2 with float32 x, y, z."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    table = np.zeros(len(pts), dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    table['x'], table['y'], table['z'] = pts.T
    return table_to_cloud(table, stamp_ns, frame_id)


def cloud_to_xyz(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 with x, y, z fields -> finite points (N, 3) float64."""
    table = cloud_to_table(msg)
    missing = {'x', 'y', 'z'} - set(table.dtype.names or ())
    if missing:
        raise ConversionError(f'PointCloud2 lacks fields {sorted(missing)}')
    pts = np.stack([table['x'], table['y'], table['z']], axis=1).astype(np.float64)
    return pts[np.all(np.isfinite(pts), axis=1)]


# ---------------------------------------------------------------- markers
def _color(rgba) -> ColorRGBA:
    r, g, b, a = (float(v) for v in rgba)
    return ColorRGBA(r=r, g=g, b=b, a=a)


def mesh_marker_parts(vertices: np.ndarray, faces: np.ndarray, ns: str, marker_id: int, stamp_ns: int,
                      frame_id: str, rgba=(0.8, 0.6, 0.2, 1.0)) -> tuple[Marker, np.ndarray]:
    """`mesh_to_marker` in two parts: the marker without its points, and the points as an array (3F, 3) (the
    triangles' corners in order), for `marker_wire.serialize_marker_array`."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).ravel()].reshape(-1, 3)
    m = Marker(header=make_header(stamp_ns, frame_id), ns=ns, id=int(marker_id), type=Marker.TRIANGLE_LIST,
               action=Marker.ADD, color=_color(rgba))
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    return m, tri


def with_points(marker: Marker, points: np.ndarray) -> Marker:
    """A copy of `marker` whose points are the rows of `points` (N, 3)."""
    m = copy.deepcopy(marker)
    m.points = [Point(x=x, y=y, z=z) for x, y, z in points.tolist()]   # tolist: Python floats at once, 2x faster
    return m


def mesh_to_marker(vertices: np.ndarray, faces: np.ndarray, ns: str, marker_id: int, stamp_ns: int,
                   frame_id: str, rgba=(0.8, 0.6, 0.2, 1.0)) -> Marker:
    """TRIANGLE_LIST marker with world-frame vertices (identity pose, unit scale), per CONTRACT.md."""
    return with_points(*mesh_marker_parts(vertices, faces, ns, marker_id, stamp_ns, frame_id, rgba))


def marker_to_mesh(marker: Marker, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """TRIANGLE_LIST marker -> (vertices (3F, 3) in the marker's frame after pose and scale, faces (F, 3)).
    points: (3F, 3) in place of the marker's own (as `marker_wire.read_marker_array` gives them)."""
    if marker.type != Marker.TRIANGLE_LIST:
        raise ConversionError(f'marker {marker.ns}/{marker.id} is type {marker.type}, expected TRIANGLE_LIST')
    pts = np.array([[p.x, p.y, p.z] for p in marker.points] if points is None else points,
                   dtype=np.float64).reshape(-1, 3)
    if len(pts) % 3:
        raise ConversionError(f'marker {marker.ns}/{marker.id} has {len(pts)} points, not a multiple of 3')
    pts = pts * np.array([marker.scale.x, marker.scale.y, marker.scale.z])
    T = pose_to_matrix(marker.pose)
    pts = pts @ T[:3, :3].T + T[:3, 3]
    return pts, np.arange(len(pts)).reshape(-1, 3)


def box_to_marker(center, size, yaw: float, ns: str, marker_id: int, stamp_ns: int, frame_id: str,
                  rgba=(0.2, 0.8, 0.2, 0.4)) -> Marker:
    """CUBE marker for an upright box (centre, size (dx, dy, dz), yaw about z)."""
    m = Marker(header=make_header(stamp_ns, frame_id), ns=ns, id=int(marker_id), type=Marker.CUBE,
               action=Marker.ADD, color=_color(rgba))
    m.pose = matrix_to_pose(make_transform(yaw_matrix(yaw), center))
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in size)
    return m


def marker_to_box(marker: Marker) -> Box3D:
    """CUBE marker -> `Box3D` (centre, size, yaw about z; unpacks as that triple)."""
    T = pose_to_matrix(marker.pose)
    yaw = float(np.arctan2(T[1, 0], T[0, 0]))
    return Box3D(T[:3, 3].copy(), np.array([marker.scale.x, marker.scale.y, marker.scale.z]), yaw)


def delete_marker(ns: str, marker_id: int, stamp_ns: int, frame_id: str) -> Marker:
    """DELETE marker for (ns, id)."""
    return Marker(header=make_header(stamp_ns, frame_id), ns=ns, id=int(marker_id), action=Marker.DELETE)
