"""`rsl adapt`: described in stages/registry.py; its options are the fields of AdaptConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("adapt")
