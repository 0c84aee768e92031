"""The run format: write and read runs (ROS-free).

A *run* is an MCAP file, or a folder of them (a recording split into several files, read in name
order), holding ``tissue_msgs/msg/TissueTopology`` once (``/tissue/topology``) and
``tissue_msgs/msg/TissueState`` per frame (``/tissue/state``). The recorder writes it from the
simulator node, ``tissue-sim simulate -o RUN.mcap`` (:class:`RunWriter`) writes the same thing
headless, with the same frame encoder (:func:`tissue_sim.core.tissue_cdr.encode_frame`). Channels
are recognised by their schema name, so remapped topics work too. A file cut short (recorder killed)
is read up to the last complete message.

* :func:`load_run` - one pass over the file(s): the topology and the frames, as a :class:`Run`
  (``frames`` (F, V, 3) float32 [m], ``times`` (F,) [s], joints, muscles, segment poses).
  ``stride``/``frames`` keep a subset. ``analyze``, ``render`` and ``export-run`` all start here.
* :func:`read_topology`, :func:`iter_states` - the topology alone, or a stream of
  :class:`~tissue_sim.core.tissue_cdr.StateFrame` (long runs, scans without vertices).
* :class:`RunWriter`, :func:`record_simulation`, :func:`write_run` - writing.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from tissue_sim.core import mcapio, tissue_cdr
from tissue_sim.core.cdr import CdrError
from tissue_sim.core.model import TissueTopology
from tissue_sim.core.tissue_cdr import STATE_TYPE, TOPOLOGY_TYPE, StateFrame

TOPIC_TOPOLOGY = '/tissue/topology'
TOPIC_STATE = '/tissue/state'

# What the simulator node's publishers offer (ros/common.py: qos_latched, qos_stream()); written as
# the channels' offered_qos_profiles so `ros2 bag play` replays the topology latched.
OFFERED_QOS = {TOPIC_TOPOLOGY: mcapio.QOS_LATCHED, TOPIC_STATE: mcapio.qos_stream(10)}


class RunError(ValueError):
    """A run that cannot be read (message names the file and the problem)."""


@dataclasses.dataclass(eq=False)
class Run:
    """A run in memory. Frame axis first; units SI; model frame."""
    path: Path
    model: TissueTopology               # decoded /tissue/topology (meta: model_hash, parameters_yaml)
    frame_index: np.ndarray             # (F,) index of each kept frame among all frames of the run
    times: np.ndarray                   # (F,) float64 [s] sim_time
    stamps_ns: np.ndarray               # (F,) int64 header stamps
    steps: np.ndarray                   # (F,) uint64
    frames: np.ndarray                  # (F, V, 3) float32 [m]
    joint_names: tuple
    joint_positions: np.ndarray         # (F, J) [rad]
    joint_velocities: np.ndarray        # (F, J) [rad/s]
    muscle_names: tuple
    activations: np.ndarray             # (F, M) activation state
    muscle_lengths: np.ndarray          # (F, M) [m]
    muscle_volumes: np.ndarray          # (F, M) [m^3]
    segment_poses: np.ndarray           # (F, S, 7) x y z qx qy qz qw
    kinetic_energy: np.ndarray          # (F,)
    elastic_energy: np.ndarray          # (F,)
    n_total: int = 0                    # frames in the file (kept or not)
    excitations: np.ndarray = None      # (F, M) the commands (= activations in recordings made before the field)
    muscle_forces: np.ndarray = None    # (F, M) [N] (NaN in recordings made before the field)

    @property
    def n_frames(self) -> int:
        return int(self.times.shape[0])


# ----------------------------------------------------------------------------- MCAP access
def run_files(path) -> list[Path]:
    """The MCAP files of a run: the file itself, or the *.mcap files of a folder in split order."""
    p = Path(path)
    if p.is_file() and p.suffix == '.npz':
        raise RunError(f'{p}: a .npz file holds observation arrays only (tissue-sim simulate -o RUN.npz), '
                       'not a run; simulate with -o RUN.mcap, or record, to analyse it')
    try:
        return mcapio.mcap_files(p)
    except mcapio.McapIOError as e:
        raise RunError(str(e)) from None


def _iter_raw(files, want: set[str]):
    """Yield (schema name, log_time, data) of the messages whose schema is in ``want``, in file order.

    Uses the project's reader (:mod:`tissue_sim.core.mcapio`): a file cut short by a killed recorder
    yields every complete message.
    """
    for f in files:
        try:
            for m in mcapio.iter_messages(f):
                if m.schema_name in want:
                    yield m.schema_name, m.log_time, m.data
        except mcapio.McapIOError as e:
            raise RunError(str(e)) from None


def _topology(path, data) -> TissueTopology:
    try:
        return tissue_cdr.decode_topology(data)
    except CdrError as e:
        raise RunError(f'{path}: bad TissueTopology message ({e})') from None


def _no_topology(path):
    return RunError(f'{path}: no {TOPOLOGY_TYPE} message (was /tissue/topology recorded?)')


def count_states(path) -> int | None:
    """Number of TissueState messages from the MCAP summaries (None if a file has no summary)."""
    from mcap.reader import SeekingReader
    total = 0
    for f in run_files(path):
        try:
            with open(f, 'rb') as fh:
                s = SeekingReader(fh).get_summary()
        except Exception:
            return None
        if s is None or s.statistics is None:
            return None
        ids = {sid for sid, sc in s.schemas.items() if sc.name == STATE_TYPE}
        chans = [cid for cid, ch in s.channels.items() if ch.schema_id in ids]
        total += sum(s.statistics.channel_message_counts.get(c, 0) for c in chans)
    return total


def read_topology(path) -> TissueTopology:
    """The run's TissueTopology (the first one found)."""
    for _, _, data in _iter_raw(run_files(path), {TOPOLOGY_TYPE}):
        return _topology(path, data)
    raise _no_topology(path)


