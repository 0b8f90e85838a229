"""`rsl calibrate`: described in stages/registry.py; its options are the fields of CalibrateConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("calibrate")
