"""The project's MCAP reader and writer helpers (ROS-free: the ``mcap`` package + plain text).

Files written here are what rosbag2 (jazzy, mcap storage) and Foxglove open: profile ``ros2``,
schema name ``pkg/msg/Type``, schema encoding ``ros2msg`` (the .msg text with its dependencies in
sections headed ``MSG: pkg/Type``, as rosbag2 writes them), message encoding ``cdr``, zstd chunks,
a Statistics record and a ``tissue_sim`` metadata record (model, parameters, versions).

* :func:`schema_text` builds the ros2msg schema of a type from .msg files found under share dirs.
* :class:`McapWriter` writes raw CDR bytes (the recorder and headless runs); it can split files by
  size or duration and flushes whole chunks to disk so a killed writer loses little.
* :func:`iter_messages` / :func:`scan` read a file or a split run folder, including a file cut short
  by ``kill -9``: everything up to the last complete chunk is returned.

Times are integer nanoseconds (ROS time of the message: sim time when the recorder follows /clock,
wall time otherwise).
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import struct
import sys
import time
from pathlib import Path
from typing import Iterable, Iterator

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
SEPARATOR = '=' * 80
METADATA_NAME = 'tissue_sim'

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
    out['ros_distro'] = os.environ.get('ROS_DISTRO', '')
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
        self.path.parent.mkdir(parents=True, exist_ok=True)

    # -- channels
    def add_channel(self, topic: str, type_name: str, schema: str | None = None) -> None:
        """Declare a topic; ``schema`` defaults to :func:`schema_text` of the type."""
        if topic in self._channels:
            return
        type_name = full_type_name(type_name)
        if schema is None:
            schema = schema_text(type_name, self.share_dirs)
        self._channels[topic] = (type_name, schema)
        if self._writer is not None:
            self._register(topic)

    def _register(self, topic):
        type_name, schema = self._channels[topic]
        sid = self._writer.register_schema(type_name, SCHEMA_ENCODING, schema.encode())
        self._ids[topic] = self._writer.register_channel(topic, MESSAGE_ENCODING, sid, {})

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
    truncated: bool         # a file ended before its footer (writer killed): read up to last chunk


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


def _records(path: Path, state: dict) -> Iterator:
    """Records of one file; stops quietly at a cut-off tail (sets state['truncated'])."""
    with open(path, 'rb') as f:
        head = f.read(8)
        if head != b'\x89MCAP0\r\n':
            raise McapIOError(f'{path}: not an MCAP file')
        f.seek(0)
        it = StreamReader(f, record_size_limit=1 << 32).records
        while True:
            try:
                rec = next(it)
            except StopIteration:
                return
            except (McapError, struct.error, EOFError, ValueError, MemoryError) as e:
                state['truncated'] = True
                state.setdefault('errors', []).append(f'{path.name}: {type(e).__name__} {e}'.strip())
                return
            except Exception as e:     # zstd errors on a cut chunk have their own classes
                if type(e).__module__.startswith('zstandard'):
                    state['truncated'] = True
                    return
                raise
            yield rec


def _iter(path, topics, state) -> Iterator[RawMessage]:
    want = None if topics is None else set(topics)
    for f in mcap_files(path):
        schemas, channels = {}, {}
        for rec in _records(f, state):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
                state.setdefault('schemas', {})[rec.name] = rec.data.decode('utf-8', 'replace')
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
                s = schemas.get(rec.schema_id)
                state.setdefault('topics', {})[rec.topic] = s.name if s else ''
            elif isinstance(rec, Metadata):
                state.setdefault('metadata', {}).setdefault(rec.name, {}).update(rec.metadata)
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None or (want is not None and ch.topic not in want):
                    continue
                s = schemas.get(ch.schema_id)
                yield RawMessage(ch.topic, s.name if s else '', rec.log_time, rec.publish_time, rec.data)


def iter_messages(path, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
    """Messages of a file (or split folder) in file order (the recorder writes them in arrival
    order). A file cut short (writer killed) yields everything up to its last complete chunk."""
    yield from _iter(path, topics, {})


def scan(path) -> McapSummary:
    """Read through a file or split folder: topics, schemas, counts, metadata, time span."""
    state = {}
    counts, start, end = {}, None, None
    files = mcap_files(path)
    for m in _iter(path, None, state):
        counts[m.topic] = counts.get(m.topic, 0) + 1
        start = m.log_time if start is None else min(start, m.log_time)
        end = m.log_time if end is None else max(end, m.log_time)
    return McapSummary(files=files, topics=state.get('topics', {}), schemas=state.get('schemas', {}),
                       counts=counts, metadata=state.get('metadata', {}), start_ns=start, end_ns=end,
                       truncated=bool(state.get('truncated')))
