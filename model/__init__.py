"""EdMCGS: cameras and rasterizers, the model (Gaussians, control points, RGB prior, event-driven Markov
transition), its losses, training, evaluation and checkpoints. Knows nothing of where events come from."""
