"""Readers and writers for image stacks (neuron tables live in :mod:`napari_fdlc.table`)."""

from .images import ImageError, Stack, read_stack

__all__ = ["ImageError", "Stack", "read_stack"]
