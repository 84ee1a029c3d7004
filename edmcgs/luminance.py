"""What an event pixel sees of an image: its luminance, on a log scale. Shared by the model, the
simulator and the baselines, so that each turns colour into events the same way."""

LUMA = (0.299, 0.587, 0.114)
"""Rec. 601 weights of R, G, B in the luminance (OpenCV's RGB2GRAY, as ESIM uses them)."""

LOG_EPS = 1e-3
"""The offset of the log intensity, log(I + eps) with I in [0, 1]: the simulator's and the model's."""
