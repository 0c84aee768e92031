"""Load a recorded or headless run into numpy arrays (ROS-free).

A *run* is an MCAP file, or a folder of them (a recording split into several files, read in name
order), holding ``tissue_msgs/msg/TissueTopology`` once (``/tissue/topology``) and
``tissue_msgs/msg/TissueState`` per frame (``/tissue/state``). Channels are recognised by their
schema name, so remapped topics work too. A file cut short (recorder killed) is read up to the last
complete message, with a warning.

* :func:`read_topology` - the :class:`~tissue_sim.core.tissue_cdr.Topology`.
* :func:`iter_states` - stream :class:`~tissue_sim.core.tissue_cdr.State` frames (long runs).
* :func:`load_run` - everything in memory as a :class:`Run`: ``frames`` (F, V, 3) float32 [m],
  ``times`` (F,) [s], joints, muscles, segment poses. ``stride``/``frames`` pick a subset.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from tissue_sim.core import mcapio, tissue_cdr
from tissue_sim.core.cdr import CdrError
from tissue_sim.core.tissue_cdr import STATE_TYPE, TOPOLOGY_TYPE, State, Topology


class RunError(ValueError):
    """A run that cannot be read (message names the file and the problem)."""


@dataclasses.dataclass(eq=False)
class Run:
    """A run in memory. Frame axis first; units SI; model frame."""
    path: Path
    topology: Topology
    frame_index: np.ndarray             # (F,) index of each kept frame among all frames of the run
    times: np.ndarray                   # (F,) float64 [s] sim_time
    stamps_ns: np.ndarray               # (F,) int64 header stamps
    steps: np.ndarray                   # (F,) uint64
    frames: np.ndarray                  # (F, V, 3) float32 [m]
    joint_names: tuple
    joint_positions: np.ndarray         # (F, J) [rad]
    joint_velocities: np.ndarray        # (F, J) [rad/s]
    muscle_names: tuple
    activations: np.ndarray             # (F, M)
    muscle_lengths: np.ndarray          # (F, M) [m]
    muscle_volumes: np.ndarray          # (F, M) [m^3]
    segment_poses: np.ndarray           # (F, S, 7) x y z qx qy qz qw
    kinetic_energy: np.ndarray          # (F,)
    elastic_energy: np.ndarray          # (F,)

    @property
    def n_frames(self) -> int:
        return int(self.times.shape[0])


# ----------------------------------------------------------------------------- MCAP access
def run_files(path) -> list[Path]:
    """The MCAP files of a run: the file itself, or the *.mcap files of a folder in split order."""
    p = Path(path)
    if p.is_file() and p.suffix == '.npz':
        return [p]
    try:
        return mcapio.mcap_files(p)
    except mcapio.McapIOError as e:
        raise RunError(str(e)) from None


def _iter_raw(files, want: set[str]):
    """Yield (schema name, log_time, data) of the messages whose schema is in ``want``, in file order.

    Uses the project's reader (:mod:`tissue_sim.core.mcapio`): a file cut short by a killed recorder
    yields everything up to its last complete chunk.
    """
    for f in files:
        try:
            for m in mcapio.iter_messages(f):
                if m.schema_name in want:
                    yield m.schema_name, m.log_time, m.data
        except mcapio.McapIOError as e:
            raise RunError(str(e)) from None


def count_states(path) -> int | None:
    """Number of TissueState messages from the MCAP summaries (None if a file has no summary)."""
    from mcap.reader import SeekingReader
    total = 0
    for f in run_files(path):
        if f.suffix == '.npz':
            with np.load(f) as z:
                return int(z['frames'].shape[0]) if 'frames' in z.files else None
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


def read_topology(path) -> Topology:
    """The run's TissueTopology (the first one found)."""
    files = run_files(path)
    if files[0].suffix == '.npz':
        return _npz_topology(files[0])
    for _, _, data in _iter_raw(files, {TOPOLOGY_TYPE}):
        try:
            return tissue_cdr.decode_topology(data)
        except CdrError as e:
            raise RunError(f'{path}: bad TissueTopology message ({e})') from None
    raise RunError(f'{path}: no {TOPOLOGY_TYPE} message (was /tissue/topology recorded?)')


