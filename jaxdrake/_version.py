"""The version: written here only (pyproject.toml reads it as its dynamic `version`)."""

__version__ = "0.1.0"
