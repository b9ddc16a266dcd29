"""Record and replay a cell in the rosbag2 format (SQLite3 or MCAP) with standard message types only.

What a bag holds (names are :class:`BagLayout`'s defaults):

- ``/scanner/profile`` (``sensor_msgs/msg/PointCloud2``): one message per profile, height 1, fields
  ``x, y, z, intensity`` float32, in the scanner's optical frame, in metres, stamped; NaN for no return.
- ``/tf`` (``tf2_msgs/msg/TFMessage``): the flange pose the robot reports, robot base -> flange.
- ``/tf_static`` (``tf2_msgs/msg/TFMessage``): flange -> scanner optical frame (hand-eye) and robot
  base -> ``gls`` (the galvo head).
- ``/motion/start`` and ``/motion/end`` (``std_msgs/msg/Header``): the stamps at which each straight
  line of the robot began and ended (``header.stamp``; ``frame_id`` the robot base frame), one pair
  per sweep, in order.

Replay (:func:`read_sweeps`) takes the profiles stamped within each motion's start and end, places
every one through the chain base -> flange -> sensor looked up at its stamp (translation and rotation
interpolated in time; one vectorised lookup for all the sweep's stamps), and returns each sweep as an
organized cloud in the robot base frame in mm.
Every problem of the input is a ``ValueError`` naming it; nothing is guessed.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
import shutil
import threading
import tempfile
import warnings
from typing import Callable, Iterator, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from gls_calibration.scan.sweep import unit_check_distance

MM_PER_M = 1000.0
NS_PER_S = 1_000_000_000
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
HEADER = "std_msgs/msg/Header"
_FLOAT32 = 7                              # sensor_msgs/msg/PointField FLOAT32
_FIELDS = ("x", "y", "z", "intensity")
_PROFILE_DTYPE = np.dtype([(name, "<f4") for name in _FIELDS])
STORAGES = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class BagLayout:
    """Topics and frame names of a recorded cell.

    Parameters
    ----------
    scan_topic : str, default "/scanner/profile"
        The profiles (``PointCloud2``, one per profile, metres).
    tf_topic, tf_static_topic : str, default "/tf", "/tf_static"
        The robot's reported poses and the static frames.
    motion_start_topic, motion_end_topic : str, default "/motion/start", "/motion/end"
        The stamps (``std_msgs/Header``) that open and close each motion.
    base_frame, flange_frame, sensor_frame, gls_frame : str
        Names of the robot base, the flange, the scanner's optical frame and the galvo head
        (defaults "robot_base", "flange", "scanner_optical", "gls").
    """

    scan_topic: str = "/scanner/profile"
    tf_topic: str = "/tf"
    tf_static_topic: str = "/tf_static"
    motion_start_topic: str = "/motion/start"
    motion_end_topic: str = "/motion/end"
    base_frame: str = "robot_base"
    flange_frame: str = "flange"
    sensor_frame: str = "scanner_optical"
    gls_frame: str = "gls"


@dataclass(frozen=True)
class ReplayLimits:
    """What replay accepts before it calls a stream broken.

    Parameters
    ----------
    max_pose_age_s : float, default 0.05
        The newest flange pose at or before a profile may be this old, s (the robot state publisher's
        period plus its latency), and a pose at or after the profile must exist (no extrapolation).
    max_gap_periods : float, default 5.0
        A gap in the profile stream (or between the last profile and the motion's end) longer than
        this many of the sweep's median profile periods means the stream stopped.
    max_range_m : float, default 10.0
        A profile whose median point distance exceeds it, m, is not in metres.
    """

    max_pose_age_s: float = 0.05
    max_gap_periods: float = 5.0
    max_range_m: float = 10.0


STANDSTILL_TRAVEL_MM = 1.0
"""A motion whose first and last profiles' centroids lie closer than this is a stand-still (profiles
taken with the robot standing at the marking pose); a sweep travels the grid's length."""


