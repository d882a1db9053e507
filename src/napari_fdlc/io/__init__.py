"""Readers and writers for image stacks (neuron tables live in :mod:`napari_fdlc.table`)."""

from .images import ImageError, Stack, StackSeries, read_series, read_stack

__all__ = ["ImageError", "Stack", "StackSeries", "read_series", "read_stack"]
