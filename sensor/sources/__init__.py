"""Event sources: the live camera, AEDAT4 and HDF5 replays, what every replay shares, and pacing."""
