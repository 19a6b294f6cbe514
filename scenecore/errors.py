"""Errors shared by the kernel's modules (kept apart so the modules that raise them need not import each other)."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset file is missing or malformed. The message names the file and the problem."""


class ExportFormatError(ValueError):
    """An export directory is malformed, incomplete or of another version (message says which file)."""
