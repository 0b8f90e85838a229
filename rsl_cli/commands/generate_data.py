"""`rsl generate-data`: described in stages/registry.py; its options are the fields of GenerateDataConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("generate-data")
