"""The real-time stepping policy of the simulator node (tissue_sim.core.realtime), without DDS:
a fake solver whose steps cost a known wall time on a fake clock."""
import pytest

from tissue_sim.core import realtime as rt


class FakeSolver:
    """k steps cost ``overhead + k * cost`` seconds of the fake wall clock."""

    def __init__(self, cost, overhead=0.0):
        self.cost, self.overhead = cost, overhead
        self.now, self.steps, self.calls = 0.0, 0, []

    def clock(self):
        return self.now

    def run(self, k):
        assert k >= 1
        self.now += self.overhead + k * self.cost
        self.steps += k
        self.calls.append(k)


def pacer(solver, dt):
    p = rt.Pacer(solver.run, dt, clock=solver.clock)
    p.warm_up()
    return p


def test_frame_period_and_budget():
    period = rt.frame_period(34.0)
    assert 1.0 / period == pytest.approx(34.0 * rt.HEADROOM)
    assert rt.step_budget(period, 0.0) == pytest.approx(0.85 * period)
    assert rt.step_budget(period, 0.004) == pytest.approx(0.85 * period - 0.004)
    assert rt.step_budget(period, 1.0) == pytest.approx(0.2 * period)      # a slow publish leaves a floor


@pytest.mark.parametrize('rate', [1.0, 0.5, 3.0])
def test_sim_time_follows_wall_time_times_rate_when_the_solver_keeps_up(rate):
    s = FakeSolver(cost=2e-6)
    p = pacer(s, dt=1e-3)
    s.steps = 0
    period = rt.frame_period(34.0)
    for _ in range(340):
        p.advance(period, realtime=True, rate=rate, cap=2000, budget=rt.step_budget(period, 0.0))
    wall = 340 * period
    assert s.steps * 1e-3 == pytest.approx(wall * rate, abs=1e-3)        # within one step: the debt carries
    assert 0.0 <= p.sim_debt < 1e-3


def test_a_slow_solver_falls_behind_without_spiralling():
    """Each frame steps for its budget only and the debt is dropped: the real-time factor drops to
    what the solver can do, the frame rate is kept."""
    s = FakeSolver(cost=1e-3)                  # 1 ms per step of 0.1 ms: real-time factor 0.1 at best
    p = pacer(s, dt=1e-4)
    period = rt.frame_period(34.0)
    budget = rt.step_budget(period, 0.0)
    per_frame = []
    for _ in range(50):
        n0, t0 = s.steps, s.now
        p.advance(period, realtime=True, rate=1.0, cap=2000, budget=budget)
        per_frame.append(s.steps - n0)
        assert s.now - t0 <= budget + s.cost + 1e-12          # at most one step past the budget
        assert p.sim_debt == 0.0
    assert min(per_frame) >= int(budget / s.cost) - 1


def test_cap_limits_the_steps_and_drops_the_debt():
    s = FakeSolver(cost=1e-7)
    p = pacer(s, dt=1e-4)
    n = p.advance(1.0, realtime=True, rate=1.0, cap=500, budget=1.0)    # 10,000 steps owed
    assert n == 500 and p.sim_debt == 0.0


def test_as_fast_as_possible_fills_the_budget_in_few_batched_calls():
    s = FakeSolver(cost=1e-5, overhead=2e-6)   # a call costs a fifth of a step more
    p = pacer(s, dt=1e-3)
    s.calls.clear()
    period = rt.frame_period(34.0)
    budget = rt.step_budget(period, 0.0)
    t0 = s.now
    n = p.advance(period, realtime=False, rate=1.0, cap=100000, budget=budget)
    assert budget - 2 * s.cost - s.overhead <= s.now - t0 <= budget + s.cost + s.overhead
    assert n > 0.9 * budget / (s.cost + s.overhead / 10)
    assert len(s.calls) <= 12                  # batches sized from the measured cost, not one call per step
    assert p.step_cost == pytest.approx(s.cost, rel=0.3)


def test_a_failing_step_propagates_and_reset_drops_the_debt():
    class Diverged(Exception):
        pass

    s = FakeSolver(cost=1e-6)
    p = pacer(s, dt=1e-3)

    def fail(k):
        raise Diverged('boom')
    p.run_steps = fail
    with pytest.raises(Diverged):
        p.advance(0.5, realtime=True, rate=1.0, cap=2000, budget=0.02)
    assert p.sim_debt == pytest.approx(0.5)
    p.reset()
    assert p.sim_debt == 0.0


def test_warm_up_times_a_scratch_runner():
    s, scratch = FakeSolver(cost=3e-5), FakeSolver(cost=3e-5)
    p = rt.Pacer(s.run, 1e-3, clock=scratch.clock)
    assert p.warm_up(scratch.run) == pytest.approx(3e-5)
    assert s.steps == 0 and scratch.steps == rt.WARM_STEPS
