"""The exceptions users see. Each message names the place: the node, the file, the field."""


class CSGError(Exception):
    """Base class of every error mitsuba-csg raises on bad input."""


class ModelError(CSGError, ValueError):
    """An invalid model: bad primitive parameter, singular transform, empty operation."""


class TreeTooDeepError(ModelError):
    """The tree needs a deeper traversal stack than the kernel allows; optimize it first."""
