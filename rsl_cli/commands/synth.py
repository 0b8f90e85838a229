"""`rsl synth`: described in stages/registry.py; its options are the fields of SynthConfig (generated)."""
from rsl_cli.options import stage_command

register = stage_command("synth")
