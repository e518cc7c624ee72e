"""Benchmark data for the estimators: simulated systems of the kinds the public nonlinear benchmarks hold
(:mod:`ident.benchmarks.simulated`)."""
from ident.benchmarks.simulated import (
    SIMULATED_BENCHMARKS,
    SimulatedBenchmark,
    cascaded_tanks,
    coupled_drives,
    duffing_oscillator,
    simulated_benchmark,
)

__all__ = [
    "SIMULATED_BENCHMARKS",
    "SimulatedBenchmark",
    "cascaded_tanks",
    "coupled_drives",
    "duffing_oscillator",
    "simulated_benchmark",
]
