"""Neural and linear subspaces x = φ(z), reduced dynamics and the reduced adjoint (JAX)."""
