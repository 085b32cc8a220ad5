"""NumPy poses, clouds and covariances as Foxglove's well-known messages (`foxglove.messages`),
so every result channel carries a `foxglove.*` schema that Foxglove draws natively."""

from __future__ import annotations

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    Duration,
    FrameTransform,
    FrameTransforms,
    JointState,
    JointStates,
    LinePrimitive,
    LinePrimitiveLineType,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from mcl3d.core.geometry import rot_to_quat

ELLIPSOID_SIGMA = 2.0  # the covariance ellipsoid's semi-axes are this many standard deviations
FLOAT32 = PackedElementFieldNumericType.Float32


def stamp(stamp_ns: int) -> Timestamp:
    return Timestamp(int(stamp_ns) // 1_000_000_000, int(stamp_ns) % 1_000_000_000)


def _vector_quaternion(T: np.ndarray) -> tuple[Vector3, Quaternion]:
    x, y, z = (float(v) for v in T[:3, 3])
    qx, qy, qz, qw = (float(v) for v in rot_to_quat(T[:3, :3]))
    return Vector3(x=x, y=y, z=z), Quaternion(x=qx, y=qy, z=qz, w=qw)


def pose(T: np.ndarray) -> Pose:
    """The 4x4 transform `T` as a Foxglove pose (quaternion x, y, z, w as in CONVENTIONS)."""
    position, orientation = _vector_quaternion(T)
    return Pose(position=position, orientation=orientation)


def pose_in_frame(stamp_ns: int, frame: str, T: np.ndarray) -> PoseInFrame:
    return PoseInFrame(timestamp=stamp(stamp_ns), frame_id=frame, pose=pose(T))


def poses_in_frame(stamp_ns: int, frame: str, poses: np.ndarray) -> PosesInFrame:
    return PosesInFrame(timestamp=stamp(stamp_ns), frame_id=frame, poses=[pose(T) for T in poses])


def transform(stamp_ns: int, parent: str, child: str, T_parent_child: np.ndarray
              ) -> FrameTransforms:
    translation, rotation = _vector_quaternion(T_parent_child)
    return FrameTransforms(transforms=[FrameTransform(
        timestamp=stamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
        translation=translation, rotation=rotation)])


def point_cloud(stamp_ns: int, frame: str, points: np.ndarray,
                extra: dict[str, np.ndarray] | None = None,
                T_frame_cloud: np.ndarray | None = None) -> PointCloud:
    """x, y, z and any `extra` per-point fields, all float32, packed point after point; the
    points are in `frame`, or in a cloud placed in `frame` by `T_frame_cloud` (the message's
    pose: a scan in the map frame without transforming its points)."""
    columns = [np.asarray(points, np.float32).reshape(-1, 3)]
    names = ["x", "y", "z"]
    for name, values in (extra or {}).items():
        columns.append(np.asarray(values, np.float32).reshape(-1, 1))
        names.append(name)
    packed = np.ascontiguousarray(np.hstack(columns), dtype="<f4")
    fields = [PackedElementField(name=n, offset=4 * i, type=FLOAT32) for i, n in enumerate(names)]
    origin = np.eye(4) if T_frame_cloud is None else T_frame_cloud
    return PointCloud(timestamp=stamp(stamp_ns), frame_id=frame, pose=pose(origin),
                      point_stride=4 * len(names), fields=fields, data=packed.tobytes())


def color(rgba: tuple[float, float, float, float]) -> Color:
    r, g, b, a = rgba
    return Color(r=r, g=g, b=b, a=a)


def ellipsoid(T: np.ndarray, position_cov: np.ndarray, rgba) -> SpherePrimitive:
    """The `ELLIPSOID_SIGMA` ellipsoid of a 3x3 positional covariance (m²) centred on `T`'s
    position. The covariance is in `T`'s own axes (the tangent at the mean, right
    perturbation, as the filters report it), so its eigenvectors are turned by `T`'s rotation."""
    cov = 0.5 * (position_cov + position_cov.T)
    eigvals, axes = np.linalg.eigh(cov)
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    frame = np.eye(4)
    frame[:3, :3] = T[:3, :3] @ axes
    frame[:3, 3] = T[:3, 3]
    dx, dy, dz = (2.0 * ELLIPSOID_SIGMA * np.sqrt(np.clip(eigvals, 0.0, None))).tolist()
    return SpherePrimitive(pose=pose(frame), size=Vector3(x=dx, y=dy, z=dz), color=color(rgba))


def arrow(T: np.ndarray, length_m: float, rgba) -> ArrowPrimitive:
    """An arrow along the pose's x axis (the lidar's forward direction)."""
    return ArrowPrimitive(pose=pose(T), shaft_length=0.7 * length_m,
                          shaft_diameter=0.08 * length_m, head_length=0.3 * length_m,
                          head_diameter=0.2 * length_m, color=color(rgba))


def text(T: np.ndarray, label: str, rgba, size_m: float = 0.3) -> TextPrimitive:
    return TextPrimitive(pose=pose(T), billboard=True, font_size=size_m, text=label,
                         color=color(rgba))


def lines(points: np.ndarray, rgba, kind: str = "strip", thickness_m: float = 0.05
          ) -> LinePrimitive:
    """A line strip through `points` (N, 3), or (`kind="list"`) segments between pairs."""
    line_type = LinePrimitiveLineType.LineStrip if kind == "strip" else (
        LinePrimitiveLineType.LineList)
    return LinePrimitive(type=line_type, pose=pose(np.eye(4)), thickness=thickness_m,
                         points=[Point3(x=float(x), y=float(y), z=float(z))
                                 for x, y, z in np.asarray(points, np.float64).reshape(-1, 3)],
                         color=color(rgba))


def scene(stamp_ns: int, frame: str, entities: dict[str, dict],
          replace: bool = True) -> SceneUpdate:
    """A scene that replaces everything the channel drew before (or, with `replace` False,
    adds to it): one entity per id, its primitives given by `SceneEntity` keyword (spheres,
    arrows, lines, texts)."""
    clear = SceneEntityDeletion(timestamp=stamp(stamp_ns), type=SceneEntityDeletionType.All)
    return SceneUpdate(deletions=[clear] if replace else [], entities=[
        SceneEntity(timestamp=stamp(stamp_ns), frame_id=frame, id=name,
                    lifetime=Duration(0, 0), **primitives)
        for name, primitives in entities.items()])


def named_values(stamp_ns: int, values: dict[str, float]) -> JointStates:
    """Named numbers for Foxglove's Plot panel: Foxglove has no scalar schema, and
    JointStates is its list of named floats (plot `/stats.joints[:]{name=="ess"}.position`)."""
    return JointStates(timestamp=stamp(stamp_ns), joints=[
        JointState(name=name, position=float(v)) for name, v in values.items()
        if v is not None and np.isfinite(v)])
