"""The project's MCAP reader and writer helpers (ROS-free: the ``mcap`` package + plain text).

Files written here are what rosbag2 (jazzy, mcap storage) and Foxglove open: profile ``ros2``,
schema name ``pkg/msg/Type``, schema encoding ``ros2msg`` (the .msg text with its dependencies in
sections headed ``MSG: pkg/Type``, as rosbag2 writes them), message encoding ``cdr``, zstd chunks,
a Statistics record and a ``tissue_sim`` metadata record (model, parameters, versions).
Channel and file metadata as rosbag2 Jazzy's MCAP storage plugin writes them: each channel carries
``offered_qos_profiles`` (the YAML list rosbag2 serialises, metadata version 9: policy names, durations
as sec/nsec) and ``topic_type_hash`` (``RIHS01_<sha256>``); each file ends with a ``rosbag2``
metadata record whose ``serialized_metadata`` is the bag's metadata YAML (version 9, per-topic counts,
QoS and hashes, ``ros_distro: jazzy``), which ``ros2 bag info``/``play`` read.

* :func:`schema_text` builds the ros2msg schema of a type from .msg files found under share dirs.
* :class:`McapWriter` writes raw CDR bytes (the recorder and headless runs); it can split files by
  size or duration and flushes whole chunks to disk so a killed writer loses little.
* :func:`iter_messages` / :func:`scan` read a file or a split run folder, including a file cut short
  by ``kill -9``: every complete message is returned (:func:`iter_salvage`: the complete chunks,
  then the cut chunk as far as its compressed stream decodes).
* :class:`Qos`, :func:`qos_yaml`, :func:`type_hash`: the channel metadata; :func:`repair` rewrites a
  file cut short into a complete MCAP (summary, indexes, footer), keeping every complete message.

Times are integer nanoseconds (ROS time of the message: sim time when the recorder follows /clock,
wall time otherwise).
"""
from __future__ import annotations

import dataclasses
import functools
import io
import json
import os
import re
import struct
import sys
import time
from pathlib import Path
from typing import Iterable, Iterator

from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
SEPARATOR = '=' * 80
METADATA_NAME = 'tissue_sim'
ROSBAG2_METADATA_NAME = 'rosbag2'        # rosbag2_storage_mcap: record name, key 'serialized_metadata'
ROSBAG2_METADATA_VERSION = 9             # rosbag2 Jazzy's BagMetadata version
ROS_DISTRO = 'jazzy'                     # the distro the project's interfaces and wheels are built for
MAGIC = b'\x89MCAP0\r\n'

_BUILTIN_TYPES = {
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string', 'wstring',
}

# Used only when no share dir provides them (a headless machine without ROS message packages).
_FALLBACK_DEFINITIONS = {
    'std_msgs/Header': ('# Standard metadata for higher-level stamped data types.\n'
                        'builtin_interfaces/Time stamp\n'
                        'string frame_id\n'),
    'builtin_interfaces/Time': 'int32 sec\nuint32 nanosec\n',
    'builtin_interfaces/Duration': 'int32 sec\nuint32 nanosec\n',
}


class McapIOError(ValueError):
    """A schema that cannot be built or a file that cannot be read (message names the problem)."""


# ------------------------------------------------------------------------------------- schemas
def normalise_type(type_name: str) -> tuple[str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type')."""
    parts = type_name.strip().split('/')
    if len(parts) == 3 and parts[1] == 'msg':
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise McapIOError(f'bad message type name {type_name!r} (expected pkg/msg/Type)')


def default_share_dirs() -> list[Path]:
    """Directories holding ``<pkg>/msg/<Type>.msg``: AMENT_PREFIX_PATH shares, this interpreter's
    prefix share (PyPI ROS wheels), and the source tree's src/ (tissue_msgs before a build)."""
    dirs = []
    for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if p:
            dirs.append(Path(p) / 'share')
    dirs.append(Path(sys.prefix) / 'share')
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / 'tissue_msgs' / 'msg').is_dir():
            dirs.append(parent)
            break
    out, seen = [], set()
    for d in dirs:
        if d not in seen and d.is_dir():
            seen.add(d)
            out.append(d)
    return out


def _find_msg(pkg: str, name: str, share_dirs: Iterable) -> str | None:
    for d in share_dirs:
        f = Path(d) / pkg / 'msg' / f'{name}.msg'
        if f.is_file():
            return f.read_text(encoding='utf-8')
    return _FALLBACK_DEFINITIONS.get(f'{pkg}/{name}')


