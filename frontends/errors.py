"""The one exception type a user sees for bad input data."""


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or inconsistent.

    The message is a single line that names the offending file or folder and says how to fix it.
    """
