"""rosbag2 datasets without the ROS 2 CLI: write and read bags with the ``rosbags`` package.

This module knows ROS message *types* (so it is not in ``core``) but needs neither rclpy nor
a DDS middleware to write a bag: messages are built as ``rosbags`` typestore objects and
serialized to CDR by ``rosbags``. Reading returns the raw CDR bytes, which
``rclpy.serialization.deserialize_message`` (live tools) or :func:`deserialize` (``rosbags``,
offline tools) turn back into messages.

Bag layout written here is the one ``ros2 bag record`` writes in ROS 2 Jazzy
(rosbag2 0.26.x), so ``ros2 bag info`` / ``ros2 bag play`` accept it:

* ``metadata.yaml`` version 9 (:data:`BAG_VERSION`): since rosbag2 PR #1476 (0.25.0, the
  last release before Jazzy's 0.26.0) ``offered_qos_profiles`` is a YAML *list* of maps
  with lower-case policy names (``history: keep_last``, ``reliability: reliable`` ...)
  instead of the older quoted YAML string with integer enums (version <= 8). Every topic
  carries ``type_description_hash: RIHS01_<sha256>`` (metadata version >= 7, REP-2016 type
  hashes) and ``serialization_format: cdr``.
* MCAP storage (the rosbag2 default since Iron) with the ``ros2`` MCAP profile: schema
  encoding ``ros2msg``, message encoding ``cdr``, channel user data ``offered_qos_profiles``
  and, like rosbag2_storage_mcap's ``create_topic``, ``topic_type_hash``; or sqlite3
  storage (``.db3``, schema version 4 with ``message_definitions`` and
  ``type_description_hash`` columns).
* Type hashes come from ``rosbags``' Jazzy typestore (``Stores.ROS2_JAZZY``); the tests
  compare them with the hashes rosidl generated for the installed message packages
  (``share/<pkg>/msg/<Type>.json``, ``type_hashes[0].hash_string``).

Message timestamps: the bag (receive/log) time of every message written by
:class:`BagWriter` is the caller's ``stamp_ns`` (simulated time), the same value as the
message's ``header.stamp`` for stamped messages, so a replay with ``/clock`` reproduces the
simulated timeline exactly.
"""

from collections import namedtuple
import math
import os
from pathlib import Path

import numpy as np

from .core.conventions import (bearing_covariance6, IDX_AZ_VAR, IDX_EL_VAR,  # noqa: F401
                               NO_ELEVATION_VARIANCE, quaternion_from_azel)
from .core.text import short_repr
from .core.yaml_file import read_yaml

#: rosbag2 metadata version written (Jazzy, rosbag2 0.26.x, see module docstring).
BAG_VERSION = 9
#: Storage plugins understood by ``ros2 bag`` in Jazzy and by ``rosbags``.
STORAGES = ('mcap', 'sqlite3')
DEFAULT_STORAGE = 'mcap'
#: ROS 2 distribution recorded in written bags (metadata ros_distro).
ROS_DISTRO = 'jazzy'

#: Message type names used by bearing_loc_ros (DESIGN.md).
POSE_COV_STAMPED = 'geometry_msgs/msg/PoseWithCovarianceStamped'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
CLOCK = 'rosgraph_msgs/msg/Clock'
CLOCK_TOPIC = '/clock'

#: Layout of the bearing message covariance (DESIGN.md "The bearing message"): IDX_EL_VAR,
#: IDX_AZ_VAR and the packing come from core.conventions, shared with ros_conversions; the
#: fix's rotational variance is kept equal to ros_conversions' by test_bag.py (this module
#: must not import rclpy message packages just to write a bag).
NO_ELEVATION = NO_ELEVATION_VARIANCE
UNKNOWN_ROTATION_VARIANCE = 1.0e6
NS_PER_S = 1_000_000_000

BagMessage = namedtuple('BagMessage', 'topic msgtype log_time_ns raw')
BagMessage.__doc__ = """One message read from a bag: topic, type name, bag (log) time in
integer ns, raw CDR bytes."""

TopicInfo = namedtuple('TopicInfo', 'name msgtype count qos type_hash')
TopicInfo.__doc__ = """Topic of a bag: name, type name, message count, list of offered QoS
profiles as dicts (metadata.yaml version 9 form), RIHS01 type description hash."""

_TYPESTORE = None


