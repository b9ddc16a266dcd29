"""The smallest TF buffer the bag replay needs: stamped transforms per edge, chain lookup at a time.

Written on branch ``bags`` because the ``tf`` branch's buffer (issue 28 item 3) did not exist while
the replay was built; when that one lands it replaces this file and the two calls of
:mod:`gls_calibration.scan.bag_io` (``set_transform`` and ``lookup``) follow its API. tf2_ros is not
installable in the pip set-up, so nothing here imports ROS.

Each frame has one parent (a tree, as in tf2). A static edge holds one pose for all times; a dynamic
edge a time series, looked up by linear interpolation of the translation and slerp of the rotation
between the two samples around the stamp. Poses are 4x4 (child -> parent), in mm; stamps int ns.
"""
from __future__ import annotations

import bisect

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

_ROTATION_TOLERANCE = 1e-9


class TfBuffer:
    """Transforms between frames of one tree, static or stamped."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}
        self._samples: dict[str, tuple[list[int], list[np.ndarray]]] = {}

    def set_transform(self, parent: str, child: str, stamp_ns: int, pose: np.ndarray, static: bool = False) -> None:
        """Add the pose of ``child`` in ``parent`` (4x4, mm) at ``stamp_ns`` (any time when ``static``).

        Raises
        ------
        ValueError
            A non-finite or non-rigid pose, an empty or equal frame name, or a child given a second parent.
        """
        if not parent or not child or parent == child:
            raise ValueError(f"a transform needs two different frame names, got {parent!r} -> {child!r}")
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"the transform {parent} -> {child} at {stamp_ns} ns is not a finite 4x4 pose")
        rotation = pose[:3, :3]
        if (not np.allclose(rotation @ rotation.T, np.eye(3), atol=_ROTATION_TOLERANCE)
                or np.linalg.det(rotation) < 0):
            raise ValueError(f"the transform {parent} -> {child} at {stamp_ns} ns does not hold a proper rotation "
                             "(non-normalised quaternion?)")
        known = self._parent.get(child)
        if known is not None and known != parent:
            raise ValueError(f"frame {child} has two parents: {known} and {parent}")
        self._parent[child] = parent
        if static:
            self._static[child] = pose.copy()
            return
        stamps, poses = self._samples.setdefault(child, ([], []))
        at = bisect.bisect_right(stamps, int(stamp_ns))
        stamps.insert(at, int(stamp_ns))
        poses.insert(at, pose.copy())

    def _edge(self, child: str, stamp_ns: int, max_age_ns: int, where: str) -> np.ndarray:
        """Pose of ``child`` in its parent at ``stamp_ns``."""
        if child in self._static:
            return self._static[child]
        stamps, poses = self._samples[child]
        parent = self._parent[child]
        at = bisect.bisect_right(stamps, stamp_ns)
        if at == 0:
            raise ValueError(f"{where}: no pose of {child} in {parent} at or before {stamp_ns} ns")
        if stamps[at - 1] == stamp_ns:
            return poses[at - 1]
        age_ns = stamp_ns - stamps[at - 1]
        if age_ns > max_age_ns:
            raise ValueError(f"{where}: the newest pose of {child} in {parent} is {age_ns / 1e9:.4g} s older than "
                             f"{stamp_ns} ns (limit {max_age_ns / 1e9:.4g} s)")
        if at == len(stamps):
            raise ValueError(f"{where}: no pose of {child} in {parent} after {stamp_ns} ns (no extrapolation)")
        fraction = (stamp_ns - stamps[at - 1]) / (stamps[at] - stamps[at - 1])
        before, after = poses[at - 1], poses[at]
        pose = np.eye(4)
        pose[:3, 3] = (1.0 - fraction) * before[:3, 3] + fraction * after[:3, 3]
        pose[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix([before[:3, :3], after[:3, :3]]))(fraction).as_matrix()
        return pose

    def _to_root(self, frame: str, stamp_ns: int, max_age_ns: int, where: str) -> tuple[str, list[str], np.ndarray]:
        """Root of ``frame``'s tree, the frames on the way, and the pose of ``frame`` in the root."""
        pose = np.eye(4)
        path = [frame]
        while frame in self._parent:
            pose = self._edge(frame, stamp_ns, max_age_ns, where) @ pose
            frame = self._parent[frame]
            path.append(frame)
        return frame, path, pose

    def lookup(self, target: str, source: str, stamp_ns: int, max_age_ns: int, where: str = "tf") -> np.ndarray:
        """Pose of ``source`` in ``target`` (4x4, mm: maps ``source`` coordinates to ``target``) at ``stamp_ns``.

        ``max_age_ns``: the newest sample of a dynamic edge at or before the stamp may be this old, and a
        sample after it must exist. ValueError (prefixed ``where``) naming a missing frame or pose.
        """
        for frame in (target, source):
            if frame not in self._parent and frame not in self._parent.values():
                raise ValueError(f"{where}: frame {frame} is not in the transform tree "
                                 f"(frames: {', '.join(sorted(set(self._parent) | set(self._parent.values())))})")
        source_root, _, source_pose = self._to_root(source, stamp_ns, max_age_ns, where)
        target_root, _, target_pose = self._to_root(target, stamp_ns, max_age_ns, where)
        if source_root != target_root:
            raise ValueError(f"{where}: no transform from {source} to {target} (they hang from {source_root} and "
                             f"{target_root}, which nothing connects)")
        return np.linalg.inv(target_pose) @ source_pose