def iter_states(path, with_vertices: bool = True):
    """Stream the run's TissueState frames in recorded order."""
    for i, (_, _, data) in enumerate(_iter_raw(run_files(path), {STATE_TYPE})):
        try:
            yield tissue_cdr.decode_state(data, with_vertices=with_vertices)
        except CdrError as e:
            raise RunError(f'{path}: bad TissueState message #{i} ({e})') from None


def load_run(path, stride: int = 1, frames=None, max_frames: int | None = None, progress=None) -> Run:
    """Load a run in one pass over its file(s); keep every ``stride``-th frame, or only the frame
    indices in ``frames``. ``progress(i)`` is called for every frame read (kept or not)."""
    path = Path(path)
    files = run_files(path)
    keep = None if frames is None else set(int(f) for f in frames)
    cols = {k: [] for k in ('idx', 't', 'stamp', 'step', 'X', 'jp', 'jv', 'act', 'ml', 'mv', 'sp', 'ke', 'ee', 'ex', 'mf')}
    topo = None
    jn = mn = None
    i = -1
    for kind, _, data in _iter_raw(files, {TOPOLOGY_TYPE, STATE_TYPE}):
        if kind == TOPOLOGY_TYPE:
            if topo is None:
                topo = _topology(path, data)
            continue
        i += 1
        if progress is not None:
            progress(i)
        if (keep is not None and i not in keep) or (keep is None and i % stride):
            continue
        if max_frames is not None and len(cols['idx']) >= max_frames:
            continue
        try:
            s = tissue_cdr.decode_state(data)
        except CdrError as e:
            raise RunError(f'{path}: bad TissueState message #{i} ({e})') from None
        if jn is None:
            jn, mn = tuple(s.joint_names), tuple(s.muscle_names)
        for k, v in (('idx', i), ('t', s.sim_time), ('stamp', s.stamp_ns), ('step', s.step),
                     ('X', s.vertex_positions), ('jp', s.joint_positions), ('jv', s.joint_velocities),
                     ('act', s.activations), ('ml', s.muscle_lengths), ('mv', s.muscle_volumes),
                     ('sp', s.segment_poses), ('ke', s.kinetic_energy), ('ee', s.elastic_energy),
                     ('ex', s.excitations),
                     ('mf', s.muscle_forces if s.muscle_forces.size else np.full(len(s.muscle_names), np.nan, np.float32))):
            cols[k].append(v)
    if topo is None:
        raise _no_topology(path)
    if not cols['idx']:
        raise RunError(f'{path}: no {STATE_TYPE} frames (was /tissue/state recorded?)')
    for j, X in zip(cols['idx'], cols['X']):
        if X.shape[0] != topo.n_vertices:
            raise RunError(f'{path}: state #{j} has {X.shape[0]} vertices, the topology {topo.n_vertices}')
    F = len(cols['idx'])

    def stack(k, dtype):
        try:
            return np.stack(cols[k]).astype(dtype, copy=False)
        except ValueError:
            raise RunError(f'{path}: frames disagree in the size of {k}') from None

    return Run(path=path, model=topo, frame_index=np.array(cols['idx'], np.int64),
               times=np.array(cols['t'], np.float64), stamps_ns=np.array(cols['stamp'], np.int64),
               steps=np.array(cols['step'], np.uint64), frames=stack('X', np.float32),
               joint_names=jn, joint_positions=stack('jp', np.float64),
               joint_velocities=stack('jv', np.float64), muscle_names=mn,
               activations=stack('act', np.float32), muscle_lengths=stack('ml', np.float32),
               muscle_volumes=stack('mv', np.float32),
               segment_poses=stack('sp', np.float64).reshape(F, -1, 7),
               kinetic_energy=np.array(cols['ke']), elastic_energy=np.array(cols['ee']), n_total=i + 1,
               excitations=stack('ex', np.float32), muscle_forces=stack('mf', np.float32))


