"""CycloneDDS plumbing for the bridge: ROS 2 topic names and QoS profiles, a loopback configuration, and readers and
writers of pre-serialized CDR (for the big image messages, see :mod:`vpengine.ros2.cdr`).

ROS 2 conventions matched (rmw_cyclonedds_cpp):

* topic ``/camera/image_raw`` is the DDS topic ``rt/camera/image_raw``;
* type ``sensor_msgs/msg/Image`` is the DDS type ``sensor_msgs::msg::dds_::Image_``;
* data representation XCDR1 (encapsulation ``CDR_LE``), which is what ROS 2 writes and reads;
* QoS: the default profile is reliable, volatile, keep last 10; the sensor-data profile best effort, volatile, keep
  last 5; "latched" (what ``ros2 topic echo --qos-durability transient_local`` receives) is reliable,
  transient-local, keep last 1; "latest" (the bridge's outputs, Note [Output QoS] in :mod:`vpengine.ros2.outputs`) is
  reliable, volatile, keep last 1.
"""

from __future__ import annotations

import os
import re
from typing import Any, Literal

from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

QosName = Literal["default", "sensor", "latched", "latest"]
QOS_NAMES = ("default", "sensor", "latched", "latest")

#: The cyclonedds major release this module is tested with (its private _clayer calls, see _private_api).
TESTED_MAJOR = 11
#: The socket receive buffer the bridge asks for (Note [Input link] in vpengine.ros2.diagnostics); the kernel grants at
#: most net.core.rmem_max of it.
RECEIVE_BUFFER_BYTES = 64 << 20


def _private_api() -> tuple[Any, Any]:
    """cyclonedds' C calls behind DataWriter.write and DataReader.take, which the hot path calls with CDR bytes.

    They are private (``cyclonedds._clayer``), so an untested cyclonedds may lack or change them: fail with one line
    that says which release to install, not with a traceback from deep in a write."""
    try:
        from cyclonedds._clayer import ddspy_take, ddspy_write
    except ImportError:
        from importlib.metadata import version

        raise ImportError(
            f"vpengine.ros2 needs cyclonedds {TESTED_MAJOR}.x (it writes and takes raw CDR through cyclonedds' "
            f"private _clayer module, which cyclonedds {version('cyclonedds')} does not have as expected): "
            f"pip install 'cyclonedds>={TESTED_MAJOR},<{TESTED_MAJOR + 1}'"
        ) from None
    return ddspy_write, ddspy_take


_ANY = SampleState.Any | ViewState.Any | InstanceState.Any
_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def dds_topic(ros_topic: str) -> str:
    """``/camera/image_raw`` -> ``rt/camera/image_raw`` (a relative name is taken from the root namespace)."""
    name = ros_topic if ros_topic.startswith("/") else f"/{ros_topic}"
    name = name.rstrip("/")
    if not _ROS_NAME.match(name):
        raise ValueError(
            f"topic {ros_topic!r} is not a valid ROS 2 topic name (tokens of letters, digits and '_', "
            "not starting with a digit, separated by '/')"
        )
    return "rt" + name


def qos(name: QosName) -> Qos:
    """A ROS 2 QoS profile as CycloneDDS QoS (always XCDR1, as ROS 2 writes)."""
    xcdr1 = Policy.DataRepresentation(use_cdrv0_representation=True)
    if name == "default":
        return Qos(
            Policy.Reliability.Reliable(duration(seconds=1)),
            Policy.Durability.Volatile,
            Policy.History.KeepLast(10),
            xcdr1,
        )
    if name == "sensor":
        return Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5), xcdr1)
    if name == "latched":
        return Qos(
            Policy.Reliability.Reliable(duration(seconds=1)),
            Policy.Durability.TransientLocal,
            Policy.History.KeepLast(1),
            xcdr1,
        )
    if name == "latest":
        return Qos(
            Policy.Reliability.Reliable(duration(seconds=1)),
            Policy.Durability.Volatile,
            Policy.History.KeepLast(1),
            xcdr1,
        )
    raise ValueError(f"QoS profile {name!r} is not known; accepted: {', '.join(QOS_NAMES)}")


