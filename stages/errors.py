"""The one exception type that ends a stage with a clear message and exit code 1
(defined in the domain layer, stages/domain/errors.py; re-exported here)."""
from stages.domain.errors import CaptureError, RslError  # noqa: F401


class Interrupted(RslError):
    """Ctrl-C ended a stage, which kept what it had (the message says what and where); exit code 130.

    Not a KeyboardInterrupt: the command-line layer (typer) turns those into a bare exit code, and the
    sentence saying what was kept would be lost."""