def typestore():
    """The ``rosbags`` typestore of ROS 2 Jazzy (created once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import get_typestore, Stores
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def type_hash(msgtype):
    """RIHS01 type description hash (REP-2016) of a message type name, from rosbags."""
    return typestore().hash_rihs01(msgtype)


# --------------------------------------------------------------------------------------- QoS

def qos_profile(depth=10, reliable=True, transient_local=False):
    """An offered QoS profile as written to metadata.yaml version 9 (a dict).

    history keep_last(depth); reliability reliable|best_effort; durability
    volatile|transient_local; deadline, lifespan and liveliness lease duration 0 s 0 ns
    (``RMW_DURATION_UNSPECIFIED``: the middleware default, i.e. none); liveliness automatic.
    These are the rclpy defaults of ``create_publisher(type, topic, depth)``.
    """
    if int(depth) < 1:
        raise ValueError(f'qos depth: must be >= 1, got {depth}')
    zero = {'sec': 0, 'nsec': 0}
    return {
        'history': 'keep_last', 'depth': int(depth),
        'reliability': 'reliable' if reliable else 'best_effort',
        'durability': 'transient_local' if transient_local else 'volatile',
        'deadline': dict(zero), 'lifespan': dict(zero), 'liveliness': 'automatic',
        'liveliness_lease_duration': dict(zero), 'avoid_ros_namespace_conventions': False,
    }


#: Offered QoS of topics without a more specific profile (rclpy default: depth 10, reliable).
DEFAULT_QOS = qos_profile(10)
#: Offered QoS of the simulator node's publishers (simulator_node.BEARING_QOS, TRUTH_QOS,
#: CLOCK_QOS): reliable, keep-last 100 for bearings and truth, 10 for /clock. A reliable
#: /clock matches both the best-effort rclpy TimeSource subscription and reliable ones.
SIM_BEARING_QOS = qos_profile(100)
SIM_TRUTH_QOS = qos_profile(100)
CLOCK_QOS = qos_profile(10)


def _qos_to_rosbags(q):
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    return Qos(QosHistory[q['history'].upper()], int(q['depth']),
               QosReliability[q['reliability'].upper()],
               QosDurability[q['durability'].upper()],
               QosTime(q['deadline']['sec'], q['deadline']['nsec']),
               QosTime(q['lifespan']['sec'], q['lifespan']['nsec']),
               QosLiveliness[q['liveliness'].upper()],
               QosTime(q['liveliness_lease_duration']['sec'],
                       q['liveliness_lease_duration']['nsec']),
               bool(q['avoid_ros_namespace_conventions']))


def _qos_from_rosbags(q):
    return {
        'history': q.history.name.lower(), 'depth': int(q.depth),
        'reliability': q.reliability.name.lower(), 'durability': q.durability.name.lower(),
        'deadline': {'sec': q.deadline.sec, 'nsec': q.deadline.nsec},
        'lifespan': {'sec': q.lifespan.sec, 'nsec': q.lifespan.nsec},
        'liveliness': q.liveliness.name.lower(),
        'liveliness_lease_duration': {'sec': q.liveliness_lease_duration.sec,
                                      'nsec': q.liveliness_lease_duration.nsec},
        'avoid_ros_namespace_conventions': bool(q.avoid_ros_namespace_conventions),
    }


# ------------------------------------------------------------------------ message builders

def _time(ns):
    ns = int(ns)
    if ns < 0:
        raise ValueError(f'stamp: negative time {ns} ns')
    return typestore().types['builtin_interfaces/msg/Time'](sec=ns // NS_PER_S,
                                                            nanosec=ns % NS_PER_S)


def _header(stamp_ns, frame_id):
    return typestore().types['std_msgs/msg/Header'](stamp=_time(stamp_ns),
                                                    frame_id=str(frame_id))


def _pose_cov_stamped(stamp_ns, frame_id, position, quaternion, cov6):
    t = typestore().types
    p = [float(v) for v in position]
    q = [float(v) for v in quaternion]
    pose = t['geometry_msgs/msg/Pose'](
        position=t['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
        orientation=t['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))
    pwc = t['geometry_msgs/msg/PoseWithCovariance'](
        pose=pose, covariance=np.asarray(cov6, dtype=np.float64).reshape(36).copy())
    return t[POSE_COV_STAMPED](header=_header(stamp_ns, frame_id), pose=pwc)


def bearing_message(bearing):
    """Core :class:`~bearing_loc_ros.core.bearings.Bearing` -> rosbags PoseWithCovarianceStamped.

    Same contract as ``ros_conversions.bearing_to_msg`` (DESIGN.md bearing message):
    stamp = observation time, position = station, orientation = yaw θ, pitch −ψ, roll 0
    (``quaternion_from_azel``), covariance[0..2,0..2] = station position covariance (m²),
    covariance[4*6+4] = σ_ψ² (rad²) or −1 for an azimuth-only bearing, covariance[5*6+5] =
    σ_θ² (rad²). test_bag.py checks the CDR bytes against the rclpy conversion.
    """
    has_el = math.isfinite(bearing.elevation)
    q = quaternion_from_azel(bearing.azimuth, bearing.elevation if has_el else 0.0)
    cov = bearing_covariance6(bearing.position_covariance, bearing.sigma_azimuth,
                              bearing.sigma_elevation if has_el else None)
    return _pose_cov_stamped(bearing.stamp_ns, bearing.frame_id, bearing.position, q, cov)


def fix_message(position, covariance, stamp_ns, frame_id='map'):
    """Estimate -> rosbags PoseWithCovarianceStamped, as ``ros_conversions.fix_to_msg``.

    Position (3,) m, covariance (3, 3) m² in covariance[0..2,0..2]; orientation identity
    with variance ``UNKNOWN_ROTATION_VARIANCE`` (rad²) on the three rotation axes.
    """
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.asarray(covariance, dtype=float)
    cov[3, 3] = cov[4, 4] = cov[5, 5] = UNKNOWN_ROTATION_VARIANCE
    return _pose_cov_stamped(stamp_ns, frame_id, position, (0.0, 0.0, 0.0, 1.0), cov)


def truth_message(position, stamp_ns, frame_id='map'):
    """Ground truth (3,) m -> rosbags geometry_msgs/PoseStamped, identity orientation.

    Same message as ``simulator_node.truth_to_msg`` (topic ``<target ns>/truth``).
    """
    t = typestore().types
    p = [float(v) for v in position]
    pose = t['geometry_msgs/msg/Pose'](
        position=t['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
        orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
    return t[POSE_STAMPED](header=_header(stamp_ns, frame_id), pose=pose)


def position_of(msg):
    """(3,) position of a PoseStamped / PoseWithCovarianceStamped (rosbags or rclpy), m."""
    pose = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
    p = pose.position
    return np.array([p.x, p.y, p.z], dtype=float)


def clock_message(stamp_ns):
    """Simulated time (integer ns) -> rosbags rosgraph_msgs/Clock."""
    return typestore().types[CLOCK](clock=_time(stamp_ns))


def serialize(msg):
    """CDR bytes (little endian, with the 4-byte encapsulation header) of a rosbags message."""
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def deserialize(raw, msgtype):
    """Raw CDR bytes -> rosbags message object of type ``msgtype`` (no rclpy needed)."""
    return typestore().deserialize_cdr(raw, msgtype)


def stamp_ns(msg):
    """header.stamp (or Clock.clock) of a rosbags or rclpy message, integer ns."""
    t = msg.clock if hasattr(msg, 'clock') else msg.header.stamp
    return int(t.sec) * NS_PER_S + int(t.nanosec)


# ----------------------------------------------------------------------------------- writer

def _mcap_writer_class():
    """rosbags' MCAP storage writer, extended to add ``topic_type_hash`` channel metadata.

    rosbag2_storage_mcap (Jazzy) ``MCAPStorage::create_topic`` stores two channel metadata
    entries, ``offered_qos_profiles`` and ``topic_type_hash``; rosbags 0.11 writes only the
    first, so a bare ``.mcap`` read without metadata.yaml (``ros2 bag reindex``, Foxglove)
    would lose the type hash. Falls back to the plain writer if rosbags' internals differ.
    """
    from rosbags.rosbag2.storage_mcap import McapWriter
    try:
        from io import BytesIO
        from rosbags.rosbag2.storage_mcap import Channel, write_channel, write_string
    except ImportError:  # pragma: no cover - other rosbags versions
        return McapWriter

    class HashingMcapWriter(McapWriter):
        def add_connection(self, connection, offered_qos_profiles):
            metadata = BytesIO()
            write_string(metadata, 'offered_qos_profiles')
            write_string(metadata, offered_qos_profiles)
            write_string(metadata, 'topic_type_hash')
            write_string(metadata, connection.digest)
            self.channels.append(Channel(connection.id, connection.msgtype, connection.topic,
                                         connection.ext.serialization_format,
                                         metadata.getvalue()))
            self.channel_stats[connection.id] = 0
            write_channel(self.chunk.bio, self.channels[-1], self.schemas)

    return HashingMcapWriter


class BagWriter:
    """Write a rosbag2 bag (directory ``path`` with metadata.yaml + one storage file).

    Usage::

        with BagWriter('run1', storage='mcap') as bag:
            bag.add_topic('/station_1/bearing', POSE_COV_STAMPED)
            bag.write('/station_1/bearing', stamp_ns, bearing_message(b))

    ``write`` takes a rosbags message object (from the builders above) or raw CDR bytes.
    Topics must be absolute names. The target directory must not exist (rosbag2 refuses to
    overwrite too). ``custom_data`` (str -> str) is stored in metadata.yaml ``custom_data``.
    """

    def __init__(self, path, storage=DEFAULT_STORAGE, custom_data=None):
        from rosbags.rosbag2 import StoragePlugin, Writer
        if storage not in STORAGES:
            raise ValueError(f'storage: must be one of {STORAGES}, got {storage!r}')
        self.path = Path(path)
        if self.path.exists():
            raise ValueError(f'out: {self.path} exists already (a bag is never overwritten)')

        class _Writer(Writer):
            STORAGE_PLUGINS = dict(Writer.STORAGE_PLUGINS)
            STORAGE_PLUGINS[StoragePlugin.MCAP] = _mcap_writer_class()

        plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
        self._writer = _Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
        for key, value in (custom_data or {}).items():
            self._writer.set_custom_data(str(key), str(value))
        self._connections = {}
        self._open = False

    def open(self):
        """Create the bag directory and storage file."""
        self._writer.open()
        self._open = True
        storage = self._writer.storage
        close = storage.close

        def close_as_distro(version, metadata):
            # rosbags records itself as the distribution; the bags are Jazzy's format
            cursor = getattr(storage, 'cursor', None)
            if cursor is not None:          # sqlite3: its schema table names it too
                cursor.execute('UPDATE schema SET ros_distro = ?', (ROS_DISTRO,))
            close(version, metadata.replace('ros_distro: rosbags', f'ros_distro: {ROS_DISTRO}'))

        storage.close = close_as_distro
        return self

    def add_topic(self, topic, msgtype, qos=None):
        """Register ``topic`` (absolute name) with type name ``msgtype`` and offered ``qos``."""
        if not topic.startswith('/'):
            raise ValueError(f'topic: {topic!r} must be an absolute name')
        if topic in self._connections:
            raise ValueError(f'topic: {topic!r} added twice')
        if qos is None:
            qos = CLOCK_QOS if topic == CLOCK_TOPIC else DEFAULT_QOS
        conn = self._writer.add_connection(topic, msgtype, typestore=typestore(),
                                           serialization_format='cdr',
                                           offered_qos_profiles=[_qos_to_rosbags(qos)])
        self._connections[topic] = conn
        return conn

    def write(self, topic, log_time_ns, msg):
        """Append one message (rosbags object or CDR bytes) at bag time ``log_time_ns``."""
        try:
            conn = self._connections[topic]
        except KeyError:
            raise ValueError(f'topic: {topic!r} was not added') from None
        raw = msg if isinstance(msg, (bytes, bytearray, memoryview)) else serialize(msg)
        self._writer.write(conn, int(log_time_ns), raw)

    def close(self):
        """Write the storage index and metadata.yaml."""
        if self._open:
            self._writer.close()
            self._open = False
            meta = self.path / 'metadata.yaml'
            meta.write_text(meta.read_text(encoding='utf-8').replace(
                'ros_distro: rosbags', f'ros_distro: {ROS_DISTRO}'), encoding='utf-8')

    def __enter__(self):
        return self.open()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            try:
                self._writer.abort()
            finally:
                self._open = False
        return False


# ----------------------------------------------------------------------------------- reader

#: Top-level key of a rosbag2 ``metadata.yaml``.
METADATA_KEY = 'rosbag2_bagfile_information'


def _one_line(exc):
    """``str(exc)`` with every run of whitespace (YAML errors span lines) made one space."""
    return ' '.join(str(exc).split())


#: The 8 bytes an MCAP file starts and ends with (MCAP specification, "Magic").
MCAP_MAGIC = b'\x89MCAP0\r\n'


def _truncated_mcap_problem(path):
    """Why an MCAP file of bag directory ``path`` cannot be read because it was not closed
    (a recorder killed or a disk full leaves it without its end), or None.

    A closed MCAP file ends with MCAP_MAGIC; ``rosbags`` reads only closed files, and no
    reader installed here recovers the messages of an unclosed one.
    """
    for f in sorted(Path(path).glob('*.mcap')):
        size = f.stat().st_size
        if size == 0:
            return (f'{f.name} is empty (the recording stopped before any message was '
                    'written); record again')
        with open(f, 'rb') as fh:
            fh.seek(max(0, size - len(MCAP_MAGIC)))
            if fh.read() != MCAP_MAGIC:
                return (f'{f.name} looks truncated: its end is missing (the recording was not '
                        'closed, e.g. the recorder was killed); copy the messages it holds into '
                        'a readable file with the mcap command line tool (mcap recover '
                        f'{f.name} -o recovered.mcap, then replace {f.name} by recovered.mcap), '
                        'or record again')
    return None


def _metadata_error(meta, key, problem):
    """The one-line ValueError of field ``key`` of metadata file ``meta``."""
    return ValueError(f'bag: {meta}: {METADATA_KEY}.{key}: {problem}')


def _check_int(meta, key, value, what='an integer', minimum=None):
    """``value`` when it is an integer (not a bool) >= ``minimum``, else the ValueError naming
    field ``key``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise _metadata_error(meta, key, 'required key is missing' if value is None
                              else f'expected {what}, got {short_repr(value)}')
    if minimum is not None and value < minimum:
        raise _metadata_error(meta, key, f'expected {what} >= {minimum}, got {value}')
    return value


