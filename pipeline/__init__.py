"""invrender: single-image inverse rendering of indoor scenes (see docs/design.md)."""

__version__ = "0.1.0"
