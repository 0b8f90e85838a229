"""`rsl rollout`: described in stages/registry.py; its options are the fields of RolloutConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("rollout")