@dataclass(frozen=True)
class ReplayedSweep:
    """One motion assembled from a bag: organized cloud in the robot base frame (mm).

    Parameters
    ----------
    xyz_mm : numpy.ndarray, shape (H, W, 3)
        Points in the robot base frame, mm, float64; NaN for no return.
    intensity : numpy.ndarray, shape (H, W)
        Intensity of each point, float64.
    stamps_ns : numpy.ndarray, shape (H,)
        The profiles' stamps, ns, int64.
    start_ns, end_ns : int
        Stamps of the motion's start and end, ns.
    """

    xyz_mm: np.ndarray          # (H, W, 3) float64, NaN for no return
    intensity: np.ndarray       # (H, W) float64
    stamps_ns: np.ndarray       # (H,) int64, the profiles' stamps
    start_ns: int
    end_ns: int

    @property
    def travel_mm(self) -> float:
        """Distance between the centroids of the first and last profiles (mm); NaN when either has no point."""
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)     # a profile without a point: NaN, said below
            first, last = (np.nanmean(self.xyz_mm[row].reshape(-1, 3), axis=0) for row in (0, -1))
        return float(np.linalg.norm(last - first))

    @property
    def standstill(self) -> bool:
        """Tell whether the robot stood still (travel below ``STANDSTILL_TRAVEL_MM``).

        ValueError when the travel is unknown.
        """
        travel = self.travel_mm
        if not np.isfinite(travel):
            raise ValueError(f"motion from {self.start_ns} to {self.end_ns} ns: its first or last profile has no "
                             "point, so its travel is unknown")
        return travel < STANDSTILL_TRAVEL_MM


# --------------------------------------------------------------------------------------------- writing

def transform_msg(parent: str, child: str, pose_mm: np.ndarray, stamp_ns: int):
    """``geometry_msgs/msg/TransformStamped`` of a 4x4 pose (child -> parent, mm) in metres."""
    types = _TYPESTORE.types
    quaternion = Rotation.from_matrix(pose_mm[:3, :3]).as_quat()          # x, y, z, w
    translation = pose_mm[:3, 3] / MM_PER_M
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(stamp_ns, parent), child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](*(float(v) for v in translation)),
            rotation=types["geometry_msgs/msg/Quaternion"](*(float(v) for v in quaternion))))


def _header(stamp_ns: int, frame_id: str):
    types = _TYPESTORE.types
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return types[HEADER](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id)


def profile_msg(points_m: np.ndarray, frame_id: str, stamp_ns: int):
    """PointCloud2 of one profile: ``points_m`` (W, 4) x, y, z (m), intensity; stored as float32."""
    types = _TYPESTORE.types
    points = np.empty(points_m.shape[0], dtype=_PROFILE_DTYPE)
    for column, name in enumerate(_FIELDS):
        points[name] = points_m[:, column]
    fields = [types["sensor_msgs/msg/PointField"](name=name, offset=4 * column, datatype=_FLOAT32, count=1)
              for column, name in enumerate(_FIELDS)]
    return types[POINTCLOUD2](header=_header(stamp_ns, frame_id), height=1, width=points.size, fields=fields,
                              is_bigendian=False, point_step=_PROFILE_DTYPE.itemsize,
                              row_step=_PROFILE_DTYPE.itemsize * points.size,
                              data=points.view(np.uint8).copy(), is_dense=bool(np.isfinite(points_m).all()))


