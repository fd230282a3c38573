"""The simulated plant: numba kernels, effect composition, auxiliary trajectories."""
