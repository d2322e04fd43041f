"""The one exception type that the command line turns into a one-line message."""


class FacesynthError(Exception):
    """A user-facing error: bad input, missing file, mismatched model.

    The message names the file or field and what was expected. The command line
    prints it on one line (``error: ...``) and exits with status 2, without a traceback.
    """


class MissingExtraError(FacesynthError):
    """An optional dependency group is not installed."""

    def __init__(self, extra: str, module: str, install: str | None = None):
        super().__init__(
            f"the '{extra}' extra is needed for this ({module} is not installed): "
            + (install or f"pip install 'facesynth[{extra}]'")
        )


class DiskFullError(FacesynthError):
    """No space left on the device (or quota) while writing ``path``; nothing partial is left."""

    def __init__(self, path):
        self.path = path
        super().__init__(f"no space left on device writing {path if path is not None else '(unknown file)'}")
