"""Real-time stepping policy (ROS-free): how many solver steps a frame tick runs, and in which calls.

A frame loop (the ``simulator`` node's timer) calls :meth:`Pacer.advance` once per frame with the
wall time since the previous frame. In real-time mode that adds wall time x ``rate`` of simulated
time to a debt, paid in solver steps of ``dt`` (at most ``cap`` per frame); as fast as possible it
runs up to ``cap`` steps. Either way stepping stops when the frame's wall-time budget is spent (the
frame rate comes first): then sim time falls behind and the debt is dropped, so a slow solver runs
at a real-time factor below ``rate`` instead of spiralling.

The steps of a frame run in a few batched solver calls, each sized from the measured wall time per
step to ``BATCH_FILL`` of the budget left: a call has a fixed cost (~20 % of a paper-set step), and
k steps in one call give bit for bit the state of k calls of one step (activations change only
between frames), so batching changes the timing only.

With two or more cores the frame loop and the stepping run side by side (:class:`SolverThread`): a
thread of its own runs the Pacer in chunks of ``CHUNK_SHARE`` of a frame period of owed sim time and,
after each chunk, leaves a copy of the state (``latest``) for the frame loop to publish. The compiled
step releases the GIL (numba ``nogil``), so stepping takes one core while the frame loop builds and
publishes on another: the published frame is the state at the end of the last chunk, at most a chunk
(~15 ms at 34 Hz) behind the solver. The steps are the same calls either way, so the states are the
same bit for bit.
"""
from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Callable

BATCH_FILL = 0.8     # a solver call is sized to this share of the frame's stepping time left
WARM_STEPS = 10      # steps timed at start-up for the first batch's size
HEADROOM = 1.02      # frames are scheduled at publish_rate x HEADROOM (publish_rate is the floor)
BUDGET_SHARE = 0.85  # of the frame period, less the measured publish cost, goes to stepping ...
BUDGET_FLOOR = 0.2   # ... but never less than this share of it
CHUNK_SHARE = 0.5    # SolverThread: a chunk is the steps owed over this share of a frame period
GIL_SWITCH = 0.0005  # [s] sys.setswitchinterval with a SolverThread: how long it may wait for the GIL after a chunk
                     # while the frame loop runs Python (Python's default is 5 ms, a third of a chunk)


def frame_period(publish_rate: float) -> float:
    """Seconds between frames for a floor of ``publish_rate`` frames per second."""
    return 1.0 / (publish_rate * HEADROOM)


def step_budget(period: float, publish_cost: float) -> float:
    """Wall seconds of stepping in one frame of ``period`` s that publishes in ``publish_cost`` s."""
    return max(BUDGET_FLOOR * period, BUDGET_SHARE * period - publish_cost)


class Pacer:
    """Runs the solver steps of each frame. ``run_steps(k)`` advances the solver by k steps of ``dt``
    (it may raise: the exception propagates and the debt is kept until :meth:`reset`);
    ``clock`` is the wall clock [s] (time.perf_counter; a test passes a fake one)."""

    def __init__(self, run_steps: Callable[[int], None], dt: float, clock: Callable[[], float] = time.perf_counter):
        self.run_steps, self.dt, self.clock = run_steps, float(dt), clock
        self.step_cost = 0.0        # wall seconds per step, a running estimate (set by warm_up)
        self.sim_debt = 0.0         # simulated seconds owed to wall time (real-time mode)

    def warm_up(self, run_steps: Callable[[int], None] | None = None, n: int = WARM_STEPS) -> float:
        """Time ``n`` steps of ``run_steps`` (default: the pacer's own; a scratch state's keeps the
        run at rest) for the first batch's size; returns the cost per step."""
        t0 = self.clock()
        (run_steps or self.run_steps)(n)
        self.step_cost = max((self.clock() - t0) / n, 1e-9)
        return self.step_cost

    def reset(self) -> None:
        """Forget the debt (after a pause, a reset or a divergence)."""
        self.sim_debt = 0.0

    def advance(self, wall_dt: float, *, realtime: bool, rate: float, cap: int, budget: float) -> int:
        """The steps of one frame, ``wall_dt`` wall seconds after the previous one; returns how many."""
        t0 = self.clock()
        if not realtime:
            return self.run_within(cap, t0, budget)
        self.sim_debt += wall_dt * rate
        want = min(int(self.sim_debt / self.dt + 1e-9), cap)
        n = self.run_within(want, t0, budget)
        self.sim_debt = 0.0 if n < want or n == cap else self.sim_debt - n * self.dt
        return n

    def run_within(self, want: int, t0: float, budget: float) -> int:
        """Up to ``want`` steps until ``budget`` wall seconds from ``t0`` are spent, in batches sized
        from the measured cost per step. Returns the steps done."""
        n = 0
        while n < want:
            left = budget - (self.clock() - t0)
            if left <= 0.0:
                break
            k = min(want - n, max(1, int(BATCH_FILL * left / max(self.step_cost, 1e-9))))
            t1 = self.clock()
            self.run_steps(k)
            self.step_cost += 0.3 * ((self.clock() - t1) / k - self.step_cost)
            n += k
        return n


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the platform has one, else the CPU count): the
    simulator steps in a thread of its own only with two or more."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # pragma: no cover - platforms without affinity masks
        return os.cpu_count() or 1


