"""The one exception type that ends a stage with a clear message and exit code 1
(defined in the domain layer, stages/domain/errors.py; re-exported here)."""
from stages.domain.errors import CaptureError, RslError  # noqa: F401


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a stage; the message says what was kept (e.g. the frames saved to adapt.partial.h5)."""
