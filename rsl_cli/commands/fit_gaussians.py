"""`rsl fit-gaussians`: described in stages/registry.py; its options are the fields of FitGaussiansConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("fit-gaussians")
