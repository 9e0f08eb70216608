"""The project's own error type: the CLI prints it as one line, without a traceback."""


class NerfError(Exception):
    """An error the user can act on; the message names the file and what is wrong."""


class DatasetError(NerfError):
    """A dataset on disk is malformed or incomplete."""


class RunError(NerfError):
    """A run folder is missing, locked, or would be overwritten."""