class BagRecorder:
    """Writes a cell's streams to a new rosbag2 folder (use as a context manager).

    ``tap(topic, message)``, when given, sees every message as it is written (what a live subscriber
    would receive). The bag is written under a temporary name beside ``path`` and renamed when closed
    without error, so a failed recording leaves nothing at ``path``.

    Parameters
    ----------
    path : str or pathlib.Path
        The bag folder to create; it must not exist, its parent must.
    flange_to_sensor, base_to_gls : numpy.ndarray, shape (4, 4)
        The hand-eye and the head in the robot base (child -> parent, mm), written once on ``/tf_static``.
    layout : BagLayout, optional
        Topics and frame names.
    storage : str, default "sqlite3"
        The rosbag2 storage, one of ``STORAGES``.
    tap : callable, optional
        ``tap(topic: str, message) -> None``, called with every message written.

    Raises
    ------
    ValueError
        If ``storage`` is unknown, ``path`` exists already or its parent folder does not exist.
    """

    def __init__(self, path: str | Path, flange_to_sensor: np.ndarray, base_to_gls: np.ndarray,
                 layout: BagLayout = BagLayout(), storage: str = "sqlite3",
                 tap: Optional[Callable[[str, object], None]] = None) -> None:
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {', '.join(STORAGES)}, got {storage!r}")
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            raise ValueError(f"{self.path}: exists already; a bag is written only into a new folder")
        self.layout = layout
        # written inside a hidden folder beside the target, moved into place when complete
        if not self.path.parent.is_dir():
            raise ValueError(f"{self.path.parent}: no such folder")
        self._scratch = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent))
        self._writer = Writer(self._scratch / self.path.name, version=Writer.VERSION_LATEST,
                              storage_plugin=STORAGES[storage])
        self._static = (flange_to_sensor, base_to_gls)
        self.tap = tap
        self._connections: dict = {}
        self.clock_ns = 0

    def __enter__(self) -> "BagRecorder":
        """Open the scratch bag and its topics; remove the scratch folder if that fails."""
        try:
            self._writer.open()
            for topic, msgtype in ((self.layout.scan_topic, POINTCLOUD2), (self.layout.tf_topic, TFMESSAGE),
                                   (self.layout.tf_static_topic, TFMESSAGE),
                                   (self.layout.motion_start_topic, HEADER), (self.layout.motion_end_topic, HEADER)):
                self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=_TYPESTORE)
        except BaseException:
            shutil.rmtree(self._scratch, ignore_errors=True)
            raise
        return self

    def __exit__(self, kind, value, traceback) -> None:
        """Close the bag and, unless an exception ends the block, move it to ``path``; drop the scratch."""
        try:
            self._writer.close()
            if kind is None:
                (self._scratch / self.path.name).rename(self.path)
        finally:
            shutil.rmtree(self._scratch, ignore_errors=True)

    def _write(self, topic: str, stamp_ns: int, message) -> None:
        msgtype = self._connections[topic].msgtype
        self._writer.write(self._connections[topic], int(stamp_ns), _TYPESTORE.serialize_cdr(message, msgtype))
        if self.tap is not None:
            self.tap(topic, message)

    def write_sweep(self, start_ns: int, end_ns: int, profile_stamps_ns: Sequence[int], profiles_m: np.ndarray,
                    flange_stamps_ns: Sequence[int], base_to_flange_mm: np.ndarray) -> None:
        """One sweep: the motion's start and end, the flange poses (N, 4, 4) and the profiles (H, W, 4)."""
        layout = self.layout
        if not self.clock_ns:    # the fixed frames, once, stamped at the first motion
            flange_to_sensor, base_to_gls = self._static
            self._write(layout.tf_static_topic, start_ns, _TYPESTORE.types[TFMESSAGE](transforms=[
                transform_msg(layout.flange_frame, layout.sensor_frame, flange_to_sensor, start_ns),
                transform_msg(layout.base_frame, layout.gls_frame, base_to_gls, start_ns)]))
        self._write(layout.motion_start_topic, start_ns, _header(start_ns, layout.base_frame))
        self.write_stream(profile_stamps_ns, profiles_m, flange_stamps_ns, base_to_flange_mm)
        self._write(layout.motion_end_topic, end_ns, _header(end_ns, layout.base_frame))
        self.clock_ns = max(self.clock_ns, int(end_ns))

    def write_stream(self, profile_stamps_ns: Sequence[int], profiles_m: np.ndarray, flange_stamps_ns: Sequence[int],
                     base_to_flange_mm: np.ndarray) -> None:
        """Return the profiles and flange poses of a bag in time order.

        Profiles (H, W, 4: x, y, z in m, intensity) and flange poses (N, 4, 4, mm), in time order, poses
        first at equal stamps; outside a motion they are what a scanner streams while the robot is not
        sweeping.
        """
        layout = self.layout
        events = sorted([(int(t), 0, i) for i, t in enumerate(flange_stamps_ns)]
                        + [(int(t), 1, i) for i, t in enumerate(profile_stamps_ns)])
        for stamp, kind, index in events:
            if kind == 0:
                message = _TYPESTORE.types[TFMESSAGE](transforms=[transform_msg(
                    layout.base_frame, layout.flange_frame, base_to_flange_mm[index], stamp)])
                self._write(layout.tf_topic, stamp, message)
            else:
                self._write(layout.scan_topic, stamp, profile_msg(profiles_m[index], layout.sensor_frame, stamp))
        if len(events):
            self.clock_ns = max(self.clock_ns, events[-1][0])


# --------------------------------------------------------------------------------------------- reading

def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _pose_mm(transform) -> np.ndarray:
    q, t = transform.rotation, transform.translation
    return _pose_mm_of((q.x, q.y, q.z, q.w), (t.x, t.y, t.z))


def profile_points(message, limits: ReplayLimits, where: str) -> np.ndarray:
    """(W, 4) float64 x, y, z (m), intensity of one PointCloud2 profile; ValueError naming a problem."""
    return np.asarray(_profile_array(message, limits, where), dtype=np.float64)


