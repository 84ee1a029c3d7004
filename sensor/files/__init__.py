"""Files: our HDF5 recording format (``recording``)."""
