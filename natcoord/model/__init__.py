"""The natural-coordinate model: points and unit vectors, constant M, quadratic constraints."""
