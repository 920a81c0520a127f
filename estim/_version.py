"""The version of estim (one place: the package and generated code read it)."""

__version__ = "0.1.0"
