"""Benchmark data for the estimators: readers for the files of the public nonlinear benchmarks with their official
splits (:mod:`ident.benchmarks.readers`) and simulated systems of the same kinds (:mod:`ident.benchmarks.simulated`)."""
from ident.benchmarks.readers import (
    BENCHMARK_READERS,
    BenchmarkData,
    BenchmarkFileError,
    read_benchmark,
    read_cascaded_tanks,
    read_coupled_drives,
    read_emps,
    read_silverbox,
    read_wiener_hammerstein,
)
from ident.benchmarks.simulated import (
    SIMULATED_BENCHMARKS,
    SimulatedBenchmark,
    cascaded_tanks,
    coupled_drives,
    duffing_oscillator,
    simulated_benchmark,
)

__all__ = [
    "BENCHMARK_READERS",
    "SIMULATED_BENCHMARKS",
    "BenchmarkData",
    "BenchmarkFileError",
    "SimulatedBenchmark",
    "cascaded_tanks",
    "coupled_drives",
    "duffing_oscillator",
    "read_benchmark",
    "read_cascaded_tanks",
    "read_coupled_drives",
    "read_emps",
    "read_silverbox",
    "read_wiener_hammerstein",
    "simulated_benchmark",
]
