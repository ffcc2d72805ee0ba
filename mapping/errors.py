"""Errors of the mapping package that a user may see."""


class MapFileError(ValueError):
    """A saved map file is foreign, truncated, of another version or made with another model.

    The message is one line naming the file and how to fix the problem.
    """


class WeightsFileError(ValueError):
    """A prior weights file is missing pieces, truncated, foreign or holds more than tensors.

    The message is one line naming the file and how to fix the problem.
    """
