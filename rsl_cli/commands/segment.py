"""`rsl segment`: described in stages/registry.py; its options are the fields of SegmentConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("segment")
