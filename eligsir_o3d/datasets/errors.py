"""The one error every sequence reader raises."""


class DatasetError(ValueError):
    """A sequence that cannot be opened or read. The message names the file (and line or frame index)."""
