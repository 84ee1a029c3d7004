"""Files: our HDF5 recording format, atomic writes and ``edmcgs record``."""