def _check_str(meta, key, value, required=True):
    """``value`` when it is a string (or absent and not ``required``), else the ValueError
    naming field ``key``."""
    if value is None and not required:
        return value
    if not isinstance(value, str):
        raise _metadata_error(meta, key, 'required key is missing' if value is None
                              else f'expected a string, got {short_repr(value)}')
    return value


def _check_topics(meta, topics):
    """Check ``topics_with_message_count``: a list of mappings, each with an integer
    ``message_count`` >= 0 and a ``topic_metadata`` mapping whose ``name``, ``type`` and
    ``serialization_format`` are strings (``type_description_hash`` too when given) and
    whose ``offered_qos_profiles``, when given, are QoS profiles ``rosbags`` reads (a list
    of mappings, or the quoted YAML string of metadata version <= 8)."""
    key = 'topics_with_message_count'
    if not isinstance(topics, list):
        raise _metadata_error(meta, key, 'required key is missing' if topics is None else
                              f'expected a list of topics, got {short_repr(topics)}')
    for k, entry in enumerate(topics):
        at = f'{key}[{k}]'
        if not isinstance(entry, dict):
            raise _metadata_error(meta, at, f'expected a mapping, got {short_repr(entry)}')
        _check_int(meta, f'{at}.message_count', entry.get('message_count'),
                   'a message count', 0)
        tm = entry.get('topic_metadata')
        if not isinstance(tm, dict):
            raise _metadata_error(meta, f'{at}.topic_metadata', 'required key is missing'
                                  if tm is None else f'expected a mapping, got {short_repr(tm)}')
        for name in ('name', 'type', 'serialization_format'):
            _check_str(meta, f'{at}.topic_metadata.{name}', tm.get(name))
        _check_str(meta, f'{at}.topic_metadata.type_description_hash',
                   tm.get('type_description_hash'), required=False)
        qos = tm.get('offered_qos_profiles')
        if qos is not None:
            from rosbags.rosbag2.metadata import parse_qos
            try:
                parse_qos(qos)
            except Exception:   # rosbags raises what indexing the wrong data raises
                raise _metadata_error(meta, f'{at}.topic_metadata.offered_qos_profiles',
                                      f'expected a list of QoS profiles, got {short_repr(qos)}'
                                      ) from None