_FIELD_RE = re.compile(r'^\s*([A-Za-z][\w/]*)(?:<=\d+)?(\[[^\]]*\])?\s+([A-Za-z]\w*)(.*)$')


def _dependencies(pkg: str, text: str) -> list[str]:
    """Complex field types used by a .msg text, as 'pkg/Type', in order of first use."""
    deps = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        m = _FIELD_RE.match(line)
        if not m:
            continue
        base, rest = m.group(1), m.group(4).strip()
        if rest.startswith('=') and base in _BUILTIN_TYPES:     # constant
            continue
        if base in _BUILTIN_TYPES:
            continue
        if '/' in base:
            dpkg, dname = normalise_type(base)
        elif base == 'Header':
            dpkg, dname = 'std_msgs', 'Header'
        else:
            dpkg, dname = pkg, base
        dep = f'{dpkg}/{dname}'
        if dep not in deps:
            deps.append(dep)
    return deps


def schema_text(type_name: str, share_dirs: Iterable | None = None) -> str:
    """The ros2msg schema of ``type_name`` ('pkg/msg/Type') as rosbag2 writes it: the type's .msg
    text, then each dependency (depth first, once) after a line of 80 '=' and ``MSG: pkg/Type``."""
    share_dirs = list(default_share_dirs() if share_dirs is None else share_dirs)
    pkg, name = normalise_type(type_name)
    top = _find_msg(pkg, name, share_dirs)
    if top is None:
        raise McapIOError(f'no definition of {pkg}/msg/{name} (looked for {pkg}/msg/{name}.msg under: '
                          f'{", ".join(map(str, share_dirs)) or "no share dirs"})')
    parts = [top.rstrip('\n')]
    done = {f'{pkg}/{name}'}
    stack = list(reversed(_dependencies(pkg, top)))
    while stack:
        dep = stack.pop()
        if dep in done:
            continue
        done.add(dep)
        dpkg, dname = dep.split('/')
        text = _find_msg(dpkg, dname, share_dirs)
        if text is None:
            raise McapIOError(f'{type_name}: no definition of dependency {dpkg}/msg/{dname}')
        parts.append(f'{SEPARATOR}\nMSG: {dep}\n{text.rstrip(chr(10))}')
        stack.extend(reversed([d for d in _dependencies(dpkg, text) if d not in done]))
    return '\n'.join(parts) + '\n'


def full_type_name(type_name: str) -> str:
    pkg, name = normalise_type(type_name)
    return f'{pkg}/msg/{name}'


# ------------------------------------------------------------------------ channel metadata (rosbag2)
INFINITE_SEC, INFINITE_NSEC = 9223372036, 854775807      # RMW_DURATION_INFINITE as rosbag2 writes it
_POLICIES = {
    'history': ('keep_last', 'keep_all', 'system_default', 'unknown'),
    'reliability': ('reliable', 'best_effort', 'system_default', 'best_available', 'unknown'),
    'durability': ('volatile', 'transient_local', 'system_default', 'best_available', 'unknown'),
    'liveliness': ('automatic', 'manual_by_topic', 'system_default', 'best_available', 'unknown'),
}


