"""The solver: local shape-preserving elastic cells, volume-preserving contraction, skeleton dynamics.

MuJoCo/Newton-style API (docs/ARCHITECTURE.md, docs/solver.md)::

    sim = compile_model(tissue_model, Params.paper())   # immutable SimModel
    state = make_state(sim); ctrl = make_control(sim)   # mutable State, Control (activation (M,))
    step(sim, state, ctrl)                              # in place; DivergenceError on failure
    observe(sim, state)                                 # joint angles, muscle lengths/volumes, energies
    reference_step(sim, state, activation)              # the same step in plain numpy (the readable definition)
    for t, s in simulate(sim, 3.0, {'hamstrings': [(0, 1)]}, every=10): ...
"""
from tissue_sim.core import numba_cache

numba_cache.install()     # before any kernel of the package is compiled or loaded

from tissue_sim.core.solver.model import (Control, DivergenceError, SimModel, State, compile_model,
                                          make_control, make_state, muscle_indices, reset,
                                          set_joint_positions)
from tissue_sim.core.solver.params import Params
from tissue_sim.core.activation import timeline_function
from tissue_sim.core.solver.measures import kinetic_energy, skeleton_energy
from tissue_sim.core.solver.reference import reference_step
from tissue_sim.core.solver.run import observe, simulate
from tissue_sim.core.solver.step import step

__all__ = ['Params', 'SimModel', 'State', 'Control', 'DivergenceError', 'compile_model', 'make_state',
           'make_control', 'reset', 'step', 'observe', 'simulate', 'timeline_function', 'muscle_indices',
           'set_joint_positions', 'skeleton_energy', 'kinetic_energy', 'reference_step']