def read_metadata(path):
    """Parse ``<path>/metadata.yaml`` and return its ``rosbag2_bagfile_information`` dict.

    Checks every field a reader uses, so that a damaged or hand-edited file is named
    instead of failing later: the document is a mapping holding the mapping
    ``rosbag2_bagfile_information``, whose ``version`` is an integer within 1 to
    :data:`BAG_VERSION`, ``storage_identifier`` one of :data:`STORAGES`,
    ``relative_file_paths`` a non-empty list of file names, ``duration.nanoseconds`` and
    ``message_count`` integers >= 0, ``starting_time.nanoseconds_since_epoch`` an integer,
    ``compression_format`` and ``compression_mode`` strings when given, and
    ``topics_with_message_count`` as :func:`_check_topics` says. Anything else raises a
    one-line ValueError ``'bag: <file>: rosbag2_bagfile_information.<field>: <problem>'``
    (never a YAML, Key or Type error). A directory without the file raises ValueError
    ``'bag: <path> has no metadata.yaml ...'`` (naming the storage files it holds, which
    ``ros2 bag reindex`` can describe).
    """
    meta = Path(path) / 'metadata.yaml'
    if not meta.is_file():
        raise ValueError(_no_metadata_problem(path))
    doc = read_yaml(meta, f'bag: {meta}', 'metadata')
    if doc is None:
        raise ValueError(f'bag: {meta}: empty file (not rosbag2 metadata)')
    if not isinstance(doc, dict):
        raise ValueError(f'bag: {meta}: expected a mapping with key {METADATA_KEY}, got '
                         f'{type(doc).__name__} (not rosbag2 metadata)')
    info = doc.get(METADATA_KEY)
    if not isinstance(info, dict):
        problem = ('required key is missing (not rosbag2 metadata)' if info is None
                   else f'expected a mapping, got {type(info).__name__}')
        raise ValueError(f'bag: {meta}: {METADATA_KEY}: {problem}')
    duration = info.get('duration')
    ns = duration.get('nanoseconds') if isinstance(duration, dict) else None
    _check_int(meta, 'duration.nanoseconds', ns, 'an integer (ns)', 0)
    files = info.get('relative_file_paths')
    if not isinstance(files, list) or not all(isinstance(x, str) for x in files):
        raise _metadata_error(meta, 'relative_file_paths', 'required key is missing'
                              if files is None else f'expected a list of file names, got '
                              f'{short_repr(files)}')
    if not files:
        raise _metadata_error(meta, 'relative_file_paths', 'the list is empty: it names no '
                              'storage file, so the bag has no message to read')
    version = _check_int(meta, 'version', info.get('version'), 'an integer', 1)
    if version > BAG_VERSION:
        raise _metadata_error(meta, 'version', f'{version} is newer than the metadata '
                              f'versions this tool reads (1 to {BAG_VERSION})')
    storage = _check_str(meta, 'storage_identifier', info.get('storage_identifier'))
    if storage not in STORAGES:
        raise _metadata_error(meta, 'storage_identifier', f'{storage!r} is not a storage '
                              f'this tool reads ({", ".join(STORAGES)})')
    start = info.get('starting_time')
    _check_int(meta, 'starting_time.nanoseconds_since_epoch',
               start.get('nanoseconds_since_epoch') if isinstance(start, dict) else None,
               'an integer (ns)')
    _check_int(meta, 'message_count', info.get('message_count'), 'a message count', 0)
    for key in ('compression_format', 'compression_mode'):
        _check_str(meta, key, info.get(key), required=False)
    _check_topics(meta, info.get('topics_with_message_count'))
    return info