@dataclasses.dataclass(frozen=True)
class Qos:
    """A publisher's offered QoS profile, as rosbag2 stores it in ``offered_qos_profiles``.

    Policies by their rmw names (``reliable``/``best_effort``, ``volatile``/``transient_local``,
    ``keep_last``/``keep_all``, ``automatic``/``manual_by_topic``). Durations in ns; None (or 0, the
    rmw 'default') is written as rmw's infinite duration, which is what DDS offers for an unset
    deadline, lifespan or lease (and what rosbag2 records from discovery)."""
    reliability: str = 'reliable'
    durability: str = 'volatile'
    history: str = 'keep_last'
    depth: int = 10
    deadline_ns: int | None = None
    lifespan_ns: int | None = None
    liveliness: str = 'automatic'
    liveliness_lease_ns: int | None = None
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self):
        for k, allowed in _POLICIES.items():
            if getattr(self, k) not in allowed:
                raise McapIOError(f'QoS {k} {getattr(self, k)!r}: expected one of {", ".join(allowed)}')
        if int(self.depth) < 0:
            raise McapIOError(f'QoS depth {self.depth} < 0')

    @classmethod
    def from_profile(cls, p) -> 'Qos':
        """From an ``rclpy.qos.QoSProfile`` (or a ``TopicEndpointInfo.qos_profile``), duck-typed so
        that this module needs no rclpy: the recorder passes what the publishers offer. A
        ``system_default`` policy is written as what DDS offers for it (reliable, volatile,
        keep_last, automatic), as rosbag2 records it from discovery."""
        def name(v, dds_default):
            n = str(getattr(v, 'name', v)).lower()
            return dds_default if n == 'system_default' else n

        def ns(d):
            n = int(getattr(d, 'nanoseconds', d) or 0)
            return None if n <= 0 or n >= INFINITE_SEC * 10**9 + INFINITE_NSEC else n

        return cls(reliability=name(p.reliability, 'reliable'), durability=name(p.durability, 'volatile'),
                   history=name(p.history, 'keep_last'), depth=int(p.depth), deadline_ns=ns(p.deadline),
                   lifespan_ns=ns(p.lifespan), liveliness=name(p.liveliness, 'automatic'),
                   liveliness_lease_ns=ns(p.liveliness_lease_duration),
                   avoid_ros_namespace_conventions=bool(p.avoid_ros_namespace_conventions))

    def as_dict(self) -> dict:
        """The mapping rosbag2 (metadata version 9) writes for one profile, keys in its order."""
        def t(n):
            return ({'sec': INFINITE_SEC, 'nsec': INFINITE_NSEC} if not n
                    else {'sec': int(n) // 10**9, 'nsec': int(n) % 10**9})
        return {'history': self.history, 'depth': int(self.depth), 'reliability': self.reliability,
                'durability': self.durability, 'deadline': t(self.deadline_ns), 'lifespan': t(self.lifespan_ns),
                'liveliness': self.liveliness, 'liveliness_lease_duration': t(self.liveliness_lease_ns),
                'avoid_ros_namespace_conventions': bool(self.avoid_ros_namespace_conventions)}

    @classmethod
    def from_dict(cls, d: dict) -> 'Qos':
        def ns(t):
            n = int(t['sec']) * 10**9 + int(t['nsec'])
            return None if n <= 0 or (int(t['sec']), int(t['nsec'])) == (INFINITE_SEC, INFINITE_NSEC) else n
        return cls(reliability=str(d['reliability']), durability=str(d['durability']), history=str(d['history']),
                   depth=int(d['depth']), deadline_ns=ns(d['deadline']), lifespan_ns=ns(d['lifespan']),
                   liveliness=str(d['liveliness']), liveliness_lease_ns=ns(d['liveliness_lease_duration']),
                   avoid_ros_namespace_conventions=bool(d['avoid_ros_namespace_conventions']))

    def short(self) -> str:
        """One-line summary (``tissue-sim info``)."""
        h = f'{self.history} {self.depth}' if self.history == 'keep_last' else self.history
        extra = ''.join(f', {k} {v / 1e9:g} s' for k, v in (('deadline', self.deadline_ns),
                        ('lifespan', self.lifespan_ns)) if v)
        return f'{self.reliability}, {self.durability}, {h}{extra}'


QOS_LATCHED = Qos(durability='transient_local', depth=1)   # late joiners get the last message (topology)


def qos_stream(depth: int = 10) -> Qos:
    """Reliable, volatile, keep last ``depth``: the per-frame topics."""
    return Qos(depth=depth)


def _qos_list(qos) -> list:
    if qos is None:
        return []
    if isinstance(qos, (Qos,)) or hasattr(qos, 'reliability'):
        qos = [qos]
    return [q if isinstance(q, Qos) else Qos.from_profile(q) for q in qos]


def qos_yaml(qos) -> str:
    """``offered_qos_profiles`` as rosbag2 Jazzy writes it into a channel's metadata: the YAML
    block sequence yaml-cpp emits for its list of profiles (``[]`` when none)."""
    profiles = _qos_list(qos)
    if not profiles:
        return '[]'
    lines = []
    for q in profiles:
        first = True
        for k, v in q.as_dict().items():
            lead = '- ' if first else '  '
            first = False
            if isinstance(v, dict):
                lines.append(f'{lead}{k}:')
                lines += [f'    {kk}: {vv}' for kk, vv in v.items()]
            else:
                lines.append(f'{lead}{k}: {str(v).lower() if isinstance(v, bool) else v}')
    return '\n'.join(lines)


def parse_qos_yaml(text: str) -> list:
    """The profiles of an ``offered_qos_profiles`` value (version 9 form) as :class:`Qos`."""
    import yaml
    if not text:
        return []
    try:
        data = yaml.safe_load(text) or []
        return [Qos.from_dict(d) for d in data]
    except Exception as e:
        raise McapIOError(f'bad offered_qos_profiles ({type(e).__name__}: {e})') from None


@functools.lru_cache(maxsize=None)
def _hash_from_share(pkg: str, name: str, dirs: tuple) -> str:
    full = f'{pkg}/msg/{name}'
    for d in dirs:
        f = Path(d) / pkg / 'msg' / f'{name}.json'
        if f.is_file():
            try:
                for h in json.loads(f.read_text(encoding='utf-8')).get('type_hashes', []):
                    if h.get('type_name') == full and str(h.get('hash_string', '')).startswith('RIHS01_'):
                        return h['hash_string']
            except (OSError, ValueError):
                continue
    return ''


def compute_type_hash(type_name: str, schema: str) -> str:
    """RIHS01 hash of a type computed from its ros2msg schema text (rosbags' implementation of the
    ROS 2 type-description hash, REP-2011); '' when rosbags is not installed."""
    try:
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    except ImportError:                                              # pragma: no cover
        return ''
    ts = get_typestore(Stores.EMPTY)
    try:
        ts.register(get_types_from_msg(schema, full_type_name(type_name)))
        return ts.hash_rihs01(full_type_name(type_name))
    except Exception as e:
        raise McapIOError(f'{type_name}: cannot compute its type hash from the schema ({e})') from None


def type_hash(type_name: str, schema: str | None = None, share_dirs: Iterable | None = None) -> str:
    """The type's RIHS01 hash (``topic_type_hash``): from the built interface package
    (``share/<pkg>/msg/<Type>.json``, ``type_hashes``, found through AMENT_PREFIX_PATH and this
    interpreter's share), else computed from ``schema`` (default: :func:`schema_text`)."""
    pkg, name = normalise_type(type_name)
    dirs = tuple(str(d) for d in (default_share_dirs() if share_dirs is None else share_dirs))
    h = _hash_from_share(pkg, name, dirs)
    if h:
        return h
    return compute_type_hash(type_name, schema if schema is not None else schema_text(type_name, share_dirs))


def bag_metadata_yaml(file_name: str, topics: list, ros_distro: str | None = None) -> str:
    """``serialized_metadata`` of the ``rosbag2`` metadata record of one file: rosbag2 Jazzy's
    BagMetadata (version 9). ``topics``: [(name, type, channel metadata dict, count, first_ns,
    last_ns)]. ``ros_distro`` defaults, as in rosbag2, to $ROS_DISTRO, else 'jazzy' (the pip set-up
    sets none; its wheels are Jazzy's)."""
    import yaml
    ros_distro = ros_distro or os.environ.get('ROS_DISTRO') or ROS_DISTRO
    starts = [t[4] for t in topics if t[3]]
    ends = [t[5] for t in topics if t[3]]
    start = min(starts) if starts else 0
    duration = (max(ends) - start) if ends else 0
    count = sum(int(t[3]) for t in topics)
    twmc = []
    for name, typ, meta, n, _, _ in topics:
        q = parse_qos_yaml(meta.get('offered_qos_profiles', ''))
        twmc.append({'topic_metadata': {'name': name, 'type': typ, 'serialization_format': MESSAGE_ENCODING,
                                        'offered_qos_profiles': [p.as_dict() for p in q],
                                        'type_description_hash': meta.get('topic_type_hash', '')},
                     'message_count': int(n)})
    doc = {'version': ROSBAG2_METADATA_VERSION, 'storage_identifier': 'mcap',
           'duration': {'nanoseconds': int(duration)}, 'starting_time': {'nanoseconds_since_epoch': int(start)},
           'message_count': count, 'topics_with_message_count': twmc, 'compression_format': '',
           'compression_mode': '', 'relative_file_paths': [file_name],
           'files': [{'path': file_name, 'starting_time': {'nanoseconds_since_epoch': int(start)},
                      'duration': {'nanoseconds': int(duration)}, 'message_count': count}],
           'custom_data': {}, 'ros_distro': ros_distro}
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)


# ------------------------------------------------------------------------------------- writer
def versions() -> dict:
    """Versions worth recording with a run."""
    out = {'python': sys.version.split()[0]}
    for mod in ('tissue_sim', 'numpy', 'numba', 'mcap'):
        try:
            m = __import__(mod)
            out[mod] = getattr(m, '__version__', 'unknown')
        except Exception:                                          # pragma: no cover
            pass
    out['ros_distro'] = os.environ.get('ROS_DISTRO') or ROS_DISTRO
    return out


class McapWriter:
    """Writes raw CDR messages to MCAP (ros2 profile), optionally split by size / duration.

    ``path``: the output file. With ``split_bytes`` or ``split_seconds`` > 0 the files are
    ``<stem>_0.mcap``, ``<stem>_1.mcap``, ... next to ``path`` (rosbag2's naming); each file has
    its own schemas, channels and metadata, so each opens on its own.
    ``chunk_size`` [bytes] bounds a chunk; ``flush_seconds`` closes the chunk in progress and
    flushes the file at least that often (a writer killed with SIGKILL loses at most that much).
    """

    def __init__(self, path, *, chunk_size: int = 1 << 20, compression: str = 'zstd',
                 split_bytes: int = 0, split_seconds: float = 0.0, flush_seconds: float = 1.0,
                 metadata: dict | None = None, share_dirs=None):
        self.path = Path(path)
        self.chunk_size = int(chunk_size)
        self.compression = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
                            'none': CompressionType.NONE, '': CompressionType.NONE}[compression]
        self.split_bytes = int(split_bytes)
        self.split_ns = int(split_seconds * 1e9)
        self.flush_seconds = float(flush_seconds)
        self.metadata = {k: (v if isinstance(v, str) else json.dumps(v)) for k, v in (metadata or {}).items()}
        self.share_dirs = share_dirs
        self._channels = {}          # topic -> (type_name, schema text)
        self._ids = {}               # topic -> channel id in the current file
        self._file = None
        self._writer = None
        self._index = 0
        self._first_ns = None
        self._last_flush = time.monotonic()
        self.files: list[Path] = []
        self.message_count = 0
        self._split = self.split_bytes > 0 or self.split_ns > 0
        self._extra_meta = {}
        self._stats = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)

    # -- channels
    def add_channel(self, topic: str, type_name: str, schema: str | None = None, qos=None,
                    type_hash: str | None = None) -> None:
        """Declare a topic; ``schema`` defaults to :func:`schema_text` of the type.

        ``qos``: what the topic's publisher(s) offer (a :class:`Qos`, an rclpy QoSProfile, or a
        list of them), written as the channel's ``offered_qos_profiles`` (``ros2 bag play`` offers
        the same again: a transient-local topic replays latched). ``type_hash``: RIHS01 hash,
        default :func:`type_hash` of the type."""
        if topic in self._channels:
            return
        type_name = full_type_name(type_name)
        if schema is None:
            schema = schema_text(type_name, self.share_dirs)
        if type_hash is None:
            type_hash = globals()['type_hash'](type_name, schema, self.share_dirs)
        meta = {'offered_qos_profiles': qos_yaml(qos), 'topic_type_hash': type_hash}
        self._channels[topic] = (type_name, schema, meta)
        if self._writer is not None:
            self._register(topic)

    def _register(self, topic):
        type_name, schema, meta = self._channels[topic]
        sid = self._writer.register_schema(type_name, SCHEMA_ENCODING, schema.encode())
        self._ids[topic] = self._writer.register_channel(topic, MESSAGE_ENCODING, sid, meta)

    def _current_path(self) -> Path:
        if not self._split:
            return self.path
        stem = self.path.name[:-5] if self.path.name.endswith('.mcap') else self.path.name
        return self.path.with_name(f'{stem}_{self._index}.mcap')

    def _open(self):
        p = self._current_path()
        self._file = open(p, 'wb')
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=self.compression)
        self._writer.start(profile=PROFILE, library='tissue_sim')
        self._ids = {}
        self._stats = {}             # topic -> [count, first log time, last log time] in this file
        for topic in self._channels:
            self._register(topic)
        if self.metadata:
            self._writer.add_metadata(METADATA_NAME, self.metadata)
        for name, data in self._extra_meta.items():
            self._writer.add_metadata(name, data)
        self._writer.flush()
        self._file.flush()
        self.files.append(p)

    def _close_file(self):
        if self._writer is not None:
            # what rosbag2 writes when it closes a file: the bag metadata (ros_distro, QoS, hashes)
            topics = [(t, self._channels[t][0], self._channels[t][2], *self._stats.get(t, (0, 0, 0)))
                      for t in self._channels]
            self._writer.add_metadata(ROSBAG2_METADATA_NAME, {
                'serialized_metadata': bag_metadata_yaml(self.files[-1].name, topics)})
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            self._writer = None
            self._file = None

    def add_metadata(self, name: str, data: dict) -> None:
        """A further metadata record (written now and into every later split file)."""
        data = {k: (v if isinstance(v, str) else json.dumps(v)) for k, v in data.items()}
        self._extra_meta[name] = data
        if self._writer is not None:
            self._writer.add_metadata(name, data)

    # -- data
    def write(self, topic: str, data, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one message (``data``: CDR bytes exactly as received or encoded)."""
        if topic not in self._channels:
            raise McapIOError(f'topic {topic!r} was not declared with add_channel')
        if self._writer is None:
            self._open()
            self._first_ns = log_time_ns
        elif self._split and ((self.split_ns and log_time_ns - self._first_ns >= self.split_ns)
                              or (self.split_bytes and self._file.tell() >= self.split_bytes)):
            self._close_file()
            self._index += 1
            self._open()
            self._first_ns = log_time_ns
        self._writer.add_message(self._ids[topic], log_time=int(log_time_ns), data=bytes(data),
                                 publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns))
        self.message_count += 1
        st = self._stats.get(topic)
        if st is None:
            self._stats[topic] = [1, int(log_time_ns), int(log_time_ns)]
        else:
            st[0] += 1
            st[1] = min(st[1], int(log_time_ns))
            st[2] = max(st[2], int(log_time_ns))
        now = time.monotonic()
        if self.flush_seconds >= 0 and now - self._last_flush >= self.flush_seconds:
            self.flush()
        else:
            self._file.flush()     # whatever complete chunk the Writer emitted reaches the OS now

    def flush(self):
        """Close the chunk in progress and push it to the OS (survives the process being killed)."""
        self._last_flush = time.monotonic()
        if self._writer is not None:
            self._writer.flush()

    def close(self):
        """Finish the file (summary, statistics, footer). Writes an empty file if nothing came."""
        if self._writer is None and not self.files:
            self._open()
        self._close_file()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ------------------------------------------------------------------------------------- reader
@dataclasses.dataclass(frozen=True)
class RawMessage:
    topic: str
    schema_name: str        # 'pkg/msg/Type'
    log_time: int           # [ns]
    publish_time: int       # [ns]
    data: bytes             # CDR, with its 4-byte encapsulation header


@dataclasses.dataclass
class McapSummary:
    files: list
    topics: dict            # topic -> schema name
    schemas: dict           # schema name -> schema text
    counts: dict            # topic -> messages read
    metadata: dict          # record name -> {key: value}
    start_ns: int | None
    end_ns: int | None
    truncated: bool         # a file ended before its footer (writer killed): every complete message read
    channel_metadata: dict = dataclasses.field(default_factory=dict)   # topic -> {key: value}
    topic_times: dict = dataclasses.field(default_factory=dict)        # topic -> (first, last) [ns]


def mcap_files(path) -> list[Path]:
    """A .mcap file, or the .mcap files of a folder in split order (``x_0``, ``x_1``, ... ``x_10``)."""
    p = Path(path)
    if p.is_file():
        return [p]
    if p.is_dir():
        def key(f):
            m = re.search(r'_(\d+)\.mcap$', f.name)
            return (f.name[:m.start()] if m else f.name[:-5], int(m.group(1)) if m else -1)
        files = sorted(p.glob('*.mcap'), key=key)
        if files:
            return files
        raise McapIOError(f'{p}: no .mcap files in this folder')
    raise McapIOError(f'{p}: no such file or folder')


def _iter(path, topics, state) -> Iterator[RawMessage]:
    want = None if topics is None else set(topics)
    for f in mcap_files(path):
        schemas, channels = {}, {}
        info = {}
        for rec in iter_salvage(f, info):   # a file cut short: every complete message, the cut chunk's too
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                state.setdefault('schemas', {})[rec.name] = rec.data.decode('utf-8', 'replace')
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
                s = schemas.get(rec.schema_id)
                state.setdefault('topics', {})[rec.topic] = s.name if s else ''
                state.setdefault('channel_metadata', {})[rec.topic] = dict(rec.metadata)
            elif isinstance(rec, Metadata):
                state.setdefault('metadata', {}).setdefault(rec.name, {}).update(rec.metadata)
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None or (want is not None and ch.topic not in want):
                    continue
                s = schemas.get(ch.schema_id)
                yield RawMessage(ch.topic, s.name if s else '', rec.log_time, rec.publish_time, rec.data)
        if not info.get('complete') or info.get('damaged'):
            state['truncated'] = True


def iter_messages(path, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
    """Messages of a file (or split folder) in file order (the recorder writes them in arrival
    order). A file cut short (writer killed) yields every complete message (:func:`iter_salvage`)."""
    yield from _iter(path, topics, {})


def scan(path) -> McapSummary:
    """Read through a file or split folder: topics, schemas, counts, metadata, time span."""
    state = {}
    counts, times = {}, {}
    files = mcap_files(path)
    for m in _iter(path, None, state):
        counts[m.topic] = counts.get(m.topic, 0) + 1
        t = times.get(m.topic)
        times[m.topic] = (m.log_time, m.log_time) if t is None else (min(t[0], m.log_time), max(t[1], m.log_time))
    start = min((t[0] for t in times.values()), default=None)
    end = max((t[1] for t in times.values()), default=None)
    return McapSummary(files=files, topics=state.get('topics', {}), schemas=state.get('schemas', {}),
                       counts=counts, metadata=state.get('metadata', {}), start_ns=start, end_ns=end,
                       truncated=bool(state.get('truncated')), channel_metadata=state.get('channel_metadata', {}),
                       topic_times=times)



# ------------------------------------------------------------------------------------- repair
_OP_HEADER, _OP_FOOTER, _OP_CHUNK, _OP_DATA_END = 0x01, 0x02, 0x06, 0x0F


@dataclasses.dataclass
class RepairReport:
    source: Path
    output: Path | None
    complete: bool          # the input already had its footer (nothing was cut)
    messages: int           # messages written to the output
    counts: dict            # topic -> messages
    start_ns: int | None
    end_ns: int | None
    size_in: int            # [bytes]
    used_bytes: int         # bytes of the input up to the end of the last whole record
    from_cut_chunk: int     # messages recovered from the chunk the cut went through (after used_bytes)


def _parse(raw: bytes) -> list:
    """Records of a byte string of whole MCAP records (no magic); a chunk expands into its records."""
    from mcap.exceptions import EndOfFile
    out = []
    it = StreamReader(io.BytesIO(raw), skip_magic=True, record_size_limit=None).records
    try:
        for rec in it:
            out.append(rec)
    except EndOfFile:                       # the stream reader's way of saying the bytes are used up
        pass
    return out


def _whole_records_end(buf) -> int:
    """End offset of the complete records at the start of ``buf`` (records without magic)."""
    pos, n = 0, len(buf)
    while pos + 9 <= n:
        end = pos + 9 + struct.unpack_from('<Q', buf, pos + 1)[0]
        if end > n:
            break
        pos = end
    return pos


def _cut_chunk_records(body) -> list:
    """The complete records in a chunk whose bytes were cut short: decompress what is there
    (zstd and lz4 decompress as a stream) and keep the records that are whole."""
    try:
        off = 8 + 8 + 8 + 4
        clen = struct.unpack_from('<I', body, off)[0]
        compression = bytes(body[off + 4:off + 4 + clen]).decode()
        off += 4 + clen + 8
        data = bytes(body[off:])
        if compression == 'zstd':
            import zstandard
            raw = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif compression == 'lz4':
            import lz4.frame
            raw = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif compression == '':
            raw = data
        else:
            return []
    except Exception:
        return []
    end = _whole_records_end(raw)
    try:
        return _parse(raw[:end]) if end else []
    except Exception:
        return []


def is_complete(path) -> bool:
    """True when an MCAP file ends with its footer record and magic (what readers that seek to
    the summary need); False for a file cut short."""
    path = Path(path)
    size = path.stat().st_size
    if size < 8 + 37:
        return False
    with open(path, 'rb') as f:
        f.seek(size - 37)
        tail = f.read(37)
    return tail[0] == _OP_FOOTER and struct.unpack_from('<Q', tail, 1)[0] == 20 and tail[29:] == MAGIC


def iter_salvage(path, info: dict | None = None) -> Iterator:
    """Every record of an MCAP file that survived a cut, in file order: the header, schemas,
    channels, metadata and every complete message, including the complete messages of a chunk the
    cut went through (its zstd/lz4 stream is decoded as far as it goes). Stops at the data end (the
    summary is not needed). ``info`` (a dict) receives complete (footer found), used_bytes (end of
    the last whole record), size, from_cut_chunk and, when a whole record could not be parsed
    (reading stops there), damaged. Raises McapIOError if the file is not an MCAP file."""
    import mmap
    path = Path(path)
    info = {} if info is None else info
    if not path.is_file():
        raise McapIOError(f'{path}: no such file')
    size = path.stat().st_size
    info.update(complete=False, size=size, used_bytes=8, from_cut_chunk=0)
    with open(path, 'rb') as f:
        if f.read(8) != MAGIC:
            raise McapIOError(f'{path}: not an MCAP file')
        if size < 8 + 9 or f.read(1) != bytes([_OP_HEADER]):
            raise McapIOError(f'{path}: no complete MCAP record after the magic')
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            pos = 8
            while pos + 9 <= size:
                op = buf[pos]
                length = struct.unpack_from('<Q', buf, pos + 1)[0]
                end = pos + 9 + length
                if end > size:
                    if pos == 8:
                        raise McapIOError(f'{path}: no complete MCAP record after the magic')
                    if op == _OP_CHUNK:
                        recs = _cut_chunk_records(memoryview(buf)[pos + 9:size])
                        info['from_cut_chunk'] = sum(isinstance(r, Message) for r in recs)
                        yield from recs
                    break
                if op in (_OP_FOOTER, _OP_DATA_END):
                    info['used_bytes'] = end
                    break
                try:
                    recs = _parse(buf[pos:end])
                except Exception as e:
                    if pos == 8:
                        raise McapIOError(f'{path}: unreadable header record ({type(e).__name__} {e})') from None
                    info['damaged'] = f'{type(e).__name__} {e} at byte {pos}'
                    break                                  # a damaged record: keep what came before
                info['used_bytes'] = end
                pos = end
                yield from recs
        finally:
            buf.close()
    info['complete'] = is_complete(path)


def repair(src, dst) -> RepairReport:
    """Rewrite the MCAP file ``src`` (typically cut short by a killed writer: no summary, no
    footer, the last chunk possibly cut) into a complete MCAP ``dst`` with zstd chunks, message
    indexes, summary, statistics and footer, keeping every complete message (those of the cut
    chunk included, :func:`iter_salvage`) in file order, the schemas, channels (their rosbag2
    metadata; a missing ``topic_type_hash`` is computed from the schema) and metadata records; the
    ``rosbag2`` record is written anew from the messages kept. ``dst`` must differ from ``src``.
    Raises McapIOError when nothing after the header survived (``dst`` is then left incomplete:
    write to a temporary name)."""
    src, dst = Path(src), Path(dst)
    if dst.resolve() == src.resolve():
        raise McapIOError(f'{dst}: the output must not be the input (write elsewhere, then rename)')
    info = {}
    records = iter_salvage(src, info)
    header = next(records)
    counts, times = {}, {}
    schemas, chan_ids, chan_info = {}, {}, {}
    with open(dst, 'wb') as f:
        w = Writer(f, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        w.start(profile=header.profile, library=header.library or 'tissue_sim')
        n_records = 0
        for rec in records:
            n_records += 1
            if isinstance(rec, Schema):
                if rec.id not in schemas:
                    schemas[rec.id] = (w.register_schema(rec.name, rec.encoding, rec.data), rec)
            elif isinstance(rec, Channel):
                if rec.id in chan_ids:
                    continue
                sid, srec = schemas.get(rec.schema_id, (0, None))
                meta = dict(rec.metadata)
                if srec is not None and srec.encoding == SCHEMA_ENCODING and not meta.get('topic_type_hash'):
                    try:
                        meta['topic_type_hash'] = compute_type_hash(srec.name, srec.data.decode())
                    except McapIOError:
                        pass
                chan_ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding, sid, meta)
                chan_info[rec.id] = (rec.topic, srec.name if srec else '', meta)
            elif isinstance(rec, Metadata):
                if rec.name != ROSBAG2_METADATA_NAME:
                    w.add_metadata(rec.name, dict(rec.metadata))
            elif isinstance(rec, Message):
                cid = chan_ids.get(rec.channel_id)
                if cid is None:
                    continue                               # a message before its channel: unusable
                w.add_message(cid, log_time=rec.log_time, data=rec.data, publish_time=rec.publish_time,
                              sequence=rec.sequence)
                topic = chan_info[rec.channel_id][0]
                counts[topic] = counts.get(topic, 0) + 1
                t = times.get(topic)
                times[topic] = (rec.log_time, rec.log_time) if t is None else (min(t[0], rec.log_time),
                                                                               max(t[1], rec.log_time))
        if not n_records:
            raise McapIOError(f'{src}: nothing after the MCAP header survived: nothing to recover')
        topics = [(topic, typ, meta, counts.get(topic, 0), *times.get(topic, (0, 0)))
                  for topic, typ, meta in chan_info.values()]
        w.add_metadata(ROSBAG2_METADATA_NAME, {'serialized_metadata': bag_metadata_yaml(dst.name, topics)})
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    return RepairReport(source=src, output=dst, complete=info['complete'], messages=sum(counts.values()),
                        counts=counts, start_ns=min((t[0] for t in times.values()), default=None),
                        end_ns=max((t[1] for t in times.values()), default=None), size_in=info['size'],
                        used_bytes=info['used_bytes'], from_cut_chunk=info['from_cut_chunk'])
