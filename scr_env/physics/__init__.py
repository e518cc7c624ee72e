"""Physics of the SCR plant: the one-source cell chemistry, its numba and CasADi backends, the compiled step."""
