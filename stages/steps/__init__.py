"""The stage modules: one per `rsl` command, each reads artefacts, runs, and writes its own (see stages/registry.py)."""
