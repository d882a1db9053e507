"""Everything that imports napari or Qt: readers, writer, sample, the Auto-label widget."""