def loopback_config(large_messages: bool = True) -> str:
    """A CycloneDDS configuration that keeps discovery and data on the loopback interface (127.0.0.1).

    Loopback has no multicast, so participants find each other by unicast to 127.0.0.1 on the well-known ports of
    participant indices 0..(MaxAutoParticipantIndex). ``large_messages`` sizes the transport for camera images:
    64 kB messages (loopback's MTU allows it; cyclonedds' default of 14 kB makes a 1080p frame ~450 packets), the
    bridge's receive buffer (:data:`RECEIVE_BUFFER_BYTES`, as much as net.core.rmem_max allows), and a writer
    history high-water mark of 64 MB so reliable writers of multi-megabyte images do not stall on acknowledgements.
    """
    big = "<MaxMessageSize>65500B</MaxMessageSize><FragmentSize>60000B</FragmentSize>" if large_messages else ""
    internal = (
        f'<Internal><SocketReceiveBufferSize min="default" max="{RECEIVE_BUFFER_BYTES}B"/>'
        "<Watermarks><WhcHigh>64MB</WhcHigh></Watermarks></Internal>"
        if large_messages
        else ""
    )
    return (
        '<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
        f"<AllowMulticast>false</AllowMulticast>{big}</General>"
        "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>"
        '<Peers><Peer address="127.0.0.1"/></Peers></Discovery>'
        f"{internal}</Domain></CycloneDDS>"
    )


def bridge_config(extra: str | None = None, user: str | None = None) -> str:
    """The bridge's CycloneDDS configuration: its own needs first, then the user's: ``extra`` when given (e.g.
    :func:`loopback_config`, asked for on the command line), else ``$CYCLONEDDS_URI`` (``user`` defaults to it).

    CycloneDDS reads a comma-separated list of files and XML fragments in order, and a later setting replaces an
    earlier one, so whatever the user configured wins and nothing of theirs is dropped. (Lists such as network
    interfaces and peers add up instead, which is why ``extra`` replaces $CYCLONEDDS_URI rather than joining it.)
    Of its own the bridge asks for a large socket receive buffer (:data:`RECEIVE_BUFFER_BYTES`, granted up to
    net.core.rmem_max): cyclonedds' default of 1 MB loses most 1080p frames sent best effort (Note [Input link] in
    :mod:`vpengine.ros2.diagnostics`).
    """
    user = os.environ.get("CYCLONEDDS_URI") if user is None else user
    own = (
        '<CycloneDDS><Domain id="any"><Internal>'
        f'<SocketReceiveBufferSize min="default" max="{RECEIVE_BUFFER_BYTES}B"/>'
        "</Internal></Domain></CycloneDDS>"
    )
    return ",".join(part for part in (own, (extra or user or "").strip()) if part)


def receive_buffer_granted(limit: int | None) -> int | None:
    """What the bridge's sockets get of :data:`RECEIVE_BUFFER_BYTES` where the kernel caps it at ``limit``."""
    return None if limit is None else min(limit, RECEIVE_BUFFER_BYTES)


