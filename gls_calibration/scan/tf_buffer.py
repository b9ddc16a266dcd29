"""The TF buffer of bag replay and the streaming acquisition: stamped transforms per edge, chain lookups.

Hand-written because tf2 / tf2_ros are not installable in the pip set-up (no wheels); nothing here
imports ROS, so bag replay and the live node (:mod:`gls_calibration.scan.bag_io`,
:mod:`gls_calibration.nodes.stream_acquisition`) place profiles with the same arithmetic.

Each frame has one parent (a tree, as in tf2). A static edge holds one pose for all times; a dynamic
edge a time series, looked up by linear interpolation of the translation and slerp of the rotation
between the two samples around the stamp. Poses are 4x4 (child -> parent), in mm; stamps int ns.
A whole sweep's stamps are looked up at once (:meth:`TfBuffer.try_lookup_many`): one search of each
edge's sorted stamps and one vectorised slerp, with every stamp's failure named as a single lookup
names it. An edge's samples are turned into arrays at its first lookup after a sample was added (work
in proportion to the samples held), so a sweep is looked up in one call, not stamp by stamp between
additions.
"""
from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

_ROTATION_TOLERANCE = 1e-9
# |R R^T - I| may reach this, element by element: np.allclose(R R^T, I, atol=_ROTATION_TOLERANCE) with its
# default rtol (1e-5) written out, since allclose's own overhead was a third of the cost of adding a transform
_GRAM_LIMIT = _ROTATION_TOLERANCE + 1e-5 * np.eye(3)


@dataclass(frozen=True)
class _Track:
    """A dynamic edge's samples as arrays, for vectorised lookups (rebuilt when a sample is added)."""

    stamps_ns: np.ndarray       # (k,) int64, sorted
    poses: np.ndarray           # (k, 4, 4)
    rotations: Rotation         # k
    steps: np.ndarray           # (k - 1, 3) rotation vector from each sample to the next (slerp's arc)

    @classmethod
    def of(cls, stamps_ns: list[int], poses: list[np.ndarray]) -> "_Track":
        stack = np.stack(poses)
        rotations = Rotation.from_matrix(stack[:, :3, :3])
        steps = (rotations[:-1].inv() * rotations[1:]).as_rotvec() if len(poses) > 1 else np.zeros((0, 3))
        return cls(np.asarray(stamps_ns, dtype=np.int64), stack, rotations, steps)


def _check_names(parent: str, child: str) -> None:
    if not parent or not child or parent == child:
        raise ValueError(f"a transform needs two different frame names, got {parent!r} -> {child!r}")


def _improper(parent: str, child: str, stamp_ns: int) -> str:
    return (f"the transform {parent} -> {child} at {stamp_ns} ns does not hold a proper rotation "
            "(non-normalised quaternion?)")


