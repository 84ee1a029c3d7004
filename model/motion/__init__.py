"""Motion: canonical Gaussians, control points, skinning, the RGB deformation prior, the event branch,
initialisation and leanness decisions."""
