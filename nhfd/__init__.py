"""nhfd: neural holographic fields on a holographic display bench."""

__version__ = "0.1.0"
