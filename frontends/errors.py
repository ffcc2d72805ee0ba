"""The one exception type a user sees for bad input data."""


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or inconsistent.

    The message is a single line that names the offending file or folder and says how to fix it.
    """


class OdometryProcessError(RuntimeError):
    """The odometry's child process died or stopped answering.

    The message is a single line that says what happened and what to do.
    """
