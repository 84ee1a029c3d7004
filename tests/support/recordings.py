"""Recordings the tests share."""

from pathlib import Path

DVXPLORER = Path(__file__).resolve().parents[3] / "shared" / "data" / "dvxplorer_person.aedat4"
"""A real DVXplorer recording (AEDAT4) beside the repository."""
