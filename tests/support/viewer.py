"""What the browser viewer's tests share: where the viewer's files are, and the served scene's size."""

from pathlib import Path

VIEWER = Path(__file__).resolve().parents[2] / "clients" / "viewer"
VIEW_W, VIEW_H = 160, 120
"""The viewer tests' scene, a size worth looking at in a screenshot."""
MAX_SIZE = 200
"""The server's width / height cap in the viewer tests (the page can run into it)."""
