"""The TF buffer's vectorised lookup of a sweep's stamps against one lookup per stamp (issue 33 item 3).

The reference below is the per-stamp lookup the buffer had before ``lookup_many`` (bisect on each
edge, scipy's ``Slerp`` between the two samples around the stamp, one chain walk per stamp), kept here
as the oracle: the batched lookup must give the same poses (1e-9 mm, 1e-12 rad) and, for every stamp
that cannot be placed, the very message the per-stamp lookup raised.
"""
from __future__ import annotations

import bisect

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gls_calibration.scan.tf_buffer import TfBuffer

MAX_AGE_NS = 40


class _PerStampBuffer:
    """The buffer's lookup as it was: one stamp at a time (validation left out: the inputs are valid)."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}
        self._samples: dict[str, tuple[list[int], list[np.ndarray]]] = {}

    def set_transform(self, parent, child, stamp_ns, pose, static=False):
        self._parent[child] = parent
        if static:
            self._static[child] = pose.copy()
            return
        stamps, poses = self._samples.setdefault(child, ([], []))
        at = bisect.bisect_right(stamps, int(stamp_ns))
        stamps.insert(at, int(stamp_ns))
        poses.insert(at, pose.copy())

    def _edge(self, child, stamp_ns, max_age_ns, where):
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

    def _to_root(self, frame, stamp_ns, max_age_ns, where):
        pose = np.eye(4)
        while frame in self._parent:
            pose = self._edge(frame, stamp_ns, max_age_ns, where) @ pose
            frame = self._parent[frame]
        return frame, pose

    def lookup(self, target, source, stamp_ns, max_age_ns, where="tf"):
        for frame in (target, source):
            if frame not in self._parent and frame not in self._parent.values():
                raise ValueError(f"{where}: frame {frame} is not in the transform tree "
                                 f"(frames: {', '.join(sorted(set(self._parent) | set(self._parent.values())))})")
        source_root, source_pose = self._to_root(source, stamp_ns, max_age_ns, where)
        target_root, target_pose = self._to_root(target, stamp_ns, max_age_ns, where)
        if source_root != target_root:
            raise ValueError(f"{where}: no transform from {source} to {target} (they hang from {source_root} and "
                             f"{target_root}, which nothing connects)")
        return np.linalg.inv(target_pose) @ source_pose


def _pose(rng: np.random.Generator) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 1.2, 3)).as_matrix()     # large turns between samples
    pose[:3, 3] = rng.uniform(-500.0, 500.0, 3)
    return pose


def _buffers(seed: int):
    """Both buffers fed the same random tree: base -> flange (stamped, with a gap longer than the age
    limit and a repeated stamp) -> sensor (static); base -> gls (static) -> camera (stamped on other
    stamps); world -> table (static, a second tree)."""
    rng = np.random.default_rng(seed)
    flange_ns = np.cumsum(rng.integers(5, 30, 40))
    flange_ns[25:] += 100                                   # a gap: the robot's poses stop for a while
    flange_ns = np.insert(flange_ns, 10, flange_ns[10])      # two samples at one stamp
    camera_ns = np.sort(rng.choice(np.arange(flange_ns[0] - 50, flange_ns[-1] + 50), 30, replace=False))
    transforms = [("flange", "sensor", 0, _pose(rng), True), ("base", "gls", 0, _pose(rng), True),
                  ("world", "table", 0, _pose(rng), True)]
    transforms += [("base", "flange", int(t), _pose(rng), False) for t in flange_ns]
    transforms += [("gls", "camera", int(t), _pose(rng), False) for t in camera_ns]
    order = rng.permutation(len(transforms))               # samples arrive out of order
    batched, reference = TfBuffer(), _PerStampBuffer()
    for index in order:
        for buffer in (batched, reference):
            buffer.set_transform(*transforms[index][:4], static=transforms[index][4])
    stamps = np.concatenate([flange_ns, camera_ns, flange_ns[[0, -1]] + [-1, 1],
                             rng.integers(flange_ns[0] - 60, flange_ns[-1] + 60, 200)])
    return batched, reference, rng.permutation(stamps)


def _reference(reference: _PerStampBuffer, target: str, source: str, stamps: np.ndarray):
    poses, failures = [], []
    for stamp in stamps:
        try:
            poses.append(reference.lookup(target, source, int(stamp), MAX_AGE_NS, "sweep 1"))
            failures.append(None)
        except ValueError as error:
            poses.append(np.full((4, 4), np.nan))
            failures.append(str(error))
    return np.array(poses), failures


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("target, source", [("base", "sensor"), ("camera", "sensor"), ("sensor", "gls"),
                                            ("flange", "flange"), ("base", "table"), ("base", "nowhere")])
def test_a_sweep_is_placed_as_one_lookup_per_stamp_places_it(seed, target, source):
    batched, reference, stamps = _buffers(seed)
    expected, expected_failures = _reference(reference, target, source, stamps)
    poses, failures = batched.try_lookup_many(target, source, stamps, MAX_AGE_NS, "sweep 1")
    assert failures == expected_failures          # byte-identical messages, stamp by stamp
    placed = np.array([failure is None for failure in failures])
    assert poses.shape == (stamps.size, 4, 4) and np.all(np.isnan(poses[~placed]))
    np.testing.assert_allclose(poses[placed, :3, 3], expected[placed, :3, 3], rtol=0.0, atol=1e-9)
    turned = Rotation.from_matrix(expected[placed, :3, :3]).inv() * Rotation.from_matrix(poses[placed, :3, :3])
    assert np.all(turned.magnitude() <= 1e-12)
    np.testing.assert_array_equal(poses[placed, 3], np.tile([0.0, 0.0, 0.0, 1.0], (int(placed.sum()), 1)))
    # the raising form: the first failing stamp's message, or the poses; the single lookup is the same
    if any(failure is not None for failure in failures):
        first = next(failure for failure in failures if failure is not None)
        with pytest.raises(ValueError) as raised:
            batched.lookup_many(target, source, stamps, MAX_AGE_NS, "sweep 1")
        assert str(raised.value) == first
    else:
        np.testing.assert_array_equal(batched.lookup_many(target, source, stamps, MAX_AGE_NS, "sweep 1"), poses)
    for index in range(0, stamps.size, 17):
        if failures[index] is None:
            np.testing.assert_array_equal(batched.lookup(target, source, stamps[index], MAX_AGE_NS, "sweep 1"),
                                          poses[index])
        else:
            with pytest.raises(ValueError) as raised:
                batched.lookup(target, source, stamps[index], MAX_AGE_NS, "sweep 1")
            assert str(raised.value) == failures[index]


def test_every_kind_of_failure_is_among_the_random_cases():
    """The comparison above is worth something only if each failure kind and each success kind occurs."""
    batched, _, stamps = _buffers(0)
    _, failures = batched.try_lookup_many("base", "sensor", stamps, MAX_AGE_NS, "sweep 1")
    kinds = ("at or before", "older than", "after", "not in the transform tree", "which nothing connects")
    seen = {kind for failure in failures if failure for kind in kinds if kind in failure}
    assert seen == {"at or before", "older than", "after"}
    assert sum(failure is None for failure in failures) > 100
    for target, source, kind in (("base", "nowhere", "not in the transform tree"),
                                 ("base", "table", "which nothing connects")):
        _, failures = batched.try_lookup_many(target, source, stamps, MAX_AGE_NS, "sweep 1")
        assert any(kind in failure for failure in failures if failure)


def test_stamps_on_samples_give_the_samples_and_the_cache_follows_new_samples():
    buffer = TfBuffer()
    first = np.eye(4)
    second = np.eye(4)
    second[:3, :3] = Rotation.from_euler("z", 90.0, degrees=True).as_matrix()
    second[:3, 3] = [10.0, 0.0, 0.0]
    buffer.set_transform("base", "flange", 0, first)
    buffer.set_transform("base", "flange", 100, second)
    poses = buffer.lookup_many("base", "flange", [0, 100, 50], max_age_ns=100)
    np.testing.assert_array_equal(poses[:2], [first, second])
    np.testing.assert_allclose(poses[2, :3, 3], [5.0, 0.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="no pose of flange in base after 150 ns"):
        buffer.lookup_many("base", "flange", [50, 150], max_age_ns=100)
    buffer.set_transform("base", "flange", 200, first)         # a sample added after a lookup is used
    np.testing.assert_allclose(buffer.lookup_many("base", "flange", [150], max_age_ns=100)[0, :3, 3], [5.0, 0, 0],
                               atol=1e-12)
    assert buffer.lookup_many("base", "flange", [], max_age_ns=100).shape == (0, 4, 4)
    with pytest.raises(ValueError, match="tf: stamps must be a sequence of integer nanoseconds"):
        buffer.lookup_many("base", "flange", [1.5], max_age_ns=100)
