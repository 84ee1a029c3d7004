"""Test support: reference scenes, tiny models, server harnesses. Tests and bench import it; it imports no
test module."""
