"""What the tests, the benchmarks and the scripts share: a real ``edmcgs-serve`` in a subprocess and a
local Ray Serve (``server``, ``ray_serve``), reference scenes (``scenes``, ``pose_scenes``). Not
installed; it imports only ``edmcgs``. Test-only helpers stay in ``tests/support``."""