def _storage_files(path):
    """Names of the storage files (``*.mcap``, ``*.db3``) in directory ``path``, sorted."""
    try:
        return sorted(f.name for f in Path(path).iterdir()
                      if f.suffix in ('.mcap', '.db3') and f.is_file())
    except OSError:
        return []


def _no_metadata_problem(path):
    """The error text of a directory ``path`` without metadata.yaml: a truncated MCAP file
    it holds is named as such (:func:`_truncated_mcap_problem`), other storage files with
    the way to describe them, else it is no bag."""
    try:
        problem = _truncated_mcap_problem(path)
    except OSError:
        problem = None
    if problem:
        return f'bag: cannot open {path}: {problem}'
    files = _storage_files(path)
    if files:
        return (f'bag: {path} has no metadata.yaml (it holds {", ".join(files)}: in a ROS 2 '
                f'install, ros2 bag reindex {path} writes the metadata.yaml that describes '
                'them)')
    return f'bag: {path} has no metadata.yaml (not a rosbag2 directory?)'


class BagReader:
    """Read a rosbag2 bag (either storage, metadata version <= 9) with ``rosbags``.

    ``topics`` maps topic name -> :class:`TopicInfo` (counts as metadata.yaml lists them);
    :meth:`messages` yields :class:`BagMessage` in bag-time order (ties in storage order);
    times are int ns. A malformed directory or ``metadata.yaml`` raises a one-line
    ValueError starting ``bag:`` (:func:`read_metadata`'s checks first), and so do, when
    messages are read (:meth:`messages`), a metadata.yaml that describes a topic otherwise
    than the storage file and a storage file found damaged. After a complete pass,
    :meth:`count_mismatches` names the topics of which fewer (or more) messages were read
    than metadata.yaml lists.
    """

    def __init__(self, path):
        from rosbags.rosbag2 import Reader
        path = Path(path)
        if not path.is_dir():
            raise ValueError(f'bag: {path} is not a directory')
        #: The checked ``rosbag2_bagfile_information`` of metadata.yaml (:func:`read_metadata`).
        self.metadata = read_metadata(path)
        self.files = [Path(f).name for f in self.metadata['relative_file_paths']]
        try:
            self._reader = Reader(path)
        except Exception as exc:  # rosbags raises ReaderError and friends
            raise self._open_error(path, exc) from None
        self.path = path
        #: {topic: messages read} of the current or last :meth:`messages` pass.
        self.read_counts = None
        self._listed = {}
        self._complete = False

    @staticmethod
    def _open_error(path, exc):
        """The one-line ValueError of a bag that cannot be opened: a truncated MCAP file
        named as such (:func:`_truncated_mcap_problem`), else rosbags' reason."""
        try:
            problem = _truncated_mcap_problem(path)
        except OSError:
            problem = None
        return ValueError(f'bag: cannot open {path}: {problem or _one_line(exc)}')

    def open(self):
        """Open the storage file(s)."""
        try:
            self._reader.open()
        except Exception as exc:
            raise self._open_error(self.path, exc) from None
        return self

    def _check_storage_topics(self, conns):
        """ValueError naming the first topic of ``conns`` (metadata.yaml's) with messages
        listed that the storage files do not hold under the same type, serialization
        format, offered QoS and type hash: ``rosbags`` takes a topic's messages only from a
        storage connection that matches it in all of these, so they would be silently left
        out."""
        storages = getattr(self._reader.storage, 'storages', None)
        if not storages:        # (not a directory reader: nothing to compare)
            return
        stored = [c for st in storages for c in st.connections]
        files = ', '.join(self.files)
        for conn in conns:
            if not conn.msgcount:
                continue
            same = [c for c in stored if c.topic == conn.topic]
            if any(c.msgtype == conn.msgtype and c.ext == conn.ext
                   and (not c.digest or not conn.digest or c.digest == conn.digest)
                   for c in same):
                continue
            if not same:
                problem = f'{files} has no topic {conn.topic}'
            else:
                c = same[0]
                for what, mine, theirs in (
                        ('type', conn.msgtype, c.msgtype),
                        ('serialization format', conn.ext.serialization_format,
                         c.ext.serialization_format),
                        ('offered QoS', conn.ext.offered_qos_profiles,
                         c.ext.offered_qos_profiles),
                        ('type hash', conn.digest, c.digest)):
                    if mine != theirs:
                        break
                if what == 'offered QoS':
                    mine, theirs = ('; '.join(map(_qos_text, q)) or 'none'
                                    for q in (mine, theirs))
                problem = (f'topic {conn.topic} has {what} {mine} in metadata.yaml but '
                           f'{theirs} in {files}')
            raise ValueError(
                f'bag: cannot read {self.path}: metadata.yaml does not describe its storage '
                f'file: {problem}, so its {conn.msgcount} messages cannot be read (a '
                'damaged or edited bag: correct metadata.yaml, or in a ROS 2 install '
                'move it away and let ros2 bag reindex write it again)')

    def close(self):
        """Close the storage file(s)."""
        self._reader.close()

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()
        return False

    @property
    def topics(self):
        """Dict topic -> TopicInfo(name, msgtype, count, qos list, type_hash)."""
        out = {}
        for conn in self._reader.connections:
            qos = [_qos_from_rosbags(q) for q in conn.ext.offered_qos_profiles]
            prev = out.get(conn.topic)
            count = conn.msgcount + (prev.count if prev else 0)
            out[conn.topic] = TopicInfo(conn.topic, conn.msgtype, count, qos, conn.digest)
        return out

    @property
    def start_time_ns(self):
        """Bag time of the first message, ns."""
        return int(self._reader.start_time)

    @property
    def end_time_ns(self):
        """Bag time just after the last message, ns (rosbags convention: last + 1)."""
        return int(self._reader.end_time)

    @property
    def message_count(self):
        """Total number of messages."""
        return int(self._reader.message_count)

    def messages(self, topics=None):
        """Yield BagMessage(topic, msgtype, log_time_ns, raw bytes), optionally filtered.

        Counts the messages of each topic in ``read_counts`` (see :meth:`count_mismatches`).
        A topic that metadata.yaml describes otherwise than the storage file raises a
        one-line ValueError before any message (:meth:`_check_storage_topics`). A storage
        file that cannot be read on (rosbags, struct or sqlite errors on a damaged record)
        or a message whose time is not an integer raises a one-line ValueError naming the
        bag, the file and how many messages were read (:meth:`_damaged`).
        """
        conns = [c for c in self._reader.connections if topics is None or c.topic in topics]
        self.read_counts = {c.topic: 0 for c in conns}
        self._complete = False
        self._listed = {}
        for c in conns:
            self._listed[c.topic] = self._listed.get(c.topic, 0) + c.msgcount
        if topics is not None and not conns:
            self._complete = True
            return
        self._check_storage_topics(conns)
        source = self._reader.messages(connections=conns)
        read = self.read_counts
        while True:
            try:
                conn, t, raw = next(source)
            except StopIteration:
                break
            except Exception as exc:  # rosbags, struct, sqlite3... on damaged bytes
                raise self._damaged(f'{_one_line(exc) or type(exc).__name__}') from None
            if type(t) is not int:
                raise self._damaged(f'the time of a {conn.topic} message (sqlite3 column '
                                    f'messages.timestamp) is {short_repr(t)}, not an integer (ns)')
            if not isinstance(raw, (bytes, bytearray, memoryview)):
                raise self._damaged(f'the data of a {conn.topic} message (sqlite3 column '
                                    f'messages.data) is {short_repr(raw)}, not bytes')
            read[conn.topic] += 1
            yield BagMessage(conn.topic, conn.msgtype, t, bytes(raw))
        self._complete = True

    def _damaged(self, reason):
        """The one-line ValueError of a storage file found damaged while reading messages:
        the bag, its file(s), the messages read so far, ``reason`` and what can be done."""
        files = ', '.join(self.files)
        n = sum(self.read_counts.values()) if self.read_counts else 0
        if all(f.endswith('.mcap') for f in self.files):
            name = self.files[0] if len(self.files) == 1 else 'FILE'
            advice = ('copy the records it holds that are intact into a new file with the mcap '
                      f'command line tool (mcap recover {name} -o recovered.mcap, then replace '
                      f'{name} by recovered.mcap), or record again')
        else:
            advice = ("copy what is intact into a new database with the sqlite3 command line "
                      "tool's .recover command, or record again")
        return ValueError(f'bag: cannot read {self.path}: {files} is damaged: reading stopped '
                          f'after {n} of the {sum(self._listed.values())} messages '
                          f'metadata.yaml lists ({reason}); {advice}')

    def count_mismatches(self):
        """[(topic, read, listed)] of the topics of the last complete :meth:`messages` pass
        of which another number of messages was read than metadata.yaml lists (a damaged
        storage file or a metadata.yaml that does not describe it); [] before a complete
        pass."""
        if not self._complete:
            return []
        return [(t, n, self._listed[t]) for t, n in sorted(self.read_counts.items())
                if n != self._listed[t]]


