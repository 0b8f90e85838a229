"""rsl library: the stage package (stages/steps/, one module per command), the helpers they share (artefacts,
capture, observations, ...), the engines (sim/, subspace/, render/, vision/) and the pure domain types (domain/).

Imports point one way: rsl_cli -> stages/steps/<stage>.py -> helpers -> stages/{sim,subspace,render,vision}
-> stages/domain (docs/architecture.md; tests/test_architecture.py checks it).
"""