def iter_states(path, with_vertices: bool = True):
    """Stream the run's TissueState frames in recorded order."""
    files = run_files(path)
    if files[0].suffix == '.npz':
        yield from _npz_states(files[0])
        return
    for i, (_, _, data) in enumerate(_iter_raw(files, {STATE_TYPE})):
        try:
            yield tissue_cdr.decode_state(data, with_vertices=with_vertices)
        except CdrError as e:
            raise RunError(f'{path}: bad TissueState message #{i} ({e})') from None


def load_run(path, stride: int = 1, frames=None, max_frames: int | None = None) -> Run:
    """Load a run; keep every ``stride``-th frame, or only the frame indices in ``frames``."""
    path = Path(path)
    topo = read_topology(path)
    keep = None if frames is None else set(int(f) for f in frames)
    cols = {k: [] for k in ('idx', 't', 'stamp', 'step', 'X', 'jp', 'jv', 'act', 'ml', 'mv', 'sp', 'ke', 'ee')}
    jn = mn = None
    for i, s in enumerate(iter_states(path)):
        if keep is not None and i not in keep:
            continue
        if keep is None and i % stride:
            continue
        if s.vertex_positions.shape[0] != topo.n_vertices:
            raise RunError(f'{path}: state #{i} has {s.vertex_positions.shape[0]} vertices, '
                           f'the topology {topo.n_vertices}')
        if jn is None:
            jn, mn = tuple(s.joint_names), tuple(s.muscle_names)
        cols['idx'].append(i)
        cols['t'].append(s.sim_time)
        cols['stamp'].append(s.stamp_ns)
        cols['step'].append(s.step)
        cols['X'].append(s.vertex_positions)
        cols['jp'].append(s.joint_positions)
        cols['jv'].append(s.joint_velocities)
        cols['act'].append(s.activations)
        cols['ml'].append(s.muscle_lengths)
        cols['mv'].append(s.muscle_volumes)
        cols['sp'].append(s.segment_poses)
        cols['ke'].append(s.kinetic_energy)
        cols['ee'].append(s.elastic_energy)
        if max_frames is not None and len(cols['idx']) >= max_frames:
            break
    if not cols['idx']:
        raise RunError(f'{path}: no {STATE_TYPE} frames (was /tissue/state recorded?)')

    def stack(k, shape_tail, dtype):
        try:
            return np.stack(cols[k]).astype(dtype, copy=False)
        except ValueError:
            raise RunError(f'{path}: frames disagree in the size of {k}') from None

    S = len(topo.segment_names)
    return Run(path=path, topology=topo, frame_index=np.array(cols['idx'], np.int64),
               times=np.array(cols['t'], np.float64), stamps_ns=np.array(cols['stamp'], np.int64),
               steps=np.array(cols['step'], np.uint64), frames=stack('X', None, np.float32),
               joint_names=jn, joint_positions=stack('jp', None, np.float64),
               joint_velocities=stack('jv', None, np.float64), muscle_names=mn,
               activations=stack('act', None, np.float32), muscle_lengths=stack('ml', None, np.float32),
               muscle_volumes=stack('mv', None, np.float32),
               segment_poses=stack('sp', None, np.float64).reshape(len(cols['idx']), -1, 7)
               if S else np.zeros((len(cols['idx']), 0, 7)),
               kinetic_energy=np.array(cols['ke']), elastic_energy=np.array(cols['ee']))


