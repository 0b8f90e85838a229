"""The rsl command line: typer commands that build a stage Config and call its run()."""