class TfBuffer:
    """Transforms between frames of one tree, static or stamped.

    Safe to feed from one thread while another looks up (a live node's subscriptions and its service):
    a lookup sees the samples added before it, never half an addition or an outdated cached edge.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}
        self._samples: dict[str, tuple[list[int], list[np.ndarray]]] = {}
        self._tracks: dict[str, _Track] = {}

    def set_transform(self, parent: str, child: str, stamp_ns: int, pose: np.ndarray, static: bool = False) -> None:
        """Add the pose of ``child`` in ``parent`` (4x4, mm) at ``stamp_ns`` (any time when ``static``).

        Raises
        ------
        ValueError
            A non-finite or non-rigid pose, an empty or equal frame name, or a child given a second parent.
        """
        _check_names(parent, child)
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"the transform {parent} -> {child} at {stamp_ns} ns is not a finite 4x4 pose")
        rotation = pose[:3, :3]
        if not (np.abs(rotation @ rotation.T - np.eye(3)) <= _GRAM_LIMIT).all() or np.linalg.det(rotation) < 0:
            raise ValueError(_improper(parent, child, stamp_ns))
        with self._lock:
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
            self._tracks.pop(child, None)

    def set_transforms(self, parent: str, child: str, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
        """Add the poses of ``child`` in ``parent`` (k, 4, 4; mm) at ``stamps_ns`` (k,) in one step (dynamic).

        What :meth:`set_transform` for each sample in turn does, with the checks in bulk: the same
        samples in the same order, and on a bad sample the same ``ValueError`` (the samples before
        it added).

        Raises
        ------
        ValueError
            As :meth:`set_transform`, for the first bad sample.
        """
        _check_names(parent, child)
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        poses = np.asarray(poses, dtype=float)
        if poses.shape != (stamps_ns.size, 4, 4):
            raise ValueError(f"the transforms {parent} -> {child}: {stamps_ns.size} stamps but poses of shape "
                             f"{poses.shape}")
        rotations = poses[:, :3, :3]
        bad = ~np.isfinite(poses).all(axis=(1, 2))
        with np.errstate(invalid="ignore"):
            gram = np.abs(rotations @ np.swapaxes(rotations, 1, 2) - np.eye(3))
            finite_rotations = np.where(bad[:, None, None], np.eye(3), rotations)    # det refuses NaN
            bad |= ~(gram <= _GRAM_LIMIT).all(axis=(1, 2)) | (np.linalg.det(finite_rotations) < 0)
        first = int(np.argmax(bad)) if bad.any() else stamps_ns.size
        with self._lock:
            known = self._parent.get(child)
            if known is not None and known != parent:
                raise ValueError(f"frame {child} has two parents: {known} and {parent}")
            if first:
                self._parent[child] = parent
                stamps, held = self._samples.setdefault(child, ([], []))
                new_stamps = stamps_ns[:first].tolist()
                if (not stamps or new_stamps[0] >= stamps[-1]) and all(np.diff(stamps_ns[:first]) >= 0):
                    stamps.extend(new_stamps)        # in time order after what is held: as bisect_right would
                    held.extend(poses[:first].copy())
                else:
                    for stamp_ns, pose in zip(new_stamps, poses[:first]):
                        at = bisect.bisect_right(stamps, stamp_ns)
                        stamps.insert(at, stamp_ns)
                        held.insert(at, pose.copy())
                self._tracks.pop(child, None)
        if first < stamps_ns.size:
            self.set_transform(parent, child, int(stamps_ns[first]), poses[first])    # raises its message

    def _track(self, child: str) -> _Track:
        track = self._tracks.get(child)
        if track is None:
            track = self._tracks[child] = _Track.of(*self._samples[child])
        return track

    def _edge(self, child: str, stamps_ns: np.ndarray, max_age_ns: int, where: str
              ) -> tuple[np.ndarray, dict[int, str]]:
        """Return the poses of ``child`` in its parent at ``stamps_ns`` and the failures.

        Poses of ``child`` in its parent at ``stamps_ns`` ((n, 4, 4) or one (4, 4) for a static edge) and
        the failures (index of the stamp -> message; those rows are NaN).
        """
        if child in self._static:
            return self._static[child], {}
        track = self._track(child)
        parent = self._parent[child]
        known = track.stamps_ns
        at = np.searchsorted(known, stamps_ns, side="right")
        before = np.maximum(at - 1, 0)
        exact = (at > 0) & (known[before] == stamps_ns)
        age_ns = stamps_ns - known[before]
        failed = (at == 0) | (~exact & ((age_ns > max_age_ns) | (at == known.size)))
        failures = {}
        for index in np.flatnonzero(failed):
            stamp_ns = int(stamps_ns[index])
            if at[index] == 0:
                failures[int(index)] = f"{where}: no pose of {child} in {parent} at or before {stamp_ns} ns"
            elif age_ns[index] > max_age_ns:
                failures[int(index)] = (f"{where}: the newest pose of {child} in {parent} is "
                                        f"{int(age_ns[index]) / 1e9:.4g} s older than {stamp_ns} ns "
                                        f"(limit {max_age_ns / 1e9:.4g} s)")
            else:
                failures[int(index)] = f"{where}: no pose of {child} in {parent} after {stamp_ns} ns (no extrapolation)"
        poses = np.full((stamps_ns.size, 4, 4), np.nan)
        poses[exact] = track.poses[before[exact]]
        between = np.flatnonzero(~exact & ~failed)
        if between.size:
            low = before[between]
            fraction = (stamps_ns[between] - known[low]) / (known[low + 1] - known[low])
            # slerp as scipy's Slerp computes it: the first sample turned by a fraction of the arc to the next
            rotations = track.rotations[low] * Rotation.from_rotvec(track.steps[low] * fraction[:, None])
            poses[between] = np.eye(4)
            poses[between, :3, :3] = rotations.as_matrix()
            poses[between, :3, 3] = ((1.0 - fraction)[:, None] * track.poses[low, :3, 3]
                                     + fraction[:, None] * track.poses[low + 1, :3, 3])
        return poses, failures

    def _to_root(self, frame: str, stamps_ns: np.ndarray, max_age_ns: int, where: str,
                 failures: list[Optional[str]]) -> tuple[str, Optional[np.ndarray]]:
        """Return the root of ``frame``'s tree and the poses of ``frame`` in the root.

        Root of ``frame``'s tree and the poses of ``frame`` in the root ((n, 4, 4); None: the identity);
        a stamp's first failing edge, walking up, is written into ``failures`` unless one is there.
        """
        pose = None
        while frame in self._parent:
            edge, failed = self._edge(frame, stamps_ns, max_age_ns, where)
            for index, message in failed.items():
                if failures[index] is None:
                    failures[index] = message
            pose = edge if pose is None else edge @ pose
            frame = self._parent[frame]
        return frame, pose

    def try_lookup_many(self, target: str, source: str, stamps_ns: Sequence[int], max_age_ns: int,
                        where: str = "tf") -> tuple[np.ndarray, list[Optional[str]]]:
        """Return the poses of ``source`` in ``target`` at ``stamps_ns`` and each stamp's failure.

        Poses of ``source`` in ``target`` at each of ``stamps_ns`` ((n, 4, 4), mm; NaN where it failed) and
        for each stamp None or the message :meth:`lookup` raises at that stamp (prefixed ``where``).
        """
        stamps_ns = np.asarray(stamps_ns)
        if stamps_ns.ndim != 1 or not (np.issubdtype(stamps_ns.dtype, np.integer) or stamps_ns.size == 0):
            raise ValueError(f"{where}: stamps must be a sequence of integer nanoseconds")
        with self._lock:
            return self._lookup_many(target, source, stamps_ns.astype(np.int64), max_age_ns, where)

    def _lookup_many(self, target: str, source: str, stamps_ns: np.ndarray, max_age_ns: int, where: str
                     ) -> tuple[np.ndarray, list[Optional[str]]]:
        failures: list[Optional[str]] = [None] * stamps_ns.size
        for frame in (target, source):
            if frame not in self._parent and frame not in self._parent.values():
                message = (f"{where}: frame {frame} is not in the transform tree "
                           f"(frames: {', '.join(sorted(set(self._parent) | set(self._parent.values())))})")
                return np.full((stamps_ns.size, 4, 4), np.nan), [message] * stamps_ns.size
        source_root, source_pose = self._to_root(source, stamps_ns, max_age_ns, where, failures)
        target_root, target_pose = self._to_root(target, stamps_ns, max_age_ns, where, failures)
        if source_root != target_root:
            message = (f"{where}: no transform from {source} to {target} (they hang from {source_root} and "
                       f"{target_root}, which nothing connects)")
            failures = [message if failure is None else failure for failure in failures]
        poses = np.broadcast_to(np.eye(4) if source_pose is None else source_pose, (stamps_ns.size, 4, 4)).copy()
        if target_pose is not None:
            placed = np.array([failure is None for failure in failures], dtype=bool)
            target_pose = np.broadcast_to(target_pose, poses.shape)
            poses[placed] = np.linalg.inv(target_pose[placed]) @ poses[placed]
        poses[[failure is not None for failure in failures]] = np.nan
        return poses, failures

    def lookup_many(self, target: str, source: str, stamps_ns: Sequence[int], max_age_ns: int,
                    where: str = "tf") -> np.ndarray:
        """Return the poses of ``source`` in ``target`` at ``stamps_ns``; ValueError on a failure.

        Poses of ``source`` in ``target`` at each of ``stamps_ns`` ((n, 4, 4), mm); ValueError: the first
        failing stamp's message, as :meth:`lookup` at that stamp raises it.
        """
        poses, failures = self.try_lookup_many(target, source, stamps_ns, max_age_ns, where)
        first = next((failure for failure in failures if failure is not None), None)
        if first is not None:
            raise ValueError(first)
        return poses

    def lookup(self, target: str, source: str, stamp_ns: int, max_age_ns: int, where: str = "tf") -> np.ndarray:
        """Pose of ``source`` in ``target`` (4x4, mm: maps ``source`` coordinates to ``target``) at ``stamp_ns``.

        ``max_age_ns``: the newest sample of a dynamic edge at or before the stamp may be this old, and a
        sample after it must exist. ValueError (prefixed ``where``) naming a missing frame or pose.
        """
        return self.lookup_many(target, source, [stamp_ns], max_age_ns, where)[0]
