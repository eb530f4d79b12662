"""``vpengine ros2``: the engine on a ROS 2 graph through the CycloneDDS bridge (no ROS 2 installation needed).

::

    vpengine ros2 --config configs/tiny.yaml --input-topic /camera/image_raw [--namespace /vpengine]
                  (several cameras: --input-topic front=/front/image_raw --input-topic rear=/rear/image_raw)
                  [--input-qos sensor|default] [--output-qos latest|default] [--compressed] [--depth-color] [--seg-overlay] [--domain-id N]

Topics, types and QoS: see ``docs/ros2.md`` (and :mod:`vpengine.ros2.bridge`). Prints one ``ready`` line when the
engine runs and every topic is up; Ctrl-C (SIGINT) or SIGTERM stops it cleanly (engine stopped, DDS entities
deleted) with exit status 0.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import time
from typing import Any

from vpengine.arguments import add_overrides_argument
from vpengine.cli.serve import add_serve_arguments, serve_options, serving


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", required=True, help="engine config (YAML or JSON)")
    p.add_argument(
        "--input-topic",
        required=True,
        action="append",
        metavar="[NAME=]TOPIC",
        help="camera topic, sensor_msgs/Image (e.g. /camera/image_raw); several cameras: NAME=TOPIC for each, "
        "repeated (each camera's outputs then go under <namespace>/<NAME>/)",
    )
    p.add_argument("--namespace", default="/vpengine", help="prefix of every output topic (default: /vpengine)")
    p.add_argument(
        "--input-qos",
        choices=["sensor", "default"],
        default="sensor",
        help="input QoS: sensor (best effort, keep last 5; default) or default (reliable, keep last 10)",
    )
    p.add_argument(
        "--output-qos",
        choices=["latest", "default"],
        default="latest",
        help="output QoS: latest (reliable, keep last 1; default: a slow subscriber gets the newest output, not a "
        "queue of old ones) or default (ROS 2's: reliable, keep last 10)",
    )
    p.add_argument(
        "--compressed",
        action="store_true",
        help="read sensor_msgs/CompressedImage (jpeg/png) from <input-topic>/compressed",
    )
    p.add_argument("--depth-color", action="store_true", help="also publish colour-mapped depth (<head>/depth_color)")
    p.add_argument("--seg-overlay", action="store_true", help="also publish segmentation overlays (<head>/overlay)")
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        help="DDS domain (default: $ROS_DOMAIN_ID, else 0)",
    )
    p.add_argument(
        "--input-size",
        choices=["config", "first"],
        default="config",
        help="the models' input size: the config's (default; the engine starts at once) or the first message's (the "
        "camera's frames then need no resizing); outputs are at each message's own size either way",
    )
    p.add_argument(
        "--loopback",
        action="store_true",
        help="keep DDS on 127.0.0.1 with large-message settings (instead of $CYCLONEDDS_URI)",
    )
    add_overrides_argument(p, "heads.depth.rate_hz=5")
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: run until Ctrl-C)")
    add_serve_arguments(p)


def _domain_id(arg: int | None) -> int:
    if arg is not None:
        return arg
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not env:
        return 0
    if not env.isdigit():
        raise ValueError(f"ROS_DOMAIN_ID={env!r} is not a domain id (0..232)")
    return int(env)


def main(args: argparse.Namespace) -> int:
    from vpengine.ros2.bridge import BridgeOptions, Ros2Bridge
    from vpengine.ros2.core import Ros2Core, input_topics
    from vpengine.ros2.dds import loopback_config

    serve = serve_options(args)
    overrides = list(args.overrides)
    if args.mode:
        overrides.append(f"mode={args.mode}")
    topics = input_topics(args.input_topic)
    core = Ros2Core(
        args.config,
        namespace=args.namespace,
        input_size=args.input_size,
        depth_color=args.depth_color,
        seg_overlay=args.seg_overlay,
        overrides=overrides,
        cameras=list(topics) if isinstance(topics, dict) else None,
        keep_frames=serve is not None,  # the view draws overlays and boxes on the input frames
    )
    opts = BridgeOptions(
        input_topic=topics,
        compressed=args.compressed,
        input_qos=args.input_qos,
        output_qos=args.output_qos,
        domain_id=_domain_id(args.domain_id),
        dds_config=loopback_config() if args.loopback else None,
    )
    bridge = Ros2Bridge(core, opts)
    view = contextlib.ExitStack()
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        bridge.start()
        # a head added or removed through the view would have no topics: the ROS 2 commands own heads here
        ns = core.namespace
        elsewhere = f"under vpengine ros2, add and remove heads on {ns}/add_head and {ns}/remove_head: they get topics"
        view.enter_context(serving(serve, lambda: core.engine, core.book.frame, heads_elsewhere=elsewhere))
        print(
            f"vpengine ros2: ready on domain {opts.domain_id}: {opts.subscribed_topic} -> "
            f"{', '.join(t.topic for t in core.topics)}",
            flush=True,
        )
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set() and not bridge.wait(0.2):
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        view.close()
        bridge.stop()
        for s, h in previous.items():
            signal.signal(s, h)
    c = core.counters
    print(
        f"vpengine ros2: stopped; {c['received']} messages in, {c['submitted']} submitted, "
        f"{c['superseded']} superseded, {c['rejected']} rejected, {sum(core.published.values())} published",
        flush=True,
    )
    if bridge.error is not None:
        print(f"vpengine ros2: stopped on an error: {bridge.error}", file=sys.stderr)
        return 1
    return 0
