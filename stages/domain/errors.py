"""The exception types that end a stage with a clear message and exit code 1."""


class RslError(Exception):
    """Bad input or a failed stage; the message is one sentence naming the file and the problem."""


class CaptureError(RslError):
    """A capture folder is missing something or holds malformed data."""
