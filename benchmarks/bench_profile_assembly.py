"""Placing laser-line profiles in the robot base frame: CPU per profile on both acquisition paths.

Issue 33 asks for at most 0.1 ms of CPU to place a profile. Measured here, in one run:

- the package's own sweep contract (``scan.sweep.SweepCollector``): checking and keeping each
  profile as it arrives (``add``), then placing the sweep by the reported poses (``assemble``);
- the streaming path (``scan.bag_io.StreamAssembler``, the default cell and bag replay): each
  PointCloud2 profile decoded, the TF messages (250 Hz beside 150 profiles/s) added, the sensor
  poses at the sweep's stamps looked up at once, the sweep placed; and three of its phases alone:
  the profile decoding (with its metres check), the TF messages added (kept as numbers: they go into
  the TF buffer in bulk at the first lookup, so that work counts in the next phase), the lookup and
  placement of a fed sweep. And the live node's own steps (``stream_acquisition``): the profiles
  read from their serialised bytes (``ros/cdr``), decoded and kept, and a fed sweep's answer: the TF
  lookup, the placement and the ``PointCloud2`` it answers with.

Run: .venv/bin/python benchmarks/bench_profile_assembly.py [--profiles 2000] [--points 2000]
Prints microseconds of CPU (process time) per profile, medians of 3 repeats.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from builtin_interfaces.msg import Time
from rclpy.serialization import serialize_message

from gls_calibration.ros import cdr
from gls_calibration.ros.conversions import array_to_pointcloud2
from gls_calibration.scan.bag_io import BagLayout, ReplayLimits, StreamAssembler, profile_points
from gls_calibration.scan.sweep import XYZI_FIELDS, PoseTrack, SweepCollector, SweepMotion

NS_PER_S = 1_000_000_000


def profiles(count: int, points: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.linspace(-60.0, 60.0, points)
    out = []
    for _ in range(count):
        profile = np.empty(points, dtype=[(name, np.float32) for name in XYZI_FIELDS])
        profile["x"], profile["y"] = x, 0.0
        profile["z"] = 300.0 + rng.normal(0.0, 0.01, points)
        profile["intensity"] = rng.uniform(0.2, 1.0, points)
        out.append(profile)
    return out


def cpu_s(function) -> tuple[float, object]:
    began = time.process_time()
    result = function()
    return time.process_time() - began, result


def sweep_contract(data: list[np.ndarray], speed_mm_s: float = 15.0, step_mm: float = 0.1):
    """(add every profile, assemble the sweep): the two phases of the package's own contract."""
    stamps = np.arange(len(data)) * step_mm / speed_mm_s
    poses = PoseTrack(len(data) + 1)
    for stamp in stamps:
        poses.add(float(stamp), [0.0, stamp * speed_mm_s, 0.0], Rotation.from_euler("z", 1e-4 * stamp).as_quat())
    collector = SweepCollector(len(data) + 1, data[0].size)

    def add_all():
        for stamp, profile in zip(stamps, data):
            collector.add(float(stamp), profile)

    def assemble():
        return collector.assemble(SweepMotion(direction=(0.0, 1.0, 0.0), speed_mm_s=speed_mm_s), poses=poses)[0]
    return add_all, assemble


def cloud_message(profile: np.ndarray, stamp_ns: int, frame: str):
    data = np.empty(profile.size, dtype=[(name, "<f4") for name in XYZI_FIELDS])
    for name in XYZI_FIELDS:
        data[name] = profile[name] / (1000.0 if name in "xyz" else 1.0)
    fields = [SimpleNamespace(name=name, offset=4 * i, datatype=7, count=1) for i, name in enumerate(XYZI_FIELDS)]
    return SimpleNamespace(header=SimpleNamespace(frame_id=frame, stamp=stamp(stamp_ns)), fields=fields,
                           is_bigendian=False, width=profile.size, height=1, point_step=16,
                           data=np.frombuffer(data.tobytes(), dtype=np.uint8))


def stamp(stamp_ns: int):
    return SimpleNamespace(sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S)


def transform(parent: str, child: str, stamp_ns: int, xyz_m, quaternion):
    return SimpleNamespace(header=SimpleNamespace(frame_id=parent, stamp=stamp(stamp_ns)), child_frame_id=child,
                           transform=SimpleNamespace(
                               translation=SimpleNamespace(x=xyz_m[0], y=xyz_m[1], z=xyz_m[2]),
                               rotation=SimpleNamespace(x=quaternion[0], y=quaternion[1], z=quaternion[2],
                                                        w=quaternion[3])))


