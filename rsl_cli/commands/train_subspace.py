"""`rsl train-subspace`: described in stages/registry.py; its options are the fields of TrainSubspaceConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("train-subspace")
