"""`tissue-sim info RUN`: what a recording holds, in the spirit of `ros2 bag info`."""
from __future__ import annotations

import datetime
import json
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'info'
HELP = ('summary of a run or recording (MCAP file or split folder), like `ros2 bag info`: files, size, duration, '
        'start/end, messages, per topic type, count, rate, offered QoS and type hash; ROS distro; model')


def add_arguments(p):
    p.add_argument('run', help='MCAP file, or a folder of them (a split recording)')
    p.add_argument('--json', action='store_true', help='print the summary as one JSON object')


def _stamp(ns: int | None) -> str:
    if ns is None:
        return '-'
    t = datetime.datetime.fromtimestamp(ns // 10**9, datetime.timezone.utc)
    return f'{t:%b %d %Y %H:%M:%S}.{ns % 10**9:09d} ({ns // 10**9}.{ns % 10**9:09d})'


def _size(n: int) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n:.1f} {unit}' if unit != 'B' else f'{n} B'
        n /= 1024


def summarise(path) -> dict:
    """The info of a run as a plain dict (what ``--json`` prints)."""
    import yaml

    from tissue_sim.core import mcapio
    try:
        s = mcapio.scan(path)
    except mcapio.McapIOError as e:
        raise UserError(str(e)) from None
    meta = s.metadata
    distro = ''
    rosbag2 = meta.get(mcapio.ROSBAG2_METADATA_NAME, {})
    if rosbag2.get('serialized_metadata'):
        try:
            distro = str((yaml.safe_load(rosbag2['serialized_metadata']) or {}).get('ros_distro') or '')
        except yaml.YAMLError:
            distro = ''
    distro = distro or rosbag2.get('ROS_DISTRO', '')
    if not distro:
        try:
            distro = json.loads(meta.get(mcapio.METADATA_NAME, {}).get('versions', '{}')).get('ros_distro', '')
        except (ValueError, AttributeError):
            distro = ''
    model = {}
    for rec in (mcapio.METADATA_NAME, 'tissue_sim_model'):
        m = meta.get(rec, {})
        if m.get('model'):
            model = {'name': m['model'], 'hash': m.get('model_hash', '')}
    topics = []
    for topic, typ in s.topics.items():
        n = s.counts.get(topic, 0)
        first, last = s.topic_times.get(topic, (None, None))
        cmeta = s.channel_metadata.get(topic, {})
        try:
            qos = [q.short() for q in mcapio.parse_qos_yaml(cmeta.get('offered_qos_profiles', ''))]
        except mcapio.McapIOError:
            qos = ['unreadable']
        topics.append({'topic': topic, 'type': typ, 'count': n,
                       'rate_hz': round((n - 1) / ((last - first) / 1e9), 3) if n > 1 and last > first else None,
                       'serialization_format': mcapio.MESSAGE_ENCODING, 'qos': qos,
                       'type_hash': cmeta.get('topic_type_hash', '')})
    dur = (s.end_ns - s.start_ns) / 1e9 if s.start_ns is not None else 0.0
    return {'files': [str(f) for f in s.files], 'size_bytes': sum(Path(f).stat().st_size for f in s.files),
            'storage_id': 'mcap', 'ros_distro': distro, 'duration_s': dur, 'start_ns': s.start_ns,
            'end_ns': s.end_ns, 'messages': sum(s.counts.values()), 'topics': topics, 'model': model,
            'truncated': s.truncated}


def run(args) -> int:
    info = summarise(args.run)
    if args.json:
        print(json.dumps(info))
        return 0
    w = 19
    lines = [f'{"Files:":<{w}}{info["files"][0]}'] + [f'{"":<{w}}{f}' for f in info['files'][1:]]
    lines += [f'{"Bag size:":<{w}}{_size(info["size_bytes"])}',
              f'{"Storage id:":<{w}}{info["storage_id"]}',
              f'{"ROS Distro:":<{w}}{info["ros_distro"] or "(not recorded)"}',
              f'{"Duration:":<{w}}{info["duration_s"]:.9f}s',
              f'{"Start:":<{w}}{_stamp(info["start_ns"])}',
              f'{"End:":<{w}}{_stamp(info["end_ns"])}',
              f'{"Messages:":<{w}}{info["messages"]}']
    for i, t in enumerate(info['topics']):
        rate = f'{t["rate_hz"]:.2f} Hz' if t['rate_hz'] else '-'
        lead = 'Topic information:' if i == 0 else ''
        lines.append(f'{lead:<{w}}Topic: {t["topic"]} | Type: {t["type"]} | Count: {t["count"]} | Rate: {rate} | '
                     f'Serialization Format: {t["serialization_format"]}')
        lines.append(f'{"":<{w}}    QoS: {"; ".join(t["qos"]) or "(none recorded)"} | Hash: {t["type_hash"] or "(none)"}')
    m = info['model']
    lines.append(f'{"Model:":<{w}}{m["name"]} (hash {m["hash"] or "?"})' if m else f'{"Model:":<{w}}(not recorded)')
    lines.append(f'{"Status:":<{w}}' + ('cut short (no summary/footer; read up to the last complete chunk): '
                                       'run `tissue-sim repair` on it' if info['truncated'] else 'complete'))
    print('\n'.join(lines))
    return 0
