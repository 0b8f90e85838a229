"""`rsl report`: described in stages/registry.py; its options are the fields of ReportConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("report")
