"""The neutral case layer: case files, the mechanisms they describe, generated families,
MJCF import."""
