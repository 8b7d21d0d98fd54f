"""tagloc: real-time localisation of people in robotised warehouses from floor stickers."""

from tagloc.core.errors import TaglocError

__all__ = ["TaglocError", "__version__"]
__version__ = "0.1.0"
