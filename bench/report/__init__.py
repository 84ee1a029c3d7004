"""The accuracy, speed and stability report (``python -m bench.report``), one module per section."""
