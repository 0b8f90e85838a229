"""Full-space FEM in JAX (float64): materials, incremental potential, Newton, contact, adjoint."""
