"""invrender: single-image inverse rendering of indoor scenes (see DESIGN.md)."""

__version__ = "0.1.0"
