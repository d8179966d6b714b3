"""The media stage's error, in a module of its own: the builder raises it, and so does the Dask cluster that the
builder uses (:mod:`server.media.cluster`), which the builder imports."""


class MediaError(ValueError):
    """The clip set to render is missing or inconsistent."""