# ----------------------------------------------------------------------------- writing
class RunWriter:
    """Writes a run MCAP: the topology on /tissue/topology, then one TissueState per frame on
    /tissue/state (log time = the frame's stamp), exactly what the recorder keeps from the
    simulator node, with the channel metadata rosbag2 writes (``qos``: {topic: offered QoS},
    default :data:`OFFERED_QOS`; type hashes; ``ros_distro``). Use as a context manager."""

    def __init__(self, path, model, parameters_yaml: str = '', frame_id: str = 'world',
                 metadata: dict | None = None, qos: dict | None = None, **writer_kw):
        self.path = Path(path)
        self.model, self.frame_id = model, frame_id
        meta = {'model': model.name, 'model_hash': (model.meta or {}).get('model_hash') or model.content_hash(),
                'parameters_yaml': parameters_yaml, 'versions': mcapio.versions(), **(metadata or {})}
        self._w = mcapio.McapWriter(self.path, metadata=meta, **writer_kw)
        qos = {**OFFERED_QOS, **(qos or {})}
        self._w.add_channel(TOPIC_TOPOLOGY, TOPOLOGY_TYPE, qos=qos[TOPIC_TOPOLOGY])
        self._w.add_channel(TOPIC_STATE, STATE_TYPE, qos=qos[TOPIC_STATE])
        self._w.write(TOPIC_TOPOLOGY, tissue_cdr.encode_topology(model, parameters_yaml=parameters_yaml,
                                                                 model_hash=meta['model_hash'], stamp_ns=0,
                                                                 frame_id=frame_id), 0)
        self.n_frames = 0

    def write_frame(self, state, observation: dict, activations) -> None:
        """One frame of a solver state (see :func:`tissue_sim.core.tissue_cdr.encode_frame`)."""
        stamp = int(round(state.time * 1e9))
        self._w.write(TOPIC_STATE, tissue_cdr.encode_frame(self.model, state, observation, activations,
                                                           stamp_ns=stamp, frame_id=self.frame_id), stamp)
        self.n_frames += 1

    def write_state_message(self, data: bytes, stamp_ns: int) -> None:
        """One frame already encoded (a :class:`StateFrame` via ``encode_state_obj``, or received bytes)."""
        self._w.write(TOPIC_STATE, data, int(stamp_ns))
        self.n_frames += 1

    def close(self):
        self._w.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_run(path, model, states, chunk_size: int = 1 << 20) -> Path:
    """Write a run MCAP from the topology of ``model`` and :class:`StateFrame` objects (or their CDR
    bytes); for synthetic runs and tests. Real runs come from the recorder or :func:`record_simulation`."""
    with RunWriter(path, model, flush_seconds=-1, chunk_size=chunk_size) as w:
        for i, s in enumerate(states):
            if isinstance(s, StateFrame):
                w.write_state_message(tissue_cdr.encode_state_obj(s), max(int(s.stamp_ns), 0))
            else:
                w.write_state_message(s, i)
    return Path(path)


def record_simulation(path, tm, params=None, duration: float = 1.0, timeline=None, rate_hz: float = 34.0,
                      dt: float | None = None, progress=None) -> Path:
    """Run the solver headless on TissueModel ``tm`` and write the run MCAP (topology + states at
    ``rate_hz`` of simulated time), exactly what the recorder keeps from the simulator node.

    ``timeline``: as :func:`tissue_sim.core.solver.simulate` (None: all passive). Raises the solver's
    DivergenceError if the run blows up (the frames before are kept in the file)."""
    from tissue_sim.core import solver
    sim = solver.compile_model(tm, params or solver.Params.paper())
    h = sim.params.dt if dt is None else float(dt)
    every = max(1, int(round(1.0 / (rate_hz * h))))
    fn = solver.timeline_function(sim, timeline)
    st = solver.make_state(sim)
    with RunWriter(path, tm, parameters_yaml=sim.params.to_yaml(),
                   metadata={'source': 'runio.record_simulation'}) as w:
        for t, o in solver.simulate(sim, duration, fn, dt=h, every=every, state=st, output='obs'):
            w.write_frame(st, o, fn(t))
            if progress is not None:
                progress(t)
    return Path(path)
