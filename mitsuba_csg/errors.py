"""The exceptions users see. Each message names the place: the node, the file, the field."""


class CSGError(Exception):
    """Base class of every error mitsuba-csg raises on bad input."""

    # A message quotes names and values from the input, which may be a megabyte long: past
    # this many characters its middle is left out (the place comes first, the reason last).
    MAX_MESSAGE = 2000

    def __init__(self, *args):
        if len(args) == 1 and isinstance(args[0], str) and len(args[0]) > self.MAX_MESSAGE:
            text = args[0]
            left_out = len(text) - 1500
            args = (f"{text[:1100]} ... ({left_out} characters left out) ... {text[-400:]}",)
        super().__init__(*args)


class ModelError(CSGError, ValueError):
    """An invalid model: bad primitive parameter, singular transform, empty operation."""


class TreeTooDeepError(ModelError):
    """The tree needs a deeper traversal stack than the kernel allows; optimize it first."""
