"""rsl library: one module per stage plus the physics and rendering packages.

Imports point one way: rsl_cli -> stages/<stage>.py -> stages/{sim,subspace,render,vision}.
"""