def map_threads(fn: Callable, items, jobs: int | None = None) -> list:
    """[fn(item) for item in items], up to ``jobs`` at a time on threads of their own (default: usable_cpus()), in
    the items' order. For independent runs of the solver (each with its own state): its step releases Python's lock
    (step.advance is nogil), so the runs use as many cores, and each gives what it gives alone."""
    from concurrent.futures import ThreadPoolExecutor
    items = list(items)
    jobs = max(1, min(len(items), usable_cpus() if jobs is None else int(jobs)))
    if jobs == 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(max_workers=jobs, thread_name_prefix='tissue_sim run') as pool:
        return list(pool.map(fn, items))


def lower_priority(increment: int) -> bool:
    """Raise the calling thread's nice value by ``increment`` (Linux: per thread; anyone may lower their own
    priority); False where the platform does not allow it."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + int(increment)))
        return True
    except (AttributeError, OSError):
        return False


class SolverThread:
    """Runs ``pacer`` in a thread of its own (module docstring): in real-time mode it sleeps until
    ``CHUNK_SHARE`` of a frame ``period`` of sim time is owed, then pays the debt through
    :meth:`Pacer.advance` (a frame period of wall time at most: a slow solver falls behind as in the
    frame loop); as fast as possible it steps for ``CHUNK_SHARE`` of a period at a time. After each
    chunk ``latest`` is ``snapshot()`` (a copy of the state, taken while the state is still). ``lock``
    is held while a chunk steps: who changes the state from another thread (a reset) takes it first, through
    :meth:`hold` (ahead of the next chunk).
    ``nice`` > 0 runs the thread that much below the process's priority (the frame loop then gets the CPU
    first where cores are short; the operating system already favours it, as it sleeps between frames,
    and a lower priority starved the solver beside other jobs). A step that raises pauses the thread: ``error`` is the exception, ``on_error(exc)`` is called from
    the thread. Settings (``realtime``, ``rate``, ``cap``) are plain attributes, read at each chunk."""

    def __init__(self, pacer: Pacer, snapshot: Callable[[], object], period: float, *, paused: bool = False, nice: int = 0,
                 on_error: Callable[[BaseException], None] | None = None, clock: Callable[[], float] = time.perf_counter):
        self.pacer, self.snapshot, self.period, self.on_error, self.clock = pacer, snapshot, float(period), on_error, clock
        self.realtime, self.rate, self.cap = True, 1.0, 2000
        self.nice = int(nice)
        self.lock = threading.Lock()
        self._waiting = 0               # other threads waiting in hold() (the solver thread lets them in first)
        self._waiting_lock = threading.Lock()
        self.latest = snapshot()
        self.paused = bool(paused)
        self.error: BaseException | None = None
        self.step_wall = 0.0            # wall seconds spent in chunks
        self.step_cpu = 0.0             # CPU seconds of this thread spent in chunks
        self.chunks = 0
        self._wake = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name='tissue_sim solver', daemon=True)

    def start(self) -> 'SolverThread':
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop = True
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    @contextlib.contextmanager
    def hold(self):
        """``lock`` for another thread (a pause, a reset), taken before the solver's next chunk: a plain lock is not
        fair, and a solver thread that never sleeps (as fast as possible, or behind real time) would take it again
        at once, for seconds (a pause service call timed out so), so the thread waits while anyone is here."""
        with self._waiting_lock:
            self._waiting += 1
        try:
            self.lock.acquire()
        finally:
            with self._waiting_lock:
                self._waiting -= 1
        try:
            yield
        finally:
            self.lock.release()

    def set_paused(self, paused: bool) -> None:
        """Pause (the chunk under way ends first) or resume (the debt starts from zero)."""
        with self.hold():
            self.paused = bool(paused)
            self.pacer.reset()
            if not paused:
                self.error = None
        self._wake.set()

    def refresh(self) -> None:
        """A new ``latest`` now (after the state was changed under ``lock``)."""
        self.latest = self.snapshot()

    def chunk_sim(self) -> float:
        """Sim seconds owed before a chunk starts (real-time mode)."""
        return max(self.pacer.dt, CHUNK_SHARE * self.period * self.rate)

    def _run(self) -> None:
        if self.nice > 0:
            lower_priority(self.nice)
        last = self.clock()
        while not self._stop:
            if self.paused or self.error is not None:
                self._wake.wait(0.05)
                self._wake.clear()
                last = self.clock()
                continue
            if self.realtime:
                owed = self.pacer.sim_debt + (self.clock() - last) * self.rate
                need = self.chunk_sim()
                if owed < need:
                    self._wake.wait(min((need - owed) / self.rate, self.period))
                    self._wake.clear()
                    continue
            while self._waiting and not self._stop:      # a pause or reset waits for the lock: it goes first
                time.sleep(0.0002)
            err = None
            with self.lock:
                if self.paused or self._stop:
                    continue
                now, cpu0 = self.clock(), time.thread_time()
                wall_dt, last = now - last, now
                try:
                    self.pacer.advance(wall_dt, realtime=self.realtime, rate=self.rate, cap=self.cap,
                                       budget=self.period if self.realtime else CHUNK_SHARE * self.period)
                except Exception as e:          # (a divergence, a refused step): pause, report
                    err = self.error = e
                    self.pacer.reset()
                self.latest = self.snapshot()
                self.step_wall += self.clock() - now
                self.step_cpu += time.thread_time() - cpu0
                self.chunks += 1
            if err is not None and self.on_error is not None:
                self.on_error(err)