# ----------------------------------------------------------------------------- writing (tests, synthetic runs)
def write_run(path, topology: Topology, states, topology_stamp_ns: int = 0, chunk_size: int = 1 << 20) -> Path:
    """Write a run MCAP (project writer): the topology on /tissue/topology, then each State (or its
    CDR bytes) on /tissue/state. Used for synthetic runs and tests; real runs come from the recorder
    or a headless simulation."""
    path = Path(path)
    with mcapio.McapWriter(path, flush_seconds=-1, chunk_size=chunk_size, metadata={'model': topology.model_name}) as w:
        w.add_channel('/tissue/topology', TOPOLOGY_TYPE)
        w.add_channel('/tissue/state', STATE_TYPE)
        w.write('/tissue/topology', tissue_cdr.encode_topology(topology), topology_stamp_ns)
        for i, s in enumerate(states):
            data = s if isinstance(s, (bytes, bytearray)) else tissue_cdr.encode_state_obj(s)
            stamp = int(s.stamp_ns) if isinstance(s, State) else topology_stamp_ns + i
            w.write('/tissue/state', data, max(stamp, topology_stamp_ns))
    return path


# ----------------------------------------------------------------------------- optional: headless .npz
def _npz_topology(path: Path) -> Topology:
    with np.load(path, allow_pickle=False) as z:
        if 'topology_cdr' in z.files:
            return tissue_cdr.decode_topology(z['topology_cdr'].tobytes())
        if 'model' in z.files or 'model_path' in z.files:
            pass
    raise RunError(f'{path}: .npz run without a topology (expected array "topology_cdr"); '
                   'record or simulate to an MCAP instead')


def _npz_states(path: Path):
    with np.load(path, allow_pickle=False) as z:
        if 'frames' not in z.files:
            raise RunError(f'{path}: .npz run without "frames"')
        X = z['frames']
        F = X.shape[0]
        times = z['times'] if 'times' in z.files else np.arange(F, dtype=float)
        get = lambda k, shape: z[k] if k in z.files else np.zeros(shape)   # noqa: E731
        jn = [str(s) for s in z['joint_names']] if 'joint_names' in z.files else []
        mn = [str(s) for s in z['muscle_names']] if 'muscle_names' in z.files else []
        jp = get('joint_positions', (F, len(jn)))
        jv = get('joint_velocities', (F, len(jn)))
        act = get('activations', (F, len(mn)))
        ml = get('muscle_lengths', (F, len(mn)))
        mv = get('muscle_volumes', (F, len(mn)))
        sp = get('segment_poses', (F, 0, 7))
        for i in range(F):
            yield State(int(times[i] * 1e9), 'world', i, float(times[i]), jn, jp[i], jv[i], mn,
                        act[i].astype(np.float32), ml[i].astype(np.float32), mv[i].astype(np.float32),
                        np.asarray(sp[i]).reshape(-1, 7), X[i].astype(np.float32), 0.0, 0.0)


# ----------------------------------------------------------------------------- headless solver runs
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
    topo = tissue_cdr.from_model(tm, parameters_yaml=sim.params.to_yaml())
    path = Path(path)
    with mcapio.McapWriter(path, metadata={'model': tm.name, 'source': 'runio.record_simulation'}) as w:
        w.add_channel('/tissue/topology', TOPOLOGY_TYPE)
        w.add_channel('/tissue/state', STATE_TYPE)
        w.write('/tissue/topology', tissue_cdr.encode_topology(topo), 0)
        for t, st in solver.simulate(sim, duration, timeline, dt=h, every=every):
            o = solver.observe(sim, st)
            act = fn(t)
            stamp = int(round(t * 1e9))
            w.write('/tissue/state', tissue_cdr.encode_state(
                stamp_ns=stamp, step=st.step, sim_time=t, joint_names=tm.joint_names,
                joint_positions=o['joint_positions'], joint_velocities=o['joint_velocities'],
                muscle_names=tm.muscle_names, activations=act, muscle_lengths=o['muscle_lengths'],
                muscle_volumes=o['muscle_volumes'], segment_poses=o['segment_poses'], vertex_positions=st.x,
                kinetic_energy=o['kinetic_energy'], elastic_energy=o['elastic_energy']), stamp)
            if progress is not None:
                progress(t)
    return path
