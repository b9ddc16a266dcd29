"""CPU of the stream_acquisition node per received message, by message kind, during and between sweeps.

A publisher and ``StreamAcquisitionNode`` in one process over the ROS transport (the node spun as
``gls-sim-cell`` spins it: its own single-threaded executor on its own thread). Sent: profiles
(``sensor_msgs/PointCloud2``, 2 000 points, float32 x, y, z, intensity in metres) and flange poses
(``tf2_msgs/TFMessage``, one transform each), the kinds a real scanner and robot stream, each kind
alone, first into a running acquisition (a session as ``scan/acquire`` opens it), then between
sweeps (no session). Measured: the node thread's CPU from the first message sent until every
message was taken, per message; then the sweep's assembly at the end (``_sweep``, this thread's
CPU) per profile; and, in this thread, the parts of a message's handling without the executor:
rclpy's deserialisation into a message object and ``StreamAssembler.add``.

The script runs whichever tree is on ``PYTHONPATH``; compare trees by running it alternately.

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_stream_acquisition.py [--profiles 2000] [--points 2000]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from gls_calibration.common.time_budget import thread_cpu_s
from gls_calibration.nodes.stream_acquisition import Session, StreamAcquisitionNode
from gls_calibration.ros import conversions
from gls_calibration.ros.runtime import NodeThreads
from gls_calibration.ros.stream_topics import LAYOUT, static_qos, stream_qos, time_msg, transform_msg
from gls_calibration.scan.bag_io import StreamAssembler

try:      # the node's answer as it builds it (the tree before issue 33's stream work: two conversions)
    from gls_calibration.ros.pointcloud import xyzi_cloud_to_msg as answer_msg
except ImportError:
    def answer_msg(xyz_mm, intensity, frame_id, stamp):
        return conversions.cloud_to_msg(conversions.xyzi_array(xyz_mm, intensity), frame_id, stamp)

NS_PER_S = 1_000_000_000
PROFILE_RATE_HZ = 150.0
TF_RATE_HZ = 250.0
BATCH = 50          # messages sent before waiting for the node to catch up (as the simulated drivers)


def profile_message(points: int, stamp_ns: int, frame: str, rng: np.random.Generator) -> PointCloud2:
    xyz = np.column_stack([np.linspace(-0.06, 0.06, points), np.zeros(points),
                           0.3 + rng.normal(0.0, 1e-5, points)])
    return conversions.array_to_pointcloud2(conversions.xyzi_array(xyz, rng.uniform(0.2, 1.0, points)), frame,
                                            time_msg(stamp_ns))


def flange_message(node: StreamAcquisitionNode, stamp_ns: int) -> TFMessage:
    pose = np.eye(4)
    pose[:3, 3] = (500.0, 15.0 * stamp_ns / NS_PER_S, 400.0)
    return TFMessage(transforms=[transform_msg(node.frames.base, node.frames.flange, pose, stamp_ns)])


def wait_quiet(thread, quiet_s: float = 0.3, limit_s: float = 60.0) -> None:
    """Wait until ``thread`` used (almost) no CPU for ``quiet_s``."""
    last, began = thread_cpu_s(thread), time.monotonic()
    while time.monotonic() - began < limit_s:
        time.sleep(quiet_s)
        now = thread_cpu_s(thread)
        if now - last < 0.002:
            return
        last = now


def send(publisher, messages, received=None, thread=None) -> None:
    """Publish ``messages`` in batches; ``received()`` (when given) counts those taken: wait for it."""
    for at in range(0, len(messages), BATCH):
        for message in messages[at:at + BATCH]:
            publisher.publish(message)
        if received is not None:
            limit = time.monotonic() + 30.0
            while received() < min(at + BATCH, len(messages)) - BATCH and time.monotonic() < limit:
                time.sleep(0.0005)
    if received is not None:
        limit = time.monotonic() + 60.0
        while received() < len(messages) and time.monotonic() < limit:
            time.sleep(0.001)
        if received() < len(messages):
            raise SystemExit(f"only {received()} of {len(messages)} messages arrived")
    else:
        publisher.wait_for_all_acked()
        wait_quiet(thread)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profiles", type=int, default=2000)
    parser.add_argument("--points", type=int, default=2000)
    args = parser.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = Context()
    rclpy.init(context=context)
    namespace = f"bench{os.getpid()}"
    node = StreamAcquisitionNode(context=context, namespace=namespace)
    source = Node("bench_source", context=context, namespace=namespace)
    threads = NodeThreads([node])
    thread = threads.threads[0]
    try:
        profiles_pub = source.create_publisher(PointCloud2, node.layout.scan_topic, stream_qos(10000))
        tf_pub = source.create_publisher(TFMessage, LAYOUT.tf_topic, stream_qos(10000))
        static_pub = source.create_publisher(TFMessage, LAYOUT.tf_static_topic, static_qos())
        for publisher in (profiles_pub, tf_pub):
            while publisher.get_subscription_count() == 0:
                time.sleep(0.01)
        static_pub.publish(TFMessage(transforms=[
            transform_msg(node.frames.flange, node.frames.sensor, node.frames.flange_to_sensor, 0)]))
        rng = np.random.default_rng(0)
        period_ns = int(NS_PER_S / PROFILE_RATE_HZ)
        start_ns, end_ns = NS_PER_S, NS_PER_S + period_ns * args.profiles
        profile_stamps = start_ns + period_ns // 2 + period_ns * np.arange(args.profiles + 1)
        tf_stamps = np.arange(start_ns - 2 * NS_PER_S // 250, profile_stamps[-1] + NS_PER_S // 125,
                              int(NS_PER_S / TF_RATE_HZ))
        clouds = [profile_message(args.points, int(stamp), node.frames.sensor, rng) for stamp in profile_stamps]
        poses = [flange_message(node, int(stamp)) for stamp in tf_stamps]
        time.sleep(0.5)
        wait_quiet(thread)
        rows = []
        session = Session(StreamAssembler(node.layout, node.limits, "bench"))
        for message in list(node.statics.values()):
            session.assembler.add(LAYOUT.tf_static_topic, message)
        session.assembler.add(LAYOUT.motion_start_topic, Header(stamp=time_msg(start_ns)))
        node.session = session
        for label, publisher, messages, received in (
                ("during a sweep: flange poses (TFMessage)", tf_pub, poses,
                 lambda: int(np.searchsorted(tf_stamps, session.newest_tf_ns, side="right"))),
                ("during a sweep: profiles (PointCloud2)", profiles_pub, clouds, lambda: session.profiles)):
            before = thread_cpu_s(thread)
            send(publisher, messages, received)
            rows.append((label, (thread_cpu_s(thread) - before) / len(messages), len(messages)))
        node.session = None
        session.started = True
        session.assembler.add(LAYOUT.motion_end_topic, Header(stamp=time_msg(end_ns)))
        session.end_ns = end_ns
        began = time.thread_time()
        if hasattr(node, "_placement"):     # the profiles placed a block of rows at a time into the answer
            from gls_calibration.ros.pointcloud import xyzi_blocks_to_msg

            placement = node._placement(session)
            assembly_s = time.thread_time() - began
            began = time.thread_time()
            answer = xyzi_blocks_to_msg(*placement.shape, placement.place_rows, node.frame_id,
                                        time_msg(int(placement.stamps_ns[0])))
            answer_s = time.thread_time() - began
            if placement.shape != (args.profiles, args.points) or not answer.is_dense:
                raise SystemExit(f"unexpected sweep {placement.shape}")
        else:
            sweep = node._sweep(session)
            assembly_s = time.thread_time() - began
            if sweep.xyz_mm.shape != (args.profiles, args.points, 3) or not np.isfinite(sweep.xyz_mm).all():
                raise SystemExit(f"unexpected sweep {sweep.xyz_mm.shape}")
            began = time.thread_time()
            answer = answer_msg(sweep.xyz_mm, sweep.intensity, node.frame_id, time_msg(int(sweep.stamps_ns[0])))
            answer_s = time.thread_time() - began
        began = time.thread_time()
        serialize_message(answer)
        answer_wire_s = time.thread_time() - began
        del answer
        for label, publisher, messages in (("between sweeps: flange poses", tf_pub, poses),
                                           ("between sweeps: profiles", profiles_pub, clouds)):
            before = thread_cpu_s(thread)
            send(publisher, messages, None, thread)
            rows.append((label, (thread_cpu_s(thread) - before) / len(messages), len(messages)))
        # the parts of a message's handling outside the executor, in this thread
        assembler = StreamAssembler(node.layout, node.limits, "bench")
        for message in list(node.statics.values()):
            assembler.add(LAYOUT.tf_static_topic, message)
        for label, messages, topic in (("  rclpy deserialise: TFMessage", poses, LAYOUT.tf_topic),
                                       ("  rclpy deserialise: PointCloud2", clouds, node.layout.scan_topic)):
            raw = [serialize_message(message) for message in messages]
            kind = type(messages[0])
            began = time.thread_time()
            decoded = [deserialize_message(item, kind) for item in raw]
            rows.append((label, (time.thread_time() - began) / len(raw), len(raw)))
            began = time.thread_time()
            for message in decoded:
                assembler.add(topic, message)
            rows.append((f"  StreamAssembler.add: {kind.__name__}", (time.thread_time() - began) / len(raw), len(raw)))
    finally:
        threads.stop()
        source.destroy_node()
        context.try_shutdown()
    print(f"stream_acquisition, {args.profiles} profiles of {args.points} points, {len(poses)} flange poses; "
          f"CPU per message (node thread) [load {os.getloadavg()[0]:.1f}]:")
    for label, seconds, count in rows:
        print(f"  {label:48s} {1e6 * seconds:8.1f} us  ({count} messages)")
    print(f"  {'sweep assembly at the end, per profile':48s} {1e6 * assembly_s / args.profiles:8.1f} us")
    print(f"  {'the answer: sweep to PointCloud2, per profile':48s} {1e6 * answer_s / args.profiles:8.1f} us")
    print(f"  {'the answer: rclpy serialisation, per profile':48s} {1e6 * answer_wire_s / args.profiles:8.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