def _profile_array(message, limits: ReplayLimits, where: str) -> np.ndarray:
    """Return :func:`profile_points`' points, float32 when they can stay a view of the message's read-only bytes.

    A float64 copy of every profile on arrival (new memory each: its page faults were most of the cost) is
    left to the placement, which converts one row at a time into the same float64 values.
    """
    offsets = _field_offsets(message.fields, where)
    if message.is_bigendian:
        raise ValueError(f"{where}: big-endian clouds are not supported")
    count = int(message.width) * int(message.height)
    step = int(message.point_step)
    data = np.asarray(message.data, dtype=np.uint8)
    if step < 16 or data.size < count * step:
        raise ValueError(f"{where}: the cloud's data ({data.size} bytes) is shorter than its {count} points")
    if step % 4 == 0 and all(offset % 4 == 0 and 0 <= offset <= step - 4 for offset in offsets):
        # the points as rows of float32 words: a view of read-only bytes (those a raw subscription hands over)
        # is kept as it is; otherwise (bytes the sender may reuse, columns reordered) one float64 copy
        words = data[:count * step].view("<f4").reshape(count, step // 4)
        columns = [offset // 4 for offset in offsets]
        array = words[:, :4] if columns == [0, 1, 2, 3] else words[:, columns]
        if array.flags.writeable:
            array = array.astype(np.float64)
    else:
        dtype = np.dtype({"names": list(_FIELDS), "formats": ["<f4"] * 4, "offsets": offsets, "itemsize": step})
        points = data[:count * step].view(dtype)
        array = np.empty((count, len(_FIELDS)))
        for column, name in enumerate(_FIELDS):
            array[:, column] = points[name]
    median_m = unit_check_distance(array[:, :3], 0.0, limits.max_range_m)
    if median_m > limits.max_range_m:      # False for NaN: no finite point says nothing of the unit
        raise ValueError(f"{where}: median point distance {median_m:.4g} m exceeds "
                         f"{limits.max_range_m:g} m: the cloud is not in metres (millimetres?)")
    return array


# The fields of the last cloud whose fields passed and their x, y, z, intensity offsets: ros/cdr hands a
# stream's profiles one shared tuple of immutable fields, so each profile after the first skips the checks
# (they were ~half of a profile's handling on arrival). Replaced whole (one assignment): thread-safe.
_checked_fields: tuple = ((), [])


def _field_offsets(fields, where: str) -> list[int]:
    """Return the byte offsets of x, y, z and intensity in a cloud's points; ValueError naming a problem.

    Parameters
    ----------
    fields : sequence of PointField
        The cloud's fields.
    where : str
        Names the cloud in the error message.

    Returns
    -------
    list of int
        The offsets of ``_FIELDS``, each a single float32.

    Raises
    ------
    ValueError
        When a field is missing or not a single float32.
    """
    global _checked_fields
    last_fields, last_offsets = _checked_fields
    if fields is last_fields:
        return last_offsets
    by_name = {field.name: field for field in fields}
    missing = [name for name in _FIELDS if name not in by_name]
    if missing:
        raise ValueError(f"{where}: the cloud has no field(s) {', '.join(missing)}")
    wrong = [name for name in _FIELDS if by_name[name].datatype != _FLOAT32 or by_name[name].count != 1]
    if wrong:
        raise ValueError(f"{where}: field(s) {', '.join(wrong)} are not single float32 values")
    offsets = [int(by_name[name].offset) for name in _FIELDS]
    # only an immutable tuple of immutable fields (ros/cdr's) can be told by identity to be unchanged
    if isinstance(fields, tuple) and all(isinstance(field, tuple) for field in fields):
        _checked_fields = (fields, offsets)
    return offsets


def _open(path: Path) -> Reader:
    if not path.exists():
        raise ValueError(f"{path}: no such bag")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as error:       # rosbags' reader errors and the storage libraries' own
        raise ValueError(f"{path}: unreadable bag ({type(error).__name__}: {error})") from None
    return reader


def _messages(reader: Reader, path: Path, topics: Sequence[str]) -> Iterator[tuple[str, int, object]]:
    connections = [c for c in reader.connections if c.topic in topics]
    try:
        for connection, _, raw in reader.messages(connections=connections):
            yield connection.topic, connection, _TYPESTORE.deserialize_cdr(raw, connection.msgtype)
    except Exception as error:
        raise ValueError(f"{path}: unreadable bag ({type(error).__name__}: {error})") from None


def read_sweeps(path: str | Path, layout: BagLayout = BagLayout(), limits: ReplayLimits = ReplayLimits()
                ) -> list[ReplayedSweep]:
    """Assemble every sweep of a bag (see :func:`read_recording`; no galvo frame needed).

    Parameters
    ----------
    path : str or pathlib.Path
        The rosbag2 folder.
    layout : BagLayout, optional
        Topics and frame names of the bag.
    limits : ReplayLimits, optional
        What replay accepts before it calls a stream broken.

    Returns
    -------
    list of ReplayedSweep
        Every motion of the bag, in order, in the robot base frame (mm).

    Raises
    ------
    ValueError
        As :func:`read_recording`, naming the problem.
    """
    return _read_path(Path(path), layout, limits)[0]


def read_recording(path: str | Path, layout: BagLayout = BagLayout(), limits: ReplayLimits = ReplayLimits()
                   ) -> tuple[list[ReplayedSweep], np.ndarray]:
    """Assemble every sweep of a bag in ``layout.base_frame``; return them and the gls pose.

    See the module docstring for how a sweep is assembled and placed.

    Parameters
    ----------
    path : str or pathlib.Path
        The rosbag2 folder.
    layout : BagLayout, optional
        Topics and frame names of the bag.
    limits : ReplayLimits, optional
        What replay accepts before it calls a stream broken.

    Returns
    -------
    sweeps : list of ReplayedSweep
        Every motion of the bag, in order, in the robot base frame (mm).
    base_to_gls : numpy.ndarray, shape (4, 4)
        The pose of ``layout.gls_frame`` in ``layout.base_frame`` (mm) at the first motion's start.

    Raises
    ------
    ValueError
        Naming the problem: an unreadable bag, a missing topic or frame, a motion without its end, a
        profile without a recent enough pose, a stream that stops mid-sweep, a cloud not in metres.
    """
    sweeps, buffer = _read_path(Path(path), layout, limits)
    return sweeps, _pose_at(buffer, layout.base_frame, layout.gls_frame, sweeps[0].start_ns, limits, str(path))


def _read_path(path: Path, layout: BagLayout, limits: ReplayLimits):
    reader = _open(path)
    try:
        return _read(reader, path, layout, limits)
    finally:
        reader.close()


def _read(reader: Reader, path: Path, layout: BagLayout, limits: ReplayLimits):
    topics = {c.topic: c.msgtype for c in reader.connections}
    assembler = StreamAssembler(layout, limits, str(path))
    for topic, msgtype in assembler.topics().items():
        if topic not in topics:
            raise ValueError(f"{path}: topic {topic} is not in the bag (topics: {', '.join(sorted(topics)) or 'none'})")
        if topics[topic] != msgtype:
            raise ValueError(f"{path}: topic {topic} carries {topics[topic]}, not {msgtype}")
    for topic, _, message in _messages(reader, path, list(assembler.topics())):
        assembler.add(topic, message)
    return assembler.sweeps(), assembler.buffer


class StreamAssembler:
    """Collects a cell's streams (profiles, TF, motion stamps) and assemble sweeps from them.

    Fed message by message, from a bag or live as a subscriber sees them. The same arithmetic
    serves both, so a live run and its replay agree exactly.

    Parameters
    ----------
    layout : BagLayout, optional
        Topics and frame names of the streams.
    limits : ReplayLimits, optional
        What the assembly accepts before it calls a stream broken.
    source : str, default "stream"
        Names the stream in error messages.
    """

    def __init__(self, layout: BagLayout = BagLayout(), limits: ReplayLimits = ReplayLimits(),
                 source: str = "stream") -> None:
        from gls_calibration.scan.tf_buffer import TfBuffer   # the package's buffer (time interpolation, chains)

        self.layout = layout
        self.limits = limits
        self.source = source
        self._buffer = TfBuffer()
        self._pending: list[tuple] = []     # dynamic transforms not yet in the buffer (see flush)
        self._pending_lock = threading.Lock()
        self.starts: list[int] = []
        self.ends: list[int] = []
        self.profiles: list[tuple[int, np.ndarray]] = []

    def topics(self) -> dict[str, str]:
        """Return the topics it reads and their message types."""
        layout = self.layout
        return {layout.scan_topic: POINTCLOUD2, layout.tf_topic: TFMESSAGE, layout.tf_static_topic: TFMESSAGE,
                layout.motion_start_topic: HEADER, layout.motion_end_topic: HEADER}

    @property
    def buffer(self):
        """Return the TF buffer of everything added so far (:class:`~gls_calibration.scan.tf_buffer.TfBuffer`).

        Reading it first adds the transforms still pending (:meth:`flush`).
        """
        self.flush()
        return self._buffer

    def flush(self) -> None:
        """Add the pending dynamic transforms to the buffer, in bulk; ValueError naming the first bad one.

        ``/tf`` transforms are kept as numbers when added and go into the buffer here, before any
        lookup: each run of one edge with one vectorised quaternion conversion and one bulk insertion
        (``TfBuffer.set_transforms``), the same poses, order and checks as one transform at a time. A
        run holding a transform the bulk path would not take as it is (not finite, a zero quaternion)
        is added one transform at a time, so its error is the one :meth:`add` used to raise.
        """
        with self._pending_lock:
            pending, self._pending = self._pending, []
        begin = 0
        while begin < len(pending):
            parent, child = pending[begin][:2]
            end = begin + 1
            while end < len(pending) and pending[end][0] == parent and pending[end][1] == child:
                end += 1
            try:
                _add_transform_run(self._buffer, pending[begin:end])
            except ValueError:
                with self._pending_lock:       # what follows the bad transform stays pending, as add() left it
                    self._pending[:0] = pending[end:]
                raise
            begin = end

    def add(self, topic: str, message) -> None:
        """Take one message of one of :meth:`topics` (others are ignored)."""
        layout = self.layout
        if topic == layout.tf_topic:
            rows = []
            for transform in message.transforms:
                translation, rotation = transform.transform.translation, transform.transform.rotation
                rows.append((transform.header.frame_id, transform.child_frame_id, _stamp_ns(transform.header),
                             rotation.x, rotation.y, rotation.z, rotation.w, translation.x, translation.y,
                             translation.z))
            with self._pending_lock:
                self._pending.extend(rows)
        elif topic == layout.tf_static_topic:
            self.flush()      # in the order they came
            for transform in message.transforms:
                _add_transform(self._buffer, transform, static=True)
        elif topic == layout.motion_start_topic:
            self.starts.append(_stamp_ns(message))
        elif topic == layout.motion_end_topic:
            self.ends.append(_stamp_ns(message))
        elif topic == layout.scan_topic:
            if message.header.frame_id != layout.sensor_frame:
                raise ValueError(f"{self.source}: a profile on {topic} is in frame {message.header.frame_id!r}, "
                                 f"not {layout.sensor_frame!r}")
            stamp = _stamp_ns(message.header)
            self.profiles.append((stamp, _profile_array(message, self.limits,
                                                        f"{self.source}: profile at {stamp} ns")))

    def sweeps(self) -> list[ReplayedSweep]:
        """Every complete motion's sweep, in order; ValueError naming the first problem."""
        windows = _windows(self.source, self.starts, self.ends)
        stamps = np.array([stamp for stamp, _ in self.profiles], dtype=np.int64)
        return [self._sweep(number, start, end, stamps) for number, (start, end) in enumerate(windows, 1)]

    def take_last_sweep(self) -> ReplayedSweep:
        """Return the latest motion's sweep; the profiles up to its end are dropped afterwards (live use)."""
        return self.take_last_placement().sweep()

    def take_last_placement(self) -> "SweepPlacement":
        """Return the latest motion's profiles with their poses, not yet placed; then drop the profiles up to its end.

        What :meth:`take_last_sweep` places (its ``sweep()`` is that sweep): for a caller that writes the
        placed points elsewhere row by row (the live answer's message) without the sweep's arrays.

        Returns
        -------
        SweepPlacement
            The motion's profiles, stamps and sensor poses in the base frame.

        Raises
        ------
        ValueError
            Naming the problem: no complete motion, too few profiles, a stream that stops, profiles of
            different widths, a profile without a pose.
        """
        number = len(self.starts)
        if number == 0 or len(self.ends) != number:
            raise ValueError(f"{self.source}: no complete motion to assemble")
        start, end = self.starts[-1], self.ends[-1]
        stamps = np.array([stamp for stamp, _ in self.profiles], dtype=np.int64)
        placement = self._placement(number, start, end, stamps)
        self.profiles = [item for item in self.profiles if item[0] > end]
        return placement

    def _sweep(self, number: int, start: int, end: int, stamps: np.ndarray) -> ReplayedSweep:
        return self._placement(number, start, end, stamps).sweep()

    def _placement(self, number: int, start: int, end: int, stamps: np.ndarray) -> "SweepPlacement":
        where = f"{self.source}: sweep {number} ({start} to {end} ns)"
        inside = np.flatnonzero((stamps >= start) & (stamps <= end))
        if inside.size < 2:
            raise ValueError(f"{where}: {inside.size} profile(s) within the motion")
        inside = inside[np.argsort(stamps[inside], kind="stable")]
        _check_stream(where, stamps[inside], end, self.limits)
        widths = {self.profiles[i][1].shape[0] for i in inside}
        if len(widths) != 1:
            raise ValueError(f"{where}: profiles of different widths {sorted(widths)}")
        poses = self.buffer.lookup_many(self.layout.base_frame, self.layout.sensor_frame, stamps[inside],
                                        max_age_ns=max_pose_age_ns(self.limits), where=where)
        # metres to mm folded into the rotation (transposed: the profile's rows multiply it)
        to_base_mm = np.swapaxes(poses[:, :3, :3], 1, 2) * MM_PER_M
        return SweepPlacement(tuple(self.profiles[index][1] for index in inside), stamps[inside], to_base_mm,
                              poses[:, :3, 3], start, end)


@dataclass(frozen=True)
class SweepPlacement:
    """One motion's profiles and the sensor's poses at their stamps: a sweep before its points are placed.

    Placing is done row by row (:meth:`place_row`), each profile straight from its own array, the metres
    to mm folded into the rotation (a stacked copy of the profiles and one batched product cost four
    times as much); :meth:`sweep` places every row into a :class:`ReplayedSweep`, and a caller that
    writes the points elsewhere (the live answer's message) places each row into a small buffer
    instead of the sweep's arrays, with the same arithmetic.

    Parameters
    ----------
    profiles_m : tuple of numpy.ndarray, each shape (W, 4)
        The profiles in time order: x, y, z (m) in the sensor frame, intensity; float64, or float32 (a
        view of a message's bytes) that placing turns into the same float64 values first.
    stamps_ns : numpy.ndarray, shape (H,)
        Their stamps, ns, int64.
    to_base_mm : numpy.ndarray, shape (H, 3, 3)
        Each stamp's rotation of the sensor frame into the base frame, transposed and times 1000: a
        point's row in metres times it is the point in mm, rotated.
    origins_mm : numpy.ndarray, shape (H, 3)
        The sensor's origin in the base frame at each stamp, mm.
    start_ns, end_ns : int
        Stamps of the motion's start and end, ns.
    """

    profiles_m: tuple
    stamps_ns: np.ndarray
    to_base_mm: np.ndarray
    origins_mm: np.ndarray
    start_ns: int
    end_ns: int
    _points_m: np.ndarray = dataclasses.field(init=False, repr=False, compare=False)   # a float32 row as float64
    _block_m: np.ndarray = dataclasses.field(init=False, repr=False, compare=False)    # rows of place_rows

    def __post_init__(self) -> None:
        """Make the row buffers of float32 profiles (one placement is used by one thread)."""
        object.__setattr__(self, "_points_m", np.empty((self.profiles_m[0].shape[0] if self.profiles_m else 0, 4)))
        object.__setattr__(self, "_block_m", np.empty((0,) + self._points_m.shape))

    @property
    def shape(self) -> tuple[int, int]:
        """Return the sweep's rows and points per row, (H, W)."""
        return len(self.profiles_m), self.profiles_m[0].shape[0]

    def place_row(self, row: int, out: np.ndarray) -> np.ndarray:
        """Place profile ``row`` in the base frame into ``out`` and return its intensity.

        Parameters
        ----------
        row : int
            The profile's index in the sweep.
        out : numpy.ndarray, shape (W, 3)
            float64, receives its points in the base frame, mm.

        Returns
        -------
        numpy.ndarray, shape (W,)
            The profile's intensity, float64 (a view, valid until the next call).
        """
        points_m = self.profiles_m[row]
        if points_m.dtype != np.float64:      # the float64 array the profile's decoding made before
            np.copyto(self._points_m, points_m)
            points_m = self._points_m
        np.matmul(points_m[:, :3], self.to_base_mm[row], out=out)
        for axis, origin in enumerate(self.origins_mm[row]):    # column by column: a (W, 3) += (3,) is 3x slower
            column = out[:, axis]
            column += origin
        return points_m[:, 3]

    def place_rows(self, first: int, out: np.ndarray, intensity_out: np.ndarray) -> None:
        """Place the profiles ``first`` to ``first + len(out) - 1`` in the base frame, as :meth:`place_row` does.

        A block of rows in a few calls instead of a dozen per row (the per-call overhead was most of the
        cost of a live answer's rows): the profiles are cast into one float64 block, and the batched
        product multiplies each row's (W, 3) points by its own rotation, the same matrix product per
        row as :meth:`place_row`, so the values are the same.

        Parameters
        ----------
        first : int
            Index of the block's first profile in the sweep.
        out : numpy.ndarray, shape (B, W, 3)
            float64, receives the block's points in the base frame, mm.
        intensity_out : numpy.ndarray, shape (B, W)
            Receives the block's intensities (cast to its dtype).
        """
        count = out.shape[0]
        block_m = self._block_buffer(count)
        # each profile cast to float64 into its own row of the block (the values place_row casts to)
        np.stack(self.profiles_m[first:first + count], out=block_m)
        np.matmul(block_m[:, :, :3], self.to_base_mm[first:first + count], out=out)
        for axis in range(3):
            column = out[:, :, axis]
            column += self.origins_mm[first:first + count, axis, None]
        intensity_out[...] = block_m[:, :, 3]

    def _block_buffer(self, count: int) -> np.ndarray:
        """Return a float64 (count, W, 4) buffer for :meth:`place_rows` (kept between calls)."""
        if self._block_m.shape[0] < count:
            object.__setattr__(self, "_block_m", np.empty((count,) + self._points_m.shape))
        return self._block_m[:count]

    def sweep(self) -> ReplayedSweep:
        """Return the sweep placed: every row in the base frame (mm).

        Returns
        -------
        ReplayedSweep
            The organized cloud, its intensity and stamps.
        """
        xyz = np.empty(self.shape + (3,))
        intensity = np.empty(xyz.shape[:2])
        for row in range(xyz.shape[0]):
            intensity[row] = self.place_row(row, xyz[row])
        return ReplayedSweep(xyz, intensity, self.stamps_ns, self.start_ns, self.end_ns)


def _windows(path: str, starts: list[int], ends: list[int]) -> list[tuple[int, int]]:
    if not starts:
        raise ValueError(f"{path}: no motion in the bag (no message on the motion start topic)")
    starts, ends = sorted(starts), sorted(ends)
    windows = []
    for number, start in enumerate(starts):
        following = [end for end in ends if end >= start]
        end = following[0] if following else None
        later_start = starts[number + 1] if number + 1 < len(starts) else None
        if end is None or (later_start is not None and end > later_start):
            raise ValueError(f"{path}: the motion that started at {start} ns has no end "
                             "(a recording cut mid-sweep?)")
        windows.append((start, end))
    if len(ends) != len(starts):
        raise ValueError(f"{path}: {len(starts)} motion start(s) but {len(ends)} end(s)")
    return windows


def _check_stream(where: str, stamps_ns: np.ndarray, end_ns: int, limits: ReplayLimits) -> None:
    gaps = np.diff(stamps_ns)
    period = float(np.median(gaps))
    if period <= 0:
        raise ValueError(f"{where}: profiles share stamps")
    allowed = limits.max_gap_periods * period
    longest = int(np.argmax(gaps))
    if gaps[longest] > allowed:
        raise ValueError(f"{where}: the profile stream stops for {gaps[longest] / NS_PER_S:.4g} s after "
                         f"profile {longest + 1} (more than {limits.max_gap_periods:g} profile periods)")
    if end_ns - stamps_ns[-1] > allowed:
        raise ValueError(f"{where}: the profile stream stops {(end_ns - stamps_ns[-1]) / NS_PER_S:.4g} s "
                         "before the motion ends")


def _add_transform_run(buffer, rows: list[tuple]) -> None:
    """Add ``rows`` (parent, child, stamp ns, quaternion x, y, z, w, translation m) of one edge to ``buffer``."""
    parent, child = rows[0][:2]
    numbers = np.array([row[3:] for row in rows], dtype=float)
    quaternions, translations = numbers[:, :4], numbers[:, 4:]
    if not (np.isfinite(numbers).all() and (np.einsum("ij,ij->i", quaternions, quaternions) > 0.0).all()):
        for row in rows:   # one at a time: the error is raised at the bad transform, with its own message
            buffer.set_transform(parent, child, row[2], _pose_mm_of(row[3:7], row[7:]))
        return
    poses = np.zeros((len(rows), 4, 4))
    poses[:, 3, 3] = 1.0
    poses[:, :3, :3] = Rotation.from_quat(quaternions).as_matrix()
    poses[:, :3, 3] = translations * MM_PER_M
    buffer.set_transforms(parent, child, np.array([row[2] for row in rows], dtype=np.int64), poses)


def _pose_mm_of(quaternion, translation_m) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(list(quaternion)).as_matrix()
    pose[:3, 3] = np.array(translation_m) * MM_PER_M
    return pose


def _add_transform(buffer, transform, static: bool) -> None:
    buffer.set_transform(transform.header.frame_id, transform.child_frame_id, _stamp_ns(transform.header),
                         _pose_mm(transform.transform), static=static)


def max_pose_age_ns(limits: ReplayLimits) -> int:
    """Return ``limits.max_pose_age_s`` in integer ns, as the TF buffer takes it.

    Parameters
    ----------
    limits : ReplayLimits
        The replay limits.

    Returns
    -------
    int
        The largest pose age, ns (rounded).
    """
    return int(round(limits.max_pose_age_s * NS_PER_S))


def _pose_at(buffer, target: str, source: str, stamp_ns: int, limits: ReplayLimits, where: str) -> np.ndarray:
    """Pose of ``source`` in ``target`` (4x4, mm) at ``stamp_ns``; ValueError naming a missing frame or pose."""
    return buffer.lookup(target, source, stamp_ns, max_age_ns=max_pose_age_ns(limits), where=where)