def streaming(data: list[np.ndarray], profile_rate_hz: float = 150.0, tf_rate_hz: float = 250.0):
    layout = BagLayout()
    period_ns = int(NS_PER_S / profile_rate_hz)
    start, end = period_ns, period_ns * (len(data) + 1)
    tf_stamps = np.arange(0, end + 2 * period_ns, int(NS_PER_S / tf_rate_hz))
    messages = [(layout.tf_static_topic, SimpleNamespace(transforms=[
        transform(layout.flange_frame, layout.sensor_frame, 0, (0.0, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0))]))]
    messages += [(layout.tf_topic, SimpleNamespace(transforms=[
        transform(layout.base_frame, layout.flange_frame, int(t), (0.5, 1e-9 * t * 0.015, 0.4),
                  (0.0, 0.0, 0.0, 1.0))])) for t in tf_stamps]
    messages.append((layout.motion_start_topic, SimpleNamespace(stamp=stamp(start))))
    messages += [(layout.scan_topic, cloud_message(profile, start + row * period_ns + period_ns // 2,
                                                   layout.sensor_frame)) for row, profile in enumerate(data)]
    messages.append((layout.motion_end_topic, SimpleNamespace(stamp=stamp(end))))

    def feed(topics=None) -> StreamAssembler:
        """A new assembler given every message (or those of ``topics``)."""
        assembler = StreamAssembler(layout)
        for topic, message in messages:
            if topics is None or topic in topics:
                assembler.add(topic, message)
        return assembler
    return feed


def profile_m(profile: np.ndarray) -> np.ndarray:
    """The profile as a driver sends it: float32 x, y, z in metres, intensity."""
    out = profile.copy()
    for name in "xyz":
        out[name] = profile[name] / 1000.0
    return out


def live_profiles(raws: list[bytes]) -> StreamAssembler:
    """Each serialised profile read (``ros/cdr``) and added to an assembler, which keeps it (as the node does)."""
    assembler = StreamAssembler(BagLayout())
    for raw in raws:
        assembler.add(assembler.layout.scan_topic, cdr.read_pointcloud2(raw))
    return assembler


def live_answer(assembler: StreamAssembler):
    """The node's answer of a fed sweep: placed a block of rows at a time into the message (before: the sweep first)."""
    if hasattr(assembler, "take_last_placement"):
        from gls_calibration.ros.pointcloud import xyzi_blocks_to_msg

        placement = assembler.take_last_placement()
        return xyzi_blocks_to_msg(*placement.shape, placement.place_rows, "robot_base", Time())
    from gls_calibration.ros.pointcloud import xyzi_cloud_to_msg

    sweep = assembler.take_last_sweep()
    return xyzi_cloud_to_msg(sweep.xyz_mm, sweep.intensity, "robot_base", Time())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profiles", type=int, default=2000)
    parser.add_argument("--points", type=int, default=2000)
    args = parser.parse_args()
    data = profiles(args.profiles, args.points)
    messages = [cloud_message(profile, 0, "scanner_optical") for profile in data]
    feed = streaming(data)
    tf_topics = (BagLayout().tf_topic, BagLayout().tf_static_topic)
    times: dict[str, list[float]] = {}
    for _ in range(3):
        add_all, assemble = sweep_contract(data)
        fed = feed()
        for label, function in (("sweep contract: add (check, keep)", add_all),
                                ("sweep contract: assemble (place by pose)", assemble),
                                ("streaming: decode, TF lookup, place", lambda: feed().take_last_sweep()),
                                ("streaming: decode only", lambda: [
                                    profile_points(message, ReplayLimits(), "") for message in messages]),
                                ("streaming: TF messages into the buffer only", lambda: feed(tf_topics)),
                                ("streaming: TF lookup and place only", fed.take_last_sweep)):
            times.setdefault(label, []).append(cpu_s(function)[0])
    # the live node's own steps (stream_acquisition): the profiles read from their CDR bytes, and the answer
    raws = [serialize_message(array_to_pointcloud2(profile_m(profile), "scanner_optical", Time(sec=1)))
            for profile in data]
    for _ in range(3):
        fed = feed()
        for label, function in (("live: CDR read, decode, keep (assembler)", lambda: live_profiles(raws)),
                                ("live: TF lookup, place, answer PointCloud2", lambda: live_answer(fed))):
            times.setdefault(label, []).append(cpu_s(function)[0])
    print(f"{args.profiles} profiles of {args.points} points; CPU per profile (median of 3), target 100 us:")
    for label, values in times.items():
        print(f"  {label:47s} {1e6 * statistics.median(values) / args.profiles:8.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
