"""The sparse two-level TSDF map: container, building, file format, import and export."""
