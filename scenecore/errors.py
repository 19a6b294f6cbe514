"""Errors shared by the kernel's modules (kept apart so the modules that raise them need not import each other)."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset file is missing or malformed. The message names the file and the problem."""


class ExportFormatError(ValueError):
    """An export directory is malformed, incomplete or of another version (message says which file)."""


class EmptyValidSet(ExportFormatError):
    """The scale network accepts no configuration that a search finds: the learned valid set is
    empty, or too small for the draws made. A result of training, not a malformed file."""