class DdsContext:
    """One domain participant. ``config``: a CycloneDDS XML configuration; None uses $CYCLONEDDS_URI / defaults."""

    def __init__(self, domain_id: int = 0, config: str | None = None) -> None:
        if not 0 <= domain_id <= 232:
            raise ValueError(f"DDS domain id must be 0..232 (the RTPS port mapping), got {domain_id}")
        self.domain_id = domain_id
        self._domain = Domain(domain_id, config) if config is not None else None
        self.participant = DomainParticipant(domain_id)
        self._topics: dict[str, Topic] = {}

    def topic(self, ros_topic: str, dds_type: type) -> Topic:
        name = dds_topic(ros_topic)
        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = Topic(self.participant, name, dds_type)
        elif t.data_type is not dds_type:
            raise ValueError(f"topic {ros_topic!r} is already used with type {t.data_type.__name__}")
        return t

    def writer(self, ros_topic: str, dds_type: type, qos_name: QosName = "default") -> Writer:
        return Writer(DataWriter(self.participant, self.topic(ros_topic, dds_type), qos(qos_name)))

    def reader(self, ros_topic: str, dds_type: type, qos_name: QosName = "default") -> Reader:
        return Reader(DataReader(self.participant, self.topic(ros_topic, dds_type), qos(qos_name)))

    def close(self) -> None:
        """Delete the participant and with it every reader, writer and topic (peers see them leave at once)."""
        self._topics.clear()
        p, self.participant = self.participant, None  # type: ignore[assignment]
        if p is not None:
            # cyclonedds deletes an entity (dds_delete, recursive) in __del__; call it now rather than whenever the
            # last reference goes, so a stopped bridge disappears from the graph immediately.
            p.__del__()
        self._domain = None


class Writer:
    """A DataWriter that also writes pre-serialized CDR (``write_raw``) for the hot path."""

    def __init__(self, writer: DataWriter) -> None:
        self.dds = writer
        self._write = _private_api()[0]  # the C call DataWriter.write ends in

    def write(self, sample: Any) -> None:
        self.dds.write(sample)

    def write_raw(self, data: bytes | bytearray) -> None:
        """Write CDR bytes (encapsulation header included, length a multiple of 4) as one sample."""
        ret = self._write(self.dds._ref, data)
        if ret < 0:
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"writing {len(data)} serialized bytes on {self.dds.topic.name}")

    def close(self) -> None:
        """Delete the writer now (its readers see it leave), not whenever the last reference goes; not while
        another thread writes with it."""
        self.dds.__del__()

    def matched(self) -> int:
        """How many readers this writer is matched with."""
        return len(self.dds.get_matched_subscriptions())


class Reader:
    """A DataReader that can hand out the raw CDR of each sample (``take_raw``) and wait for data."""

    def __init__(self, reader: DataReader) -> None:
        self.dds = reader
        self._take = _private_api()[1]
        self._waitset = WaitSet(reader.participant)
        self._cond = ReadCondition(reader, _ANY)
        self._waitset.attach(self._cond)

    def wait(self, timeout: float) -> bool:
        """Block until a sample is there or ``timeout`` seconds pass; True if there is data."""
        return self._waitset.wait(duration(seconds=timeout)) > 0

    def also_wake_for(self, other: Reader) -> None:
        """Let :meth:`wait` return when ``other`` has data too: one thread waits on several readers."""
        self._waitset.attach(other._cond)

    def take_raw(self, n: int = 16) -> list[bytes]:
        """Up to ``n`` samples as CDR bytes (encapsulation header included); invalid samples (disposals) skipped."""
        return [data for data, _ in self.take_raw_stamped(n)]

    def take_raw_stamped(self, n: int = 16) -> list[tuple[bytes, float]]:
        """Like :meth:`take_raw`, each with the time its writer wrote it (DDS source timestamp, s since the epoch)."""
        ret = self._take(self.dds._ref, _ANY, n)
        if isinstance(ret, int):
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"taking samples from {self.dds.topic.name}")
        return [(data, info.source_timestamp * 1e-9) for data, info in ret if info.valid_data]

    def matched(self) -> int:
        """How many writers this reader is matched with."""
        return len(self.dds.get_matched_publications())

    def take(self, n: int = 16) -> list[Any]:
        """Up to ``n`` deserialized samples (valid ones only)."""
        from cyclonedds.internal import InvalidSample  # disposals/unregistrations carry no data

        return [s for s in self.dds.take(N=n) if not isinstance(s, InvalidSample)]