def count_warning(mismatches):
    """One line naming the topics of ``mismatches`` (:meth:`BagReader.count_mismatches`)
    with the messages read and listed, or None when there are none."""
    if not mismatches:
        return None
    return ('messages read differ from the counts metadata.yaml lists (a damaged storage '
            'file, or a metadata.yaml that does not describe it): '
            + ', '.join(f'{t} {n} read of {listed} listed' for t, n, listed in mismatches))


def _qos_text(q):
    """A rosbags QoS profile as reliability/durability/history depth (an error message)."""
    return (f'{q.reliability.name.lower()}, {q.durability.name.lower()}, '
            f'{q.history.name.lower()} {q.depth}')


def station_from_topic(topic, leaf='bearing'):
    """Station id from a bearing topic: '/station_1/bearing' -> 'station_1' (DESIGN.md).

    Returns None when ``topic`` does not end in ``/<leaf>`` or has no namespace.
    """
    parts = topic.strip('/').split('/')
    if len(parts) < 2 or parts[-1] != leaf:
        return None
    return '/'.join(parts[:-1])


def share_type_hash(msgtype, prefix=None):
    """RIHS01 hash rosidl generated for ``msgtype`` in an installed ROS 2 message package.

    Reads ``<prefix>/share/<pkg>/msg/<Type>.json`` (rosidl_generator_type_description output,
    ``type_hashes[0].hash_string``); ``prefix`` defaults to the entries of AMENT_PREFIX_PATH
    and ``sys.prefix``. Returns None when no such file is installed.
    """
    import json
    import sys
    pkg, kind, name = msgtype.split('/')
    prefixes = [prefix] if prefix else (
        [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
        + [sys.prefix])
    for pre in prefixes:
        f = Path(pre) / 'share' / pkg / kind / f'{name}.json'
        if f.is_file():
            with open(f, encoding='utf-8') as fh:
                data = json.load(fh)
            for entry in data.get('type_hashes', []):
                if entry.get('type_name') == msgtype:
                    return entry.get('hash_string')
    return None
