"""The one exception type of the data layer."""


class DatasetError(ValueError):
    """A scene cannot be found, read or generated.

    The message is a single line naming the file, folder or key at fault (and, where it helps,
    what to do), so the CLI can print it as is without a traceback.
    """
